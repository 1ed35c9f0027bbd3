"""The navigation benchmark's methods, as data (:class:`eval.common.methods.Method` entries), fixed before any run.

The closed-loop experiments' noise levels (std 0.03 / 0.1 / 0.3 rad/s) are the paper's, for turn rates in
+-pi/4 rad/s. The benchmark robot turns at up to 1.5 rad/s, so its Gaussian baselines span the range that
matters for it: std 0.1, 0.3 and 1.0 rad/s (clipped to the action bounds). Method keys:

* ``mppi_0.1``, ``mppi_0.3``, ``mppi_1.0``: MPPI, Gaussian noise of that std around the warm-started nominal;
* ``log_mppi_0.3``: log-MPPI (normal x log-normal noise), std 0.3;
* ``uniform``: uniformly random discrete actions (the table's action set) on real rollouts;
* ``cu_table``: C-Uniform, the max-flow table (the paper's method);
* ``cu_coverage``: C-Uniform, the coverage-method table (built on first use: about 80 s for this robot);
* ``cu_mlp``: C-Uniform, the MLP distilled from the max-flow table (opt-in: about 10x the table's cost per cycle
  on a CPU, and trained on first use);
* ``cumppi``: CU-MPPI: the best C-Uniform rollout seeds a local MPPI pass (half of the budget each);
* ``cfu_mppi``: CFU-MPPI: the same with a map-conditioned policy (``--map-policy FILE``, from
  ``python -m training.maps.distill``), which senses the local map at each command within the task's sensing range
  (opt-in: it needs that file).

``GAUSSIAN_BASELINES`` are what every other method is compared with (the best of them per suite and budget).
"""

from __future__ import annotations

from cuniform_torch import CFUMPPI, CUMPPI, MPPI, CUniformMPPI, LogMPPI
from cuniform_torch.sampling import GaussianSampler, NormalLogNormalSampler
from eval.common.methods import Method

__all__ = ["NAV_METHODS", "DEFAULT_METHODS", "GAUSSIAN_BASELINES", "OPT_IN", "parse_nav_methods"]

_BLUES = {0.1: "#9ecae1", 0.3: "#4292c6", 1.0: "#08306b"}

NAV_METHODS: dict[str, Method] = {m.key: m for m in [
    *(Method(f"mppi_{s:.1f}", f"MPPI (std {s:.1f})", "mppi", MPPI, GaussianSampler, s, color=_BLUES[s])
      for s in (0.1, 0.3, 1.0)),
    Method("log_mppi_0.3", "log-MPPI (std 0.3)", "log_mppi", LogMPPI, NormalLogNormalSampler, 0.3, color="#f16913"),
    Method("uniform", "uniform discrete actions", "uniform", CUniformMPPI, source="uniform", color="#737373"),
    Method("cu_table", "C-Uniform (max-flow table)", "cuniform", CUniformMPPI, source="table", paper=True,
           color="#2ca02c"),
    Method("cu_coverage", "C-Uniform (coverage table)", "cuniform", CUniformMPPI, source="coverage_table",
           color="#d62728"),
    Method("cu_mlp", "C-Uniform (distilled MLP)", "cuniform", CUniformMPPI, source="policy", slow=True,
           color="#9467bd"),
    Method("cumppi", "CU-MPPI (max-flow table)", "cuniform", CUMPPI, source="table", open_loop=False,
           color="#e377c2"),
    Method("cfu_mppi", "CFU-MPPI (map-conditioned policy)", "cuniform", CFUMPPI, source="map_policy",
           open_loop=False, color="#17becf"),
]}
"""every method of the benchmark, by key"""

OPT_IN = ("cu_mlp", "cfu_mppi")
"""left out of a default run (module docstring); name them with ``--methods``"""
DEFAULT_METHODS = tuple(k for k in NAV_METHODS if k not in OPT_IN)
GAUSSIAN_BASELINES = ("mppi_0.1", "mppi_0.3", "mppi_1.0")


def parse_nav_methods(keys: tuple[str, ...] | list[str] | None) -> list[Method]:
    """The methods named by ``keys`` (None: :data:`DEFAULT_METHODS`); an unknown key lists the known ones."""
    if keys is None:
        keys = DEFAULT_METHODS
    unknown = [k for k in keys if k not in NAV_METHODS]
    if unknown:
        raise ValueError(f"unknown method(s) {', '.join(unknown)}; choose from {', '.join(NAV_METHODS)}")
    if len(set(keys)) != len(keys):
        raise ValueError(f"a method is named twice in {list(keys)}")
    return [NAV_METHODS[k] for k in keys]
