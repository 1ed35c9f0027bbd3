"""Closed-loop MountainCarContinuous-v0 (gymnasium) under MPPI, pytorch_mppi and C-Uniform controllers."""
