"""Controllers: the one MPPI core (:class:`MPPICore`) and its plug-in, the :class:`Proposal`; the MPPI family
built on them (:class:`MPPI`, :class:`LogMPPI`, :class:`CUniformMPPI`, :class:`CUMPPI`), CFU-MPPI
(:class:`CFUMPPI`, a map policy sensing the world), the samplers MPC users switch to (:class:`ColoredMPPI`,
:class:`LowPassMPPI`, :class:`SmoothMPPI`, :class:`KernelMPPI`) and mixtures of proposals (:class:`MixtureMPPI`,
:class:`CUniformMixtureMPPI`); pytorch_mppi's convention on them (:class:`DynamicsSystem`, :class:`RunningCost`,
:class:`CallableProposal`) and the automatic temperature (:func:`auto_temperature`)."""

from cuniform_torch.controllers.bank import BankProposal, BankRefreshWarning
from cuniform_torch.controllers.callables import CallableProposal, DynamicsSystem, RunningCost
from cuniform_torch.controllers.cfu import CFUMPPI, MapSensor
from cuniform_torch.controllers.core import COST_CAP, CostFn, MPPICore, mppi_weights
from cuniform_torch.controllers.filtered import ColoredMPPI, LowPassMPPI
from cuniform_torch.controllers.mixture import CUniformMixtureMPPI, MixtureMPPI, MixtureProposal
from cuniform_torch.controllers.mppi import CUMPPI, MPPI, CUniformMPPI, LogMPPI
from cuniform_torch.controllers.proposals import (
    CompositeProposal,
    GaussianProposal,
    NormalLogNormalProposal,
    PolicyProposal,
    Proposal,
    default_noise_std,
)
from cuniform_torch.controllers.result import MPPIResult
from cuniform_torch.controllers.smooth import KernelMPPI, SmoothMPPI
from cuniform_torch.controllers.temperature import auto_temperature

__all__ = [
    "MPPICore", "MPPIResult", "CostFn", "mppi_weights", "COST_CAP",
    "MPPI", "LogMPPI", "CUniformMPPI", "CUMPPI", "CFUMPPI", "MapSensor", "ColoredMPPI", "LowPassMPPI",
    "SmoothMPPI", "KernelMPPI", "MixtureMPPI", "CUniformMixtureMPPI", "MixtureProposal",
    "Proposal", "GaussianProposal", "NormalLogNormalProposal", "PolicyProposal", "BankProposal", "CompositeProposal",
    "BankRefreshWarning", "DynamicsSystem", "RunningCost", "CallableProposal", "auto_temperature", "default_noise_std",
]
