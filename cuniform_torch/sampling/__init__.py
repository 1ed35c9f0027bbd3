"""Sampling trajectories: the Policy and ActionSampler protocols, batched rollouts, Gaussian noise samplers, the start check."""
