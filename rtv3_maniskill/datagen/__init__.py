"""Demonstration data: planner demonstrations, the generate runner, DAgger, LeRobot export, merge and Hub upload."""
