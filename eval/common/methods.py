"""The methods every benchmark compares, as data: one :class:`Method` entry per method in :data:`METHODS`.

A method is a small frozen dataclass: its key and label, the paper column it belongs to, the controller class
that proposes with it, what its proposals are drawn from (a noise law around a nominal, or a *source*: a table,
the distilled MLP, uniform actions, the flow graph, a map-conditioned policy), its colour in figures and the
benchmarks it belongs to (:data:`BENCHMARKS`). :func:`make_controller` and :func:`sample_states` read only these
fields, so adding a method is adding one entry. A method two benchmarks share is one entry (the same object in
both); :func:`methods_of` is a benchmark's view and :func:`parse_methods` resolves the keys a user types in it.
:class:`Sources` holds the files the sources come from, loaded once.

The paper's experiments (``paper``: :mod:`eval.paper`, :mod:`eval.report`) sample their baselines around a zero
nominal (a first solve), at the paper's noise levels (std 0.03 / 0.1 / 0.3 rad/s, for turn rates in +-pi/4
rad/s). The navigation benchmark's robot (``navigate``: :mod:`eval.navigate`) turns at up to 1.5 rad/s, so its
Gaussian baselines span the range that matters for it, std 0.1, 0.3 and 1.0 rad/s, around the warm-started
nominal. Method keys:

* ``mppi_low|medium|high`` (paper): Gaussian noise, std 0.03 / 0.1 / 0.3 rad/s, clipped to the action bounds;
* ``log_mppi_low|medium|high`` (paper): normal x log-normal noise (log-normal factor of mean 1, variance 1);
* ``mppi_0.1``, ``mppi_0.3``, ``mppi_1.0`` (navigate): MPPI, Gaussian noise of that std, clipped;
* ``log_mppi_0.3`` (navigate): log-MPPI (normal x log-normal noise), std 0.3;
* ``uniform`` (both): uniform random discrete actions (the table's action set) on real rollouts;
* ``cu_table`` (both): C-Uniform table policy (max-flow, the paper's method) on real rollouts;
* ``cu_coverage`` (both): the coverage-method table (``--method coverage``; the navigation benchmark builds it on
  first use, about 80 s for its robot) on real rollouts;
* ``cu_mlp`` (both): the MLP distilled from the max-flow table, on real rollouts (opt-in in navigate: about 10x
  the table's cost per cycle on a CPU, and trained on first use; ``slow`` in the paper's closed loop);
* ``cu_graph`` (paper): cell sequences drawn on the max-flow graph in proportion to arc flow (the reference
  release's way; not executed dynamics, see :mod:`eval.common.graph_sampling`). Open-loop only;
* ``cumppi`` (both): CU-MPPI: the best C-Uniform rollout of the max-flow table seeds a local MPPI pass (half of
  the budget each). Closed-loop only;
* ``mppi_pink_1.0``, ``mppi_lowpass_1.0`` (navigate, opt-in): MPPI with time-correlated noise of std 1.0, pink
  (power spectrum ~ 1/f) or low-pass (AR(1), a = 0.8) (:mod:`cuniform_torch.controllers.filtered`);
* ``smppi_2.0`` (navigate, opt-in): smooth MPPI: noise of std 2.0 rad/s^2 on the turn rate's rate, integrated
  along the horizon from the last command (a sample's deviation at step t: 0.4 sqrt(t + 1) rad/s), with the
  action-sequence cost of weight 1 (:class:`~cuniform_torch.controllers.smooth.SmoothMPPI`);
* ``kmppi_1.0`` (navigate, opt-in): kernel MPPI: noise of std 1.0 on 7 control points, the sequence their RBF
  interpolation (sigma 1 step) (:class:`~cuniform_torch.controllers.smooth.KernelMPPI`);
* ``mix_cu_mppi_0.5`` (navigate, opt-in): a mixture proposal: half of K C-Uniform rollouts of the max-flow table,
  half Gaussian MPPI rollouts (std 1.0) around the warm-started weighted sequence, all weighted together
  (:class:`~cuniform_torch.controllers.mixture.CUniformMixtureMPPI`);
* ``cumppi_pipe`` (navigate, opt-in): CU-MPPI in one pass (``CUMPPI(pipelined=True)``): the local rollouts around
  the previous command's best C-Uniform sequence, rolled out and costed with this command's C-Uniform ones, all
  weighed together;
* ``cfu_mppi`` (navigate): CFU-MPPI: the same with a map-conditioned policy (``--map-policy FILE``, from
  ``python -m training.maps.distill``), which senses the local map at each command within the task's sensing
  range (opt-in: it needs that file). Closed-loop only.

``mppi_1.0`` and the five new proposals above (pink, low-pass, smooth, kernel, mixture) are also opt-in methods of
the paper's open-loop experiments (coverage, uniformity; issue 36), run on the navigation robot's table
(``--table``): their open-loop trajectories are their controller's proposals at its first command
(:attr:`Method.proposal_draws`, :func:`sample_states`).

A benchmark's Gaussian baselines (:func:`gaussian_baselines`) are what every other method is compared with in
the navigation benchmark (the best of them per suite and budget).
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from cuniform_torch import (
    CFUMPPI,
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
from cuniform_torch.common.fileio import MAX_JSON_BYTES, read_capped_text
from cuniform_torch.controllers.filtered import ColoredMPPI, LowPassMPPI
from cuniform_torch.controllers.mixture import CUniformMixtureMPPI
from cuniform_torch.controllers.smooth import KernelMPPI, SmoothMPPI
from cuniform_torch.policies import UniformPolicy
from cuniform_torch.sampling import GaussianSampler, NormalLogNormalSampler
from eval.common import config
from eval.common.graph_sampling import GraphSampler
from eval.common.paths import DEFAULT

__all__ = ["Method", "METHODS", "SOURCES", "BENCHMARKS", "PAPER", "NAVIGATE", "methods_of", "parse_methods",
           "gaussian_baselines", "Sources", "sample_states", "make_controller"]

SOURCES = ("table", "coverage_table", "policy", "uniform", "graph", "map_policy")
"""what a method's proposals can be drawn from (:meth:`Sources.load`)"""

