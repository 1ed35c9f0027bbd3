"""The set-up that :mod:`training.distill` (one table) and :mod:`training.sets.distill` (a table set) share:
seeding, the pooled cells and the fixed validation points, Adam with its cosine schedule, the run's progress
and TensorBoard writer (resumed or fresh), the rollout / coverage figures against a table, and the facts of a
finished run that both comparisons record, write and print.

Shapes: C cells (all tables, all levels), V validation points, d state dimensions, A actions, G (table, level)
groups, T horizon.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from torch.utils.tensorboard import SummaryWriter

from cuniform_torch.common.fileio import write_json
from cuniform_torch.grid.cells import Grid
from cuniform_torch.metrics import coverage
from cuniform_torch.sampling.rollout import rollout
from cuniform_torch.systems import System
from cuniform_torch.tables.file import Table
from training.tables.evaluate import cell_centres, cell_levels
from training.tables.figures import coverage_figure, trajectory_figure
from training.tables.loop import Progress, log_hyperparameters
from training.tables.samples import PooledCells, level_weights, make_samples
from training.tables.train_state import load_train_state

__all__ = ["seed_run", "pool_cells", "adam_cosine", "open_run", "TableFigures", "best_metrics",
           "run_facts", "write_comparison", "say_written"]


def seed_run(cfg: Any) -> tuple[torch.Generator, torch.Generator]:
    """Set torch's threads (``cfg.threads``, 0: torch's choice) and global seed; ``(data_gen, val_gen)``: the
    jitter and shuffling stream (saved with the training state) and the fixed validation points' (``seed + 1``)."""
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    return torch.Generator().manual_seed(cfg.seed), torch.Generator().manual_seed(cfg.seed + 1)


def pool_cells(tables: Sequence[Table], horizon: int, grid: Grid, val_points: int, val_gen: torch.Generator,
               device: torch.device) -> PooledCells:
    """The cells of ``tables`` pooled, with ``val_points`` jittered validation points per cell from ``val_gen``."""
    centres = torch.cat([cell_centres(tb) for tb in tables])  # [C, d] float64
    probs = torch.cat([torch.from_numpy(tb.action_probs) for tb in tables]).to(device)  # [C, A]
    levels = torch.cat([cell_levels(tb) for tb in tables])  # [C]
    group = torch.cat([cell_levels(tb) + i * (horizon + 1) for i, tb in enumerate(tables)])  # [C]
    G = len(tables) * (horizon + 1)
    best_rows = probs >= probs.max(dim=1, keepdim=True).values - 1e-6  # [C, A]
    val_rows, val_x = make_samples(centres, grid, val_points, False, val_gen)
    return PooledCells(centres, probs, levels, group, G, best_rows, val_rows.to(device),
                       val_x.to(device=device, dtype=torch.float32), levels[val_rows].to(device),
                       level_weights(group[val_rows], G).to(device))


def adam_cosine(model: torch.nn.Module, cfg: Any) -> tuple[torch.optim.Optimizer, Any]:
    """Adam at ``cfg.lr``, cosine-annealed per epoch to lr / 100 at ``cfg.epochs``: ``(optimizer, scheduler)``."""
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    return optimizer, torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=cfg.epochs, eta_min=cfg.lr / 100)


def open_run(cfg: Any, run_name: str, state_path: Path, fingerprint: dict[str, Any], model: torch.nn.Module,
             optimizer: torch.optim.Optimizer, scheduler: Any, data_gen: torch.Generator,
             device: torch.device) -> tuple[Progress, SummaryWriter]:
    """A fresh run named ``run_name``, or with ``cfg.resume`` the saved one (its state loaded into the model,
    the optimiser, the scheduler and the generators), and its TensorBoard writer: a resumed run logs on into
    its folder past its last epoch; a fresh one logs the config first. The caller closes the writer."""
    progress = Progress.start(model, run_name)
    if cfg.resume:
        progress.restore(load_train_state(state_path, fingerprint), model, optimizer, scheduler, data_gen, device)
    writer = SummaryWriter(str(Path(cfg.logdir) / progress.run_name),
                           purge_step=progress.epochs_run + 1 if cfg.resume else None)
    try:
        if not cfg.resume:
            log_hyperparameters(writer, cfg)
    except BaseException:
        writer.close()
        raise
    return progress, writer


