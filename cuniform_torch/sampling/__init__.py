"""Sampling trajectories: the policy contract (the Policy and ActionSampler protocols, PolicyCapabilities), batched rollouts, Gaussian noise samplers, the start check."""

from cuniform_torch.sampling.contract import ActionSampler, Policy, PolicyCapabilities, PolicyTraits
from cuniform_torch.sampling.noise import GaussianSampler, NormalLogNormalSampler, lognormal_params
from cuniform_torch.sampling.rollout import rollout, rollout_actions
from cuniform_torch.sampling.start_watch import StartMismatchWarning

__all__ = [
    "rollout", "rollout_actions", "Policy", "ActionSampler", "PolicyTraits", "PolicyCapabilities", "StartMismatchWarning",
    "GaussianSampler", "NormalLogNormalSampler", "lognormal_params",
]
