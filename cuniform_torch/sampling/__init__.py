"""Sampling trajectories: the Policy and ActionSampler protocols, batched rollouts, Gaussian noise samplers, the start check."""

from cuniform_torch.sampling.noise import GaussianSampler, NormalLogNormalSampler, lognormal_params
from cuniform_torch.sampling.rollout import ActionSampler, Policy, PolicyTraits, rollout, rollout_actions
from cuniform_torch.sampling.start_watch import StartMismatchWarning

__all__ = [
    "rollout", "rollout_actions", "Policy", "ActionSampler", "PolicyTraits", "StartMismatchWarning",
    "GaussianSampler", "NormalLogNormalSampler", "lognormal_params",
]