@dataclass
class TableFigures:
    """The ``rollouts`` and ``coverage`` figures of a policy against a table from one start; the table's side
    (200 paths, its coverage of ``n`` rollouts) is drawn once, every rollout from a generator seeded ``seed``."""

    system: System
    grid: Grid
    table: Any
    """the table's policy (it also counts the cells of L_t reached)"""
    x0: Tensor
    """``[d]`` the start, float32 on the device"""
    horizon: int
    n: int
    """rollouts of the coverage figure"""
    seed: int
    level_sizes: Sequence[int]
    table_paths: Tensor = dataclasses.field(init=False)
    """``[200, T+1, d]``"""
    table_cov: Tensor = dataclasses.field(init=False)
    """``[T+1]`` cells of each L_t that ``n`` table rollouts reach"""

    def __post_init__(self) -> None:
        self.table_paths, _ = rollout(self.system, self.table, self.x0, 200, self.horizon, self._generator())
        table_states, _ = rollout(self.system, self.table, self.x0, self.n, self.horizon, self._generator())
        self.table_cov = coverage(table_states, self.grid, self.table).in_level_set

    def _generator(self) -> torch.Generator:
        return torch.Generator(self.x0.device).manual_seed(self.seed)

    def log(self, writer: SummaryWriter, model: Any, step: int, title: str) -> None:
        """Both figures of ``model`` at global step ``step``; ``title`` heads the rollouts figure."""
        mlp_paths, _ = rollout(self.system, model, self.x0, 200, self.horizon, self._generator())
        writer.add_figure("rollouts", trajectory_figure(self.table_paths, mlp_paths, title), step)
        mlp_states, _ = rollout(self.system, model, self.x0, self.n, self.horizon, self._generator())
        mlp_cov = coverage(mlp_states, self.grid, self.table).in_level_set
        writer.add_figure("coverage", coverage_figure(self.table_cov, mlp_cov, self.level_sizes, self.n,
                                                      f"epoch {step}"), step)


def best_metrics(progress: Progress) -> dict[str, Any]:
    """The checkpoint metrics every distillation records first: the best epoch, its validation KL, train time."""
    return {"best_epoch": progress.best_epoch, "best_val_kl": progress.best_val,
            "train_seconds": progress.train_seconds}


def run_facts(cfg: Any, progress: Progress, out: Path, wall_start: float) -> dict[str, Any]:
    """The comparison JSON's record of the run: checkpoint, TensorBoard folder, config, epochs, best epoch and
    wall times (``wall_start``: the call's time.perf_counter() at its start)."""
    return {
        "checkpoint": str(out), "run": str(Path(cfg.logdir) / progress.run_name), "config": dataclasses.asdict(cfg),
        "epochs_run": progress.epochs_run, "best_epoch": progress.best_epoch, "best_val_kl": progress.best_val,
        "wall_seconds": {"train": progress.train_seconds, "total_this_call": time.perf_counter() - wall_start},
    }


def write_comparison(writer: SummaryWriter, path: Path, comparison: dict[str, Any],
                     summarize: Callable[[dict[str, Any]], str], step: int) -> str:
    """Write the comparison JSON (atomically), then log its summary (``summarize(comparison)``) as the run's
    ``comparison`` text at ``step``; returns the summary."""
    write_json(path, comparison)
    summary = summarize(comparison)
    writer.add_text("comparison", "```\n" + summary + "\n```", step)
    return summary


def say_written(summary: str, out: Path, comparison_path: Path, state_path: Path, run: str) -> None:
    """Print the summary and the files and TensorBoard folder the run wrote."""
    print(summary)
    print(f"wrote {out}, {comparison_path} and {state_path}; TensorBoard: {run}")
