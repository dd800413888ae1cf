"""Evaluation: the episode loop with simulated users, goals, prediction, planning and the shared-control benchmark."""