PAPER = "paper"
"""the paper's experiments (:mod:`eval.paper`, :mod:`eval.report`)"""
NAVIGATE = "navigate"
"""the navigation benchmark (:mod:`eval.navigate`)"""
BENCHMARKS = (PAPER, NAVIGATE)
"""what a method can belong to (:attr:`Method.benchmarks`)"""


@dataclass(frozen=True)
class Method:
    """One compared method (see the module docstring)."""

    key: str
    label: str
    """its name in tables and figures (a benchmark may print another: :attr:`labels`)"""
    family: str
    """the paper's column: "mppi", "log_mppi" or "cuniform" (or "uniform", ours)"""
    controller: Callable[..., Any] | None = None
    """the MPPI-family class that proposes with this method (None: open-loop only)"""
    noise: type | None = None
    """a noise baseline's open-loop law (``GaussianSampler``, ``NormalLogNormalSampler``), std ``noise_std``"""
    noise_std: float | None = None
    source: str | None = None
    """a C-Uniform or uniform method's proposals: one of :data:`SOURCES`"""
    open_loop: bool = True
    """it draws open-loop trajectories (coverage, uniformity, trajectory fans)"""
    proposal_draws: bool = False
    """its open-loop trajectories are its controller's own K proposals around a zero nominal (one ``plan`` with a
    zero cost, :func:`sample_states`), not draws of ``noise`` or ``source`` alone: a proposal they cannot express
    (time-correlated noise, a mixture)"""
    slow: bool = False
    """left out of a default closed-loop run unless asked for (see :data:`eval.paper.episodes.SLOW_NOTE`)"""
    paper: bool = False
    """the paper's own method of its column (its C-Uniform column is ours)"""
    color: str = "black"
    linestyle: str = "-"
    benchmarks: tuple[str, ...] = ()
    """the benchmarks it belongs to (of :data:`BENCHMARKS`): where a user can name its key"""
    labels: tuple[tuple[str, str], ...] = ()
    """``(benchmark, label)`` pairs: a benchmark that prints another label than :attr:`label` (its records,
    tables and figures keep the label they always had)"""
    opt_in: tuple[str, ...] = ()
    """the benchmarks whose default run (no keys given) leaves it out: a user names it to run it"""

    def __post_init__(self) -> None:
        if (self.noise is None) == (self.source is None):
            raise ValueError(f"method {self.key}: give a noise law or a source, not both or neither")
        if self.source is not None and self.source not in SOURCES:
            raise ValueError(f"method {self.key}: unknown source {self.source!r}; choose from {', '.join(SOURCES)}")
        if self.proposal_draws and (self.controller is None or not self.open_loop):
            raise ValueError(f"method {self.key}: proposal_draws needs a controller and open_loop")
        if not self.benchmarks:
            raise ValueError(f"method {self.key}: give the benchmark(s) it belongs to, of {', '.join(BENCHMARKS)}")
        named = {"benchmarks": self.benchmarks, "labels": tuple(b for b, _ in self.labels), "opt_in": self.opt_in}
        for what, names in named.items():
            bad = [b for b in names if b not in BENCHMARKS or (what != "benchmarks" and b not in self.benchmarks)]
            if bad:
                raise ValueError(f"method {self.key}: {what} names {', '.join(map(repr, bad))}, not one of its "
                                 f"benchmarks ({', '.join(self.benchmarks)}) of {', '.join(BENCHMARKS)}")

    @property
    def closed_loop(self) -> bool:
        return self.controller is not None

    def label_in(self, benchmark: str) -> str:
        """The label ``benchmark`` prints for this method."""
        return dict(self.labels).get(benchmark, self.label)


