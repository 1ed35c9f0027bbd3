"""Controllers: the one MPPI core (:class:`MPPICore`) and its plug-in, the :class:`Proposal`; the MPPI family
built on them (:class:`MPPI`, :class:`LogMPPI`, :class:`CUniformMPPI`, :class:`CUMPPI`) and CFU-MPPI
(:class:`CFUMPPI`, a map policy sensing the world)."""

from cuniform_torch.controllers.bank import BankProposal, BankRefreshWarning
from cuniform_torch.controllers.cfu import CFUMPPI, SensedMapPolicy
from cuniform_torch.controllers.core import COST_CAP, CostFn, MPPICore, mppi_weights
from cuniform_torch.controllers.filtered import ColoredMPPI, LowPassMPPI
from cuniform_torch.controllers.mppi import CUMPPI, MPPI, CUniformMPPI, LogMPPI
from cuniform_torch.controllers.proposals import (
    CompositeProposal,
    GaussianProposal,
    NormalLogNormalProposal,
    PolicyProposal,
    Proposal,
)
from cuniform_torch.controllers.result import MPPIResult

__all__ = [
    "MPPICore", "MPPIResult", "CostFn", "mppi_weights", "COST_CAP",
    "MPPI", "LogMPPI", "CUniformMPPI", "CUMPPI", "CFUMPPI", "SensedMapPolicy", "ColoredMPPI", "LowPassMPPI",
    "Proposal", "GaussianProposal", "NormalLogNormalProposal", "PolicyProposal", "BankProposal", "CompositeProposal",
    "BankRefreshWarning",
]
