"""The methods every experiment compares, as data: one :class:`Method` entry per method in :data:`METHODS`.

A method is a small frozen dataclass: its key and label, the paper column it belongs to, the controller class
that proposes with it, what its proposals are drawn from (a noise law around a nominal, or a *source*: a table,
the distilled MLP, uniform actions, the flow graph) and its colour in figures. :func:`make_controller` and
:func:`sample_states` read only these fields, so adding a method is adding one entry. :class:`Sources` holds
the files the sources come from, loaded once.

Baselines sample around a zero nominal (a first solve). Method keys:

* ``mppi_low|medium|high``: Gaussian noise, std 0.03 / 0.1 / 0.3 rad/s, clipped to the action bounds;
* ``log_mppi_low|medium|high``: normal x log-normal noise (log-normal factor of mean 1, variance 1);
* ``uniform``: uniform random discrete actions (the table's action set);
* ``cu_table``: C-Uniform table policy (max-flow, the paper's method) on real rollouts;
* ``cu_coverage``: the coverage-method table (``--method coverage``) on real rollouts;
* ``cu_mlp``: the MLP distilled from the max-flow table, on real rollouts;
* ``cu_graph``: cell sequences drawn on the max-flow graph in proportion to arc flow (the reference release's
  way; not executed dynamics, see :mod:`eval.common.graph_sampling`). Open-loop only;
* ``cumppi``: CU-MPPI (best C-Uniform rollout of the max-flow table seeds a local MPPI pass). Closed-loop only.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from cuniform_torch import (
    CUMPPI,
    MPPI,
    CUniformMPPI,
    LogMPPI,
    TablePolicy,
    load_map_policy,
    load_policy,
    load_table,
    read_table,
    rollout,
)
from cuniform_torch.policies import UniformPolicy
from cuniform_torch.sampling import GaussianSampler, NormalLogNormalSampler
from eval.common import config
from eval.common.graph_sampling import GraphSampler
from eval.common.paths import DEFAULT

__all__ = ["Method", "METHODS", "SOURCES", "parse_methods", "Sources", "sample_states", "make_controller"]

SOURCES = ("table", "coverage_table", "policy", "uniform", "graph", "map_policy")
"""what a method's proposals can be drawn from (:meth:`Sources.load`)"""


@dataclass(frozen=True)
class Method:
    """One compared method (see the module docstring)."""

    key: str
    label: str
    family: str
    """the paper's column: "mppi", "log_mppi" or "cuniform" (or "uniform", ours)"""
    controller: type | None = None
    """the MPPI-family class that proposes with this method (None: open-loop only)"""
    noise: type | None = None
    """a noise baseline's open-loop law (``GaussianSampler``, ``NormalLogNormalSampler``), std ``noise_std``"""
    noise_std: float | None = None
    source: str | None = None
    """a C-Uniform or uniform method's proposals: one of :data:`SOURCES`"""
    open_loop: bool = True
    """it draws open-loop trajectories (coverage, uniformity, trajectory fans)"""
    slow: bool = False
    """left out of a default closed-loop run unless asked for (see :data:`eval.paper.episodes.SLOW_NOTE`)"""
    paper: bool = False
    """the paper's own method of its column (its C-Uniform column is ours)"""
    color: str = "black"
    linestyle: str = "-"

    def __post_init__(self) -> None:
        if (self.noise is None) == (self.source is None):
            raise ValueError(f"method {self.key}: give a noise law or a source, not both or neither")
        if self.source is not None and self.source not in SOURCES:
            raise ValueError(f"method {self.key}: unknown source {self.source!r}; choose from {', '.join(SOURCES)}")

    @property
    def closed_loop(self) -> bool:
        return self.controller is not None


_SHADES = {"mppi": {"low": "#9ecae1", "medium": "#4292c6", "high": "#08519c"},  # darker = more noise
           "log_mppi": {"low": "#fdae6b", "medium": "#f16913", "high": "#a63603"}}

METHODS: dict[str, Method] = {m.key: m for m in [
    *(Method(f"mppi_{lvl}", f"MPPI {lvl} (std {s:g})", "mppi", MPPI, GaussianSampler, s, color=_SHADES["mppi"][lvl])
      for lvl, s in config.NOISE_LEVELS.items()),
    *(Method(f"log_mppi_{lvl}", f"log-MPPI {lvl} (std {s:g})", "log_mppi", LogMPPI, NormalLogNormalSampler, s,
             color=_SHADES["log_mppi"][lvl]) for lvl, s in config.NOISE_LEVELS.items()),
    Method("uniform", "uniform discrete actions", "uniform", CUniformMPPI, source="uniform", color="#737373"),
    Method("cu_table", "C-Uniform table (max-flow)", "cuniform", CUniformMPPI, source="table", paper=True,
           color="#2ca02c"),
    Method("cu_coverage", "C-Uniform table (coverage method)", "cuniform", CUniformMPPI, source="coverage_table",
           color="#d62728"),
    Method("cu_mlp", "C-Uniform distilled MLP", "cuniform", CUniformMPPI, source="policy", slow=True, color="#9467bd"),
    Method("cu_graph", "C-Uniform graph sampling (cells, not executed)", "cuniform", source="graph",
           color="#8c564b", linestyle="--"),
    Method("cumppi", "CU-MPPI (max-flow table)", "cuniform", CUMPPI, source="table", open_loop=False,
           color="#e377c2"),
]}


