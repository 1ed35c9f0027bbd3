"""Distillation of C-Uniform tables into small MLP policies.

The library's training jobs are importable from here (:mod:`training.api`; they load on first use)::

    from training import DistillConfig, MapDistillConfig, distill_policy, train_map_policy

* ``python -m training.distill --tables out/dubins.npz``: the training script (:mod:`training.distill`), one
  table (or several pooled) -> pi(u | x, t); ``--tables DIR`` of a table set (:mod:`training.sets.distill`) ->
  one start-conditioned pi(u | x, t, x0);
* :mod:`training.tables.evaluate`: the comparison of a policy (a distilled MLP, or anything with the Policy interface)
  with its table: KL per level at cell centres and jittered points, coverage of real rollouts, fallback rates
  and sizes. The script calls it at the end; it works the same on a saved checkpoint;
* ``python -m training.sets.evaluate``: a start-conditioned MLP against its set at held-out starts, and the
  controller's command time with each;
* helpers: :mod:`training.tables.samples` (the training points and weights), :mod:`training.tables.train_state` (``--resume``),
  :mod:`training.tables.figures` (TensorBoard figures), :mod:`training.tables.support` (the cells a checkpoint records).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from precompute.startup import install_when_run_as_command

install_when_run_as_command()  # python -m ...: Ctrl-C during the imports is one line and exit 130

if TYPE_CHECKING:
    from training.api import DistillConfig, MapDistillConfig, distill_policy, train_map_policy

__all__ = ["DistillConfig", "MapDistillConfig", "distill_policy", "train_map_policy"]


def __getattr__(name: str) -> Any:
    """The public names of :mod:`training.api`, imported on first use (``python -m training.distill`` would
    otherwise find its own module imported before it runs)."""
    if name in __all__:
        import training.api

        return getattr(training.api, name)
    raise AttributeError(f"module 'training' has no attribute {name!r}")