_SHADES = {"mppi": {"low": "#9ecae1", "medium": "#4292c6", "high": "#08519c"},  # darker = more noise
           "log_mppi": {"low": "#fdae6b", "medium": "#f16913", "high": "#a63603"}}
_BLUES = {0.1: "#9ecae1", 0.3: "#4292c6", 1.0: "#08306b"}
_NAV_NOISE = (0.1, 0.3, 1.0)
"""the navigation benchmark's Gaussian stds (rad/s; module docstring)"""
_BOTH = (PAPER, NAVIGATE)

METHODS: dict[str, Method] = {m.key: m for m in [
    *(Method(f"mppi_{lvl}", f"MPPI {lvl} (std {s:g})", "mppi", MPPI, GaussianSampler, s, color=_SHADES["mppi"][lvl],
             benchmarks=(PAPER,)) for lvl, s in config.NOISE_LEVELS.items()),
    *(Method(f"log_mppi_{lvl}", f"log-MPPI {lvl} (std {s:g})", "log_mppi", LogMPPI, NormalLogNormalSampler, s,
             color=_SHADES["log_mppi"][lvl], benchmarks=(PAPER,)) for lvl, s in config.NOISE_LEVELS.items()),
    *(Method(f"mppi_{s:.1f}", f"MPPI (std {s:.1f})", "mppi", MPPI, GaussianSampler, s, color=_BLUES[s],
             benchmarks=(NAVIGATE,)) for s in _NAV_NOISE[:2]),
    # std 1.0 is also the white-noise peer of the time-correlated proposals in the paper's open-loop experiments
    Method("mppi_1.0", "MPPI (std 1.0)", "mppi", MPPI, GaussianSampler, 1.0, color=_BLUES[1.0], benchmarks=_BOTH,
           opt_in=(PAPER,)),
    Method("log_mppi_0.3", "log-MPPI (std 0.3)", "log_mppi", LogMPPI, NormalLogNormalSampler, 0.3, color="#f16913",
           benchmarks=(NAVIGATE,)),
    Method("mppi_pink_1.0", "MPPI, pink noise (std 1.0)", "mppi", ColoredMPPI, GaussianSampler, 1.0,
           proposal_draws=True, color="#6a51a3", benchmarks=_BOTH, opt_in=_BOTH),
    Method("mppi_lowpass_1.0", "MPPI, low-pass noise (std 1.0, a 0.8)", "mppi", LowPassMPPI, GaussianSampler, 1.0,
           proposal_draws=True, color="#807dba", benchmarks=_BOTH, opt_in=_BOTH),
    Method("smppi_2.0", "smooth MPPI (rate std 2.0 rad/s^2)", "mppi", SmoothMPPI, GaussianSampler, 2.0,
           proposal_draws=True, color="#54278f", benchmarks=_BOTH, opt_in=_BOTH),
    Method("kmppi_1.0", "kernel MPPI (7 control points, std 1.0)", "mppi", KernelMPPI, GaussianSampler, 1.0,
           proposal_draws=True, color="#9e9ac8", benchmarks=_BOTH, opt_in=_BOTH),
    Method("uniform", "uniform discrete actions", "uniform", CUniformMPPI, source="uniform", color="#737373",
           benchmarks=_BOTH),
    Method("cu_table", "C-Uniform table (max-flow)", "cuniform", CUniformMPPI, source="table", paper=True,
           color="#2ca02c", benchmarks=_BOTH, labels=((NAVIGATE, "C-Uniform (max-flow table)"),)),
    Method("cu_coverage", "C-Uniform table (coverage method)", "cuniform", CUniformMPPI, source="coverage_table",
           color="#d62728", benchmarks=_BOTH, labels=((NAVIGATE, "C-Uniform (coverage table)"),)),
    Method("cu_mlp", "C-Uniform distilled MLP", "cuniform", CUniformMPPI, source="policy", slow=True, color="#9467bd",
           benchmarks=_BOTH, labels=((NAVIGATE, "C-Uniform (distilled MLP)"),), opt_in=(NAVIGATE,)),
    Method("cu_graph", "C-Uniform graph sampling (cells, not executed)", "cuniform", source="graph",
           color="#8c564b", linestyle="--", benchmarks=(PAPER,)),
    Method("cumppi", "CU-MPPI (max-flow table)", "cuniform", CUMPPI, source="table", open_loop=False,
           color="#e377c2", benchmarks=_BOTH),
    Method("cumppi_pipe", "CU-MPPI in one pass (max-flow table)", "cuniform", functools.partial(CUMPPI, pipelined=True),
           source="table", open_loop=False, color="#c51b8a", benchmarks=(NAVIGATE,), opt_in=(NAVIGATE,)),
    Method("mix_cu_mppi_0.5", "mixture: half C-Uniform table, half MPPI std 1.0", "cuniform",
           functools.partial(CUniformMixtureMPPI, cuniform_fraction=0.5, noise_std=1.0), source="table",
           proposal_draws=True, color="#74c476", benchmarks=_BOTH, opt_in=_BOTH),
    Method("cfu_mppi", "CFU-MPPI (map-conditioned policy)", "cuniform", CFUMPPI, source="map_policy",
           open_loop=False, color="#17becf", benchmarks=(NAVIGATE,), opt_in=(NAVIGATE,)),
]}
"""every method of every benchmark, by key (a key names one method in all the benchmarks it belongs to)"""