def parse_methods(keys: list[str] | tuple[str, ...] | None, closed_loop: bool = False) -> list[Method]:
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
    """The files the methods' sources come from, each loaded once, when first used."""

    table: Path = DEFAULT.table
    """the max-flow table: also the system, grid and horizon of an experiment"""
    coverage_table: Path = DEFAULT.coverage_table
    policy: Path = DEFAULT.policy
    map_policy: Path | None = None
    """a map-conditioned policy (``python -m training.maps.distill``), for CFU-MPPI"""
    device: str = "cpu"
    _cache: dict = field(default_factory=dict, repr=False)

    def file_of(self, source: str) -> Path:
        """The file ``source`` is read from."""
        return {"coverage_table": self.coverage_table, "policy": self.policy,
                "map_policy": self.map_policy}.get(source, self.table)

    def load(self, source: str) -> Any:
        """The object a source names: a TablePolicy (``table``, ``coverage_table``), an MLPPolicy (``policy``), a
        UniformPolicy over the table's actions (``uniform``), a GraphSampler (``graph``)."""
        if source not in self._cache:
            loaders: dict[str, Callable[[Path], Any]] = {
                "table": lambda p: load_table(p, device=self.device),
                "coverage_table": lambda p: load_table(p, device=self.device),
                "policy": lambda p: load_policy(p, device=self.device),
                "uniform": lambda p: UniformPolicy(self.system, horizon=None, device=self.device),
                "graph": lambda p: GraphSampler(read_table(p), device=self.device),  # with the flow graph
                "map_policy": lambda p: load_map_policy(p, device=self.device),
            }
            path = self.file_of(source)
            if path is None:
                raise FileNotFoundError(f"{source}: no file given (--map-policy FILE; python -m training.maps.distill "
                                        "trains one)")
            if not Path(path).exists():
                raise FileNotFoundError(f"{source} file {path} not found (python -m eval.report builds it)")
            self._cache[source] = loaders[source](path)
        return self._cache[source]

    def table_policy(self) -> TablePolicy:
        return self.load("table")

    @property
    def system(self):
        return self.table_policy().system

    @property
    def horizon(self) -> int:
        return self.table_policy().horizon


def _noise_sampler(method: Method, system, horizon: int, device: str):
    actions = system.action_set(dtype=torch.float32, device=device)  # [A, q]
    low, high = actions.min(dim=0).values, actions.max(dim=0).values
    nominal = torch.zeros((horizon, actions.shape[1]), device=device)
    return method.noise(nominal, method.noise_std, low, high)


def sample_states(method: Method, sources: Sources, num_samples: int, horizon: int,
                  generator: torch.Generator) -> Tensor:
    """``[N, T+1, d]`` open-loop trajectories of ``method`` from the origin (float32, on the sources' device)."""
    if method.source == "graph":  # cell sequences, not a rollout
        return sources.load("graph").sample(num_samples, horizon, generator)
    system = sources.system
    x0 = torch.zeros(len(system.periodic), device=sources.device)
    if method.source is None:
        sampler = _noise_sampler(method, system, horizon, sources.device)
    else:
        sampler = sources.load(method.source)
    return rollout(system, sampler, x0, num_samples, horizon, generator)[0]


def make_controller(method: Method, sources: Sources, cost_fn, num_samples: int, horizon: int,
                    seed: int, lambda_: float = config.LAMBDA, world: Any = None, max_range: float | None = None):
    """The MPPI-family controller that proposes with ``method`` (``command(state) -> [q]``); a map-conditioned
    method (source ``map_policy``) senses ``world`` within ``max_range`` (m) at each command."""
    if not method.closed_loop:
        raise ValueError(f"{method.key} samples cells, not executable actions: it has no controller")
    kw = dict(num_samples=num_samples, horizon=horizon, lambda_=lambda_, device=sources.device, seed=seed)
    if method.source is None:  # a noise baseline: the system and the noise level
        return method.controller(sources.system, cost_fn, noise_std=method.noise_std, **kw)
    if method.source == "map_policy":
        if world is None:
            raise ValueError(f"{method.key} senses a world map: give world=")
        return method.controller(sources.load(method.source), world, cost_fn, max_range=max_range, **kw)
    return method.controller(sources.load(method.source), cost_fn, **kw)
