"""The settings of one distillation (:class:`DistillConfig`): one table, several pooled tables, or a table set.

Its own module, below both :mod:`training.distill` (one table, and the CLI) and :mod:`training.sets.distill` (a
table set), so that neither imports the other for it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

from precompute.cli import RUNS

__all__ = ["DistillConfig", "DEFAULT_EPOCHS", "DEFAULT_CELL_PASSES", "with_epochs"]

DEFAULT_EPOCHS = 100
"""epochs of a default run on a table of at most :data:`DEFAULT_CELL_PASSES` / 100 cells"""
DEFAULT_CELL_PASSES = 6_800_000
"""cells x epochs a default run makes at most: a larger table gets fewer epochs (each epoch already makes more
optimiser steps), never fewer than 20. The paper-scale table (168,933 cells) gets 41 epochs, 236 s on a 2-core CPU,
at KL 0.055 (docs/results/distillation.md); 100 epochs there would take about 8 minutes."""


@dataclass
class DistillConfig:
    """Settings of one distillation; every field is a flag (``--batch-size``, ...)."""

    tables: list[str] = field(default_factory=list)
    """table files (.npz) to distil; several must share the system JSON and actions (their cells are pooled); or
    one table-set folder (python -m precompute.build --starts): a start-conditioned policy (training.sets.distill)"""
    hidden: int = 128
    """hidden units per layer"""
    layers: int = 3
    """hidden layers"""
    frequencies: int = 6
    """octaves K of the sin / cos encoding of the input features (sin(2^k pi f), cos(2^k pi f), k < K): what lets
    a small network fit a table's cell-to-cell detail in a hundred epochs; 0: the plain features (those of the
    networks distilled before the encoding: on out/dubins.npz 1500 epochs of 3 x 256 reached KL 0.052, 100 epochs
    with the encoding 0.022). One table (or pooled tables) only: a table set's start-conditioned MLP reads the
    plain features and ignores it"""
    epochs: int | None = None
    """passes over the data, each with fresh jitter (default: 100, fewer on tables of over 68,000 cells so that a
    default run makes at most 6.8 million cell passes: the paper-scale table's 168,933 cells get 41; see
    docs/results/distillation.md for the time and the KL of the default and of longer runs)"""
    lr: float = 5e-3
    """Adam's initial learning rate, cosine-annealed per epoch to lr / 100 at the last epoch"""
    batch_size: int = 1024
    """samples per optimiser step"""
    seed: int = 0
    """seed of the initial weights, the jitter, the shuffling, the validation points and the evaluation rollouts"""
    device: str = "cpu"
    """torch device to train and evaluate on (cpu, cuda, cuda:1, ...)"""
    threads: int = 1
    """torch CPU threads (0: torch's choice, one per core). 1 by default: on 2 idle cores a second thread made
    a 4096-sample step of a 3 x 256 network (the default before the encoding) about 1.6x faster, but when other
    processes keep the cores busy it makes it about 10x slower (OpenMP hand-offs between oversubscribed threads)"""
    out: str | None = None
    """checkpoint to write (default: out/<first table stem>.policy.pt)"""
    jitter: int = 4
    """jittered points per cell per epoch, on top of the cell centre (also per cell in the final jittered KL;
    4 there when 0)"""
    val_points: int = 2
    """held-out jittered points per cell for the validation KL (drawn once)"""
    patience: int = 300
    """stop when the validation KL has not improved for this many epochs"""
    logdir: str = str(RUNS)
    """folder of the TensorBoard runs"""
    quiet: bool = False
    """no progress bar"""
    resume: bool = False
    """continue from <out>.train.pt (refused when the settings or the tables differ)"""
    eval_samples: list[int] = field(default_factory=lambda: [1000, 10000])
    """rollout counts N of the final coverage comparison (the first also sets the coverage figure's N)"""
    eval_every: int = 100
    """epochs between the eval/kl_level_<t> scalars and the figures"""
    system_module: list[str] = field(default_factory=list)
    """modules to import first (--system-module, repeatable): they register the user systems the tables name"""


def with_epochs(cfg: DistillConfig, cells: int) -> DistillConfig:
    """``cfg`` with ``epochs`` set: as given, or the default for a table (or set) of ``cells`` cells in all levels:
    :data:`DEFAULT_EPOCHS`, down to ``ceil(DEFAULT_CELL_PASSES / cells)`` (at least 20) for large tables."""
    if cfg.epochs is not None:
        return cfg
    epochs = min(DEFAULT_EPOCHS, max(20, math.ceil(DEFAULT_CELL_PASSES / max(cells, 1))))
    return dataclasses.replace(cfg, epochs=epochs)