def _check_benchmark(benchmark: str) -> None:
    if benchmark not in BENCHMARKS:
        raise ValueError(f"unknown benchmark {benchmark!r}; choose from {', '.join(BENCHMARKS)}")


def methods_of(benchmark: str) -> dict[str, Method]:
    """The methods of ``benchmark`` (of :data:`BENCHMARKS`), by key, in :data:`METHODS`' order (read at each call,
    so an entry added to :data:`METHODS` shows)."""
    _check_benchmark(benchmark)
    return {k: m for k, m in METHODS.items() if benchmark in m.benchmarks}


def parse_methods(keys: Sequence[str] | None, *, benchmark: str, closed_loop: bool) -> list[Method]:
    """The methods of ``benchmark`` named by ``keys``, among those that run closed-loop (``closed_loop``) or draw
    open-loop trajectories (not ``closed_loop``); None: every such method but the benchmark's opt-in ones.

    An unknown key (or one of another benchmark) lists the known ones; a key named twice is refused."""
    usable = {k: m for k, m in methods_of(benchmark).items() if (m.closed_loop if closed_loop else m.open_loop)}
    if keys is None:
        return [m for m in usable.values() if benchmark not in m.opt_in]
    keys = list(keys)
    unknown = [k for k in keys if k not in usable]
    if unknown:
        raise ValueError(f"unknown method(s) {', '.join(unknown)}; choose from {', '.join(usable)}")
    if len(set(keys)) != len(keys):
        raise ValueError(f"a method is named twice in {keys}")
    return [usable[k] for k in keys]


def gaussian_baselines(benchmark: str) -> tuple[str, ...]:
    """The keys of ``benchmark``'s Gaussian-noise MPPI baselines (what the navigation benchmark compares every
    other method with; white noise: the colored and low-pass ones are methods of their own), in :data:`METHODS`'
    order."""
    return tuple(k for k, m in methods_of(benchmark).items() if m.noise is GaussianSampler and m.controller is MPPI)


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

    def file_of(self, source: str) -> Path | None:
        """The file ``source`` is read from (None: no map policy given)."""
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
        """The table's system: from the loaded table when a method has loaded it, else from the table file's
        system JSON alone (a noise baseline needs the system, not the table: loading the table would cost it
        seconds per process for nothing)."""
        if "table" in self._cache:
            return self._cache["table"].system
        if "system" not in self._cache:
            self._cache["system"] = _table_system(self.table)
        return self._cache["system"]

    @property
    def horizon(self) -> int:
        return self.table_policy().horizon


