"""Demonstration data: the expert motion planner and (elsewhere) dataset writers."""
