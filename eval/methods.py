"""The methods every experiment compares, as one registry: open-loop samples and closed-loop controllers.

A :class:`Method` names a way to propose trajectories; :class:`Sources` holds what the C-Uniform methods need
(tables, the distilled MLP), loaded once. :func:`sample_states` draws N open-loop trajectories from the
origin (coverage, uniformity, trajectory fans); :func:`make_controller` builds the MPPI-family controller that
uses the method's proposals (sudden obstacle, cluttered environments).

Baselines sample around a zero nominal (a first solve). Method keys:

* ``mppi_low|medium|high``: Gaussian noise, std 0.03 / 0.1 / 0.3 rad/s, clipped to the action bounds;
* ``log_mppi_low|medium|high``: normal x log-normal noise (log-normal factor of mean 1, variance 1);
* ``uniform``: uniform random discrete actions (the table's action set);
* ``cu_table``: C-Uniform table policy (max-flow, the paper's method) on real rollouts;
* ``cu_coverage``: the coverage-method table (``--method coverage``) on real rollouts;
* ``cu_mlp``: the MLP distilled from the max-flow table, on real rollouts;
* ``cu_graph``: cell sequences drawn on the max-flow graph in proportion to arc flow (the reference release's
  way; not executed dynamics, see :mod:`cuniform_torch.graph`). Open-loop only;
* ``cumppi``: CU-MPPI (best C-Uniform rollout of the max-flow table seeds a local MPPI pass). Closed-loop only.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from cuniform_torch import (CUMPPI, MPPI, CUniformMPPI, GaussianSampler, LogMPPI, NormalLogNormalSampler,
                            TablePolicy, UniformPolicy, load_policy, load_table, read_table, rollout)
from cuniform_torch.graph import GraphSampler

from . import config


@dataclass(frozen=True)
class Method:
    key: str
    label: str
    family: str
    """"mppi", "log_mppi", "uniform" or "cuniform" (the paper's three columns plus uniform)"""
    noise_std: float | None = None
    open_loop: bool = True
    closed_loop: bool = True


METHODS: dict[str, Method] = {m.key: m for m in [
    *(Method(f"mppi_{lvl}", f"MPPI {lvl} (std {s:g})", "mppi", s) for lvl, s in config.NOISE_LEVELS.items()),
    *(Method(f"log_mppi_{lvl}", f"log-MPPI {lvl} (std {s:g})", "log_mppi", s) for lvl, s in config.NOISE_LEVELS.items()),
    Method("uniform", "uniform discrete actions", "uniform"),
    Method("cu_table", "C-Uniform table (max-flow)", "cuniform"),
    Method("cu_coverage", "C-Uniform table (coverage method)", "cuniform"),
    Method("cu_mlp", "C-Uniform distilled MLP", "cuniform"),
    Method("cu_graph", "C-Uniform graph sampling (cells, not executed)", "cuniform", closed_loop=False),
    Method("cumppi", "CU-MPPI (max-flow table)", "cuniform", open_loop=False),
]}


def parse_methods(keys: list[str] | None, closed_loop: bool = False) -> list[Method]:
    """Methods by key (None: every method that applies); an unknown key lists the known ones."""
    usable = [m for m in METHODS.values() if (m.closed_loop if closed_loop else m.open_loop)]
    if keys is None:
        return usable
    known = {m.key: m for m in usable}
    unknown = [k for k in keys if k not in known]
    if unknown:
        raise ValueError(f"unknown method(s) {', '.join(unknown)}; choose from {', '.join(known)}")
    return [known[k] for k in keys]


@dataclass
class Sources:
    """Tables and the distilled policy the C-Uniform methods draw on, loaded lazily from their paths."""

    table: Path = config.TABLE
    coverage_table: Path = config.COVERAGE_TABLE
    policy: Path = config.POLICY
    device: str = "cpu"
    _cache: dict = field(default_factory=dict, repr=False)

    def _load(self, key: str, loader, path: Path):
        if key not in self._cache:
            if not Path(path).exists():
                raise FileNotFoundError(f"{key} file {path} not found (python -m eval.report builds it)")
            self._cache[key] = loader(path)
        return self._cache[key]

    def table_policy(self) -> TablePolicy:
        return self._load("table", lambda p: load_table(p, device=self.device), self.table)

    def coverage_policy(self) -> TablePolicy:
        return self._load("coverage_table", lambda p: load_table(p, device=self.device), self.coverage_table)

    def mlp_policy(self):
        return self._load("policy", lambda p: load_policy(p, device=self.device), self.policy)

    def graph(self) -> GraphSampler:
        # read again with the flow graph, which the table policy leaves in the file
        return self._load("graph", lambda p: GraphSampler(read_table(p), device=self.device), self.table)

    def policy_for(self, method: Method):
        """The discrete Policy behind a C-Uniform or uniform method."""
        if method.key in ("cu_table", "cumppi"):
            return self.table_policy()
        if method.key == "cu_coverage":
            return self.coverage_policy()
        if method.key == "cu_mlp":
            return self.mlp_policy()
        if method.key == "uniform":
            base = self.table_policy()
            return UniformPolicy(base.system, horizon=None, device=self.device)
        raise ValueError(f"{method.key} has no discrete policy")

    @property
    def system(self):
        return self.table_policy().system

    @property
    def horizon(self) -> int:
        return self.table_policy().horizon


def sample_states(method: Method, sources: Sources, num_samples: int, horizon: int,
                  generator: torch.Generator) -> Tensor:
    """``[N, T+1, d]`` open-loop trajectories of ``method`` from the origin (float32, on the sources' device)."""
    system = sources.system
    d = len(system.periodic)
    x0 = torch.zeros(d, device=sources.device)
    if method.key == "cu_graph":
        return sources.graph().sample(num_samples, horizon, generator)
    if method.family in ("mppi", "log_mppi"):
        actions = system.action_set(dtype=torch.float32, device=sources.device)  # [A, q]
        low, high = actions.min(dim=0).values, actions.max(dim=0).values
        nominal = torch.zeros((horizon, actions.shape[1]), device=sources.device)
        cls = GaussianSampler if method.family == "mppi" else NormalLogNormalSampler
        sampler = cls(nominal, method.noise_std, low, high)
        return rollout(system, sampler, x0, num_samples, horizon, generator)[0]
    return rollout(system, sources.policy_for(method), x0, num_samples, horizon, generator)[0]


def make_controller(method: Method, sources: Sources, cost_fn, num_samples: int, horizon: int,
                    seed: int, lambda_: float = config.LAMBDA):
    """The MPPI-family controller that proposes with ``method`` (``command(state) -> [q]``)."""
    if not method.closed_loop:
        raise ValueError(f"{method.key} samples cells, not executable actions: it has no controller")
    system = sources.system
    kw = dict(num_samples=num_samples, lambda_=lambda_, device=sources.device, seed=seed)
    if method.family == "mppi":
        return MPPI(system, cost_fn, horizon=horizon, noise_std=method.noise_std, **kw)
    if method.family == "log_mppi":
        return LogMPPI(system, cost_fn, horizon=horizon, noise_std=method.noise_std, **kw)
    if method.key == "cumppi":
        return CUMPPI(sources.policy_for(method), cost_fn, horizon=horizon, **kw)
    return CUniformMPPI(sources.policy_for(method), cost_fn, horizon=horizon, **kw)
