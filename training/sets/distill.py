"""Distil a table set into one start-conditioned MLP pi(u | x, t, x0): ``python -m training.distill --tables DIR``.

Shapes: S starts (tables), C cells (all tables, all levels), N samples of an epoch, B of a batch, V validation
points, d state dimensions, G (table, level) groups.

``DIR`` is a folder of ``python -m precompute.build --starts SPEC --out DIR`` (read by
:func:`cuniform_torch.load_table_set`, which checks it). The network is a
:class:`~cuniform_torch.policies.start_mlp.StartMLPPolicy`: the state features of every cell of every table (each table
is in its start's frame on an SE(2)-invariant system, as the runtime rolls out) plus the features of that
table's start over the start dimensions; the target of a point is its cell's row in its own table. Everything
else is :mod:`training.distill`'s: the jittered points, the level-weighted KL (every (table, level) group
counts equally), Adam with a cosine learning rate, early stopping on fixed validation points, the training
state after every epoch (``--resume``), TensorBoard (``losses/``, ``charts/``; every ``--eval-every`` epochs
``eval/kl_start_<i>``, the mean KL over the levels at the cell centres of start i's table, and the
``rollouts`` and ``coverage`` figures from the middle start) and the progress bar.

Outputs: the checkpoint ``--out`` (``cuniform-policy/1`` with ``start_region``), ``<out>.train.pt`` and
``<out stem>.comparison.json``: per start, :func:`training.tables.evaluate.compare` of the MLP from that start with
that start's table (KL at centres and jittered points, coverage of real rollouts), also printed.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from cuniform_torch.common.fileio import MAX_JSON_BYTES, read_capped_text
from cuniform_torch.grid.cells import Grid
from cuniform_torch.policies.checkpoint import file_sha256, policy_checkpoint, save_policy
from cuniform_torch.policies.mlp import MLPConfig, default_feature_scale
from cuniform_torch.policies.start_mlp import StartMLPPolicy, StartRegion, start_dims_of
from cuniform_torch.policies.table_set import SET_INDEX, load_table_set
from training.tables.config import with_epochs
from training.tables.evaluate import compare, kl_per_level
from training.tables.loop import run_epochs
from training.tables.setup import (
    TableFigures,
    adam_cosine,
    best_metrics,
    open_run,
    pool_cells,
    run_facts,
    say_written,
    seed_run,
    write_comparison,
)
from training.tables.support import pooled_support
from training.tables.train_state import RESUME_KEYS, UsageError, save_train_state

if TYPE_CHECKING:
    from training.tables.config import DistillConfig

__all__ = ["distill_set", "format_set_comparison"]


def distill_set(cfg: DistillConfig, out: Path, state_path: Path, comparison_path: Path) -> int:
    """Train, checkpoint and compare (module docstring); the caller holds the lock of ``out``."""
    wall_start = time.perf_counter()
    folder = Path(cfg.tables[0])
    device = torch.device(cfg.device)

    # ---- the set
    tset = load_table_set(folder)
    members = tset.members
    tables = [m.table for m in members]
    starts = tset.starts  # [S, d] float64
    cfg = with_epochs(cfg, sum(int(tb.cells.shape[0]) for tb in tables))
    system, T = members[0].system, tables[0].horizon
    grid = Grid.of(system)
    dims = start_dims_of(system)
    if not dims:
        raise UsageError(f"--tables {folder}: {system.name} has no dimension beyond its pose; one table serves "
                         f"every start, distil a table file")
    index = json.loads(read_capped_text(folder / SET_INDEX, MAX_JSON_BYTES, "the table-set index"))
    files = [folder / e["file"] for e in index["tables"]]
    shas = [file_sha256(p) for p in files]
    fingerprint = {**{k: getattr(cfg, k) for k in RESUME_KEYS}, "tables_sha256": [file_sha256(folder / SET_INDEX), *shas]}

    data_gen, val_gen = seed_run(cfg)

    # ---- data: every cell of every (table, level) group, with its table's start
    cells = pool_cells(tables, T, grid, cfg.val_points, val_gen, device)
    cell_start = torch.repeat_interleave(starts, torch.tensor([tb.cells.shape[0] for tb in tables]), dim=0)
    cell_start = cell_start.to(device=device, dtype=torch.float32)  # [C, d]

    # ---- model and optimiser
    mlp_config = MLPConfig(state_dim=grid.dim, num_actions=tables[0].actions.shape[0], horizon=T,
                           periodic=list(grid.periodic), feature_scale=default_feature_scale(cells.centres, grid),
                           hidden=cfg.hidden, layers=cfg.layers, start_dims=dims)
    region = StartRegion(starts[:, dims].clone(), dims)
    model = StartMLPPolicy(mlp_config, system, torch.from_numpy(tables[0].actions), region,
                           support=pooled_support(tables, T)).to(device)
    optimizer, scheduler = adam_cosine(model, cfg)

    # ---- resume, TensorBoard
    progress, writer = open_run(cfg, f"{folder.name}__distill_set__{cfg.seed}__{int(time.time())}", state_path,
                                fingerprint, model, optimizer, scheduler, data_gen, device)
    try:
        mid = len(members) // 2  # the figures' start
        x_mid = starts[mid].to(device=device, dtype=torch.float32)  # [d]
        figures = TableFigures(system, grid, members[mid], x_mid, T, cfg.eval_samples[0], cfg.seed,
                               tables[mid].level_sizes)

        def evaluate(step: int) -> None:
            for i, tb in enumerate(tables):
                model.for_start(starts[i].to(device=device, dtype=torch.float32))
                per_level = kl_per_level(model, tb, device=device)
                writer.add_scalar(f"eval/kl_start_{i}", sum(per_level) / len(per_level), step)
            figures.log(writer, model, step, f"epoch {step}, start {starts[mid].tolist()}")

        # save looks save_train_state up here at each call (a test wraps it)
        run_epochs(cfg, progress, model, lambda x, t, r: model(x, t, cell_start[r]), optimizer, scheduler, cells,
                   grid, data_gen, device, writer, evaluate, lambda state: save_train_state(state_path, state),
                   fingerprint, "distill set")

        # ---- checkpoint: the best validation state; per start, the comparison with that start's table
        model.load_state_dict(progress.best_state)
        model.eval()
        per_start = []
        for i, tb in enumerate(tables):
            model.for_start(starts[i].to(device=device, dtype=torch.float32))
            per_start.append({"start": starts[i].tolist(), "table": files[i].name, "cells": int(tb.cells.shape[0]),
                              **compare(model, tb, cfg.eval_samples, seed=cfg.seed, jitter_per_cell=cfg.jitter or 4,
                                        device=device)})
        metrics: dict[str, Any] = {
            **best_metrics(progress), "kl_centres_mean_per_start": [r["kl_centres"]["mean"] for r in per_start],
            "kl_jitter_mean_per_start": [r["kl_jitter"]["mean"] for r in per_start],
        }
        for n in cfg.eval_samples:
            metrics[f"coverage_ratio_in_level_set_{n}_per_start"] = [r["coverage"][str(n)]["ratio"]["in_level_set_sum"]
                                                                     for r in per_start]
        source = {"path": str(folder), "sha256": fingerprint["tables_sha256"][0],
                  "all_tables": json.dumps([{"path": str(p), "sha256": s} for p, s in zip(files, shas)])}
        save_policy(out, policy_checkpoint(model, tables[0].system, source=source, metrics=metrics))

        arrays = sum(int(tb.cells.nbytes + tb.action_probs.nbytes) for tb in tables)
        ckpt_bytes = out.stat().st_size
        comparison = {
            "set": str(folder), "tables": [{"path": str(p), "sha256": s} for p, s in zip(files, shas)],
            **run_facts(cfg, progress, out, wall_start),
            "sizes": {"table_arrays_bytes": arrays, "checkpoint_bytes": ckpt_bytes, "compression_ratio": arrays / ckpt_bytes},
            "per_start": per_start,
        }
        summary = write_comparison(writer, comparison_path, comparison, format_set_comparison, progress.epochs_run)
    finally:
        writer.close()
    say_written(summary, out, comparison_path, state_path, comparison["run"])
    return 0


def format_set_comparison(c: dict[str, Any]) -> str:
    """A short summary: the training, the sizes, and per start the KL and the coverage ratio vs its table."""
    s = c["sizes"]
    ns = list(c["per_start"][0]["coverage"])
    lines = [
        f"distilled {len(c['per_start'])} tables in {c['wall_seconds']['train']:.1f}s of training "
        f"({c['epochs_run']} epochs, best {c['best_epoch']}, val KL {c['best_val_kl']:.4f})",
        f"sizes: tables' arrays {s['table_arrays_bytes']:,} B, checkpoint {s['checkpoint_bytes']:,} B: "
        f"{s['compression_ratio']:.2f}x",
        "start                              cells  KL centres  KL jitter  " + "  ".join(f"coverage N={n}" for n in ns),
    ]
    for r in c["per_start"]:
        cov = "  ".join(f"{r['coverage'][n]['ratio']['in_level_set_sum']:12.3f}" for n in ns)
        start = "[" + ", ".join(f"{v:.4g}" for v in r["start"]) + "]"
        lines.append(f"{start:32s} {r['cells']:7d} {r['kl_centres']['mean']:11.4f} {r['kl_jitter']['mean']:10.4f}  {cov}")
    lines.append("(coverage: cells of L_t reached by the MLP's rollouts / by its table's, summed over the levels)")
    return "\n".join(lines)