def _table_system(path: Path):
    """The system of the table at ``path`` (a table file or a table set's folder) from its system JSON only: read
    with the bounded reader and rebuilt from the registry (nothing the file names is imported or called)."""
    from cuniform_torch.common.npz import read_npz
    from cuniform_torch.policies.table_set import SET_INDEX
    from cuniform_torch.systems import system_from_json

    path = Path(path)
    if path.is_dir():  # a table set: every member is the same system; the first one says which
        index = json.loads(read_capped_text(path / SET_INDEX, MAX_JSON_BYTES, "the table-set index"))
        path = path / str(index["tables"][0]["file"])
    if not path.is_file():
        raise FileNotFoundError(f"table file {path} not found (python -m eval.report builds it)")
    text = read_npz(path, keys=["system"], expect={"system": ((), None)}, max_bytes=1 << 20)["system"]
    return system_from_json(str(text[()]))[0]


def _noise_sampler(method: Method, system, horizon: int, device: str):
    actions = system.action_set(dtype=torch.float32, device=device)  # [A, q]
    low, high = actions.min(dim=0).values, actions.max(dim=0).values
    nominal = torch.zeros((horizon, actions.shape[1]), device=device)
    if method.noise is None:
        raise ValueError(f"{method.key} draws from the source {method.source!r}, not a noise law")
    return method.noise(nominal, method.noise_std, low, high)


def _zero_cost(states: Tensor, actions: Tensor) -> Tensor:
    """``[N, T+1, d]``, ``[N, T, q]`` -> ``[N]`` zeros: every proposal weighs the same (open-loop draws)."""
    return states.new_zeros(states.shape[0])


def sample_states(method: Method, sources: Sources, num_samples: int, horizon: int,
                  generator: torch.Generator) -> Tensor:
    """``[N, T+1, d]`` open-loop trajectories of ``method`` from the origin (float32, on the sources' device).

    A :attr:`Method.proposal_draws` method's are its controller's N proposals at its first command (zero nominal,
    zero last action): one :meth:`~cuniform_torch.controllers.core.MPPICore.plan` with a zero cost, the controller
    seeded from ``generator`` (so a seed gives the same trajectories)."""
    if method.source == "graph":  # cell sequences, not a rollout
        return sources.load("graph").sample(num_samples, horizon, generator)
    system = sources.system
    x0 = torch.zeros(len(system.periodic), device=sources.device)
    if method.proposal_draws:
        seed = int(torch.randint(0, 2**31 - 1, (), generator=generator, device=generator.device))
        controller = make_controller(method, sources, _zero_cost, num_samples, horizon, seed=seed)
        try:
            return controller.plan(x0).states  # [N, T+1, d]; plan leaves the warm start alone
        finally:
            controller.close()
    if method.source is None:
        sampler = _noise_sampler(method, system, horizon, sources.device)
    else:
        sampler = sources.load(method.source)
    return rollout(system, sampler, x0, num_samples, horizon, generator)[0]


def make_controller(method: Method, sources: Sources, cost_fn, num_samples: int, horizon: int,
                    seed: int | Sequence[int], lambda_: float = config.LAMBDA, world: Any = None,
                    max_range: float | None = None, num_robots: int = 1):
    """The MPPI-family controller that proposes with ``method`` (``command(state) -> [q]``); a map-conditioned
    method (source ``map_policy``) senses ``world`` within ``max_range`` (m) at each command. ``num_robots`` B > 1:
    one controller of B robots (``command(states [B, d]) -> [B, q]``), ``seed`` one int per robot."""
    controller = method.controller
    if controller is None:  # not closed_loop
        raise ValueError(f"{method.key} samples cells, not executable actions: it has no controller")
    kw: dict[str, Any] = dict(num_samples=num_samples, horizon=horizon, lambda_=lambda_, device=sources.device,
                              seed=seed)
    if num_robots != 1:  # only then: a user's controller of one robot need not take it
        kw["num_robots"] = num_robots
    if method.source is None:  # a noise baseline: the system and the noise level
        return controller(sources.system, cost_fn, noise_std=method.noise_std, **kw)
    if method.source == "map_policy":
        if world is None:
            raise ValueError(f"{method.key} senses a world map: give world=")
        return controller(sources.load(method.source), world, cost_fn, max_range=max_range, **kw)
    return controller(sources.load(method.source), cost_fn, **kw)
