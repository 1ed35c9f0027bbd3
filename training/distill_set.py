"""Distil a table set into one start-conditioned MLP pi(u | x, t, x0): ``python -m training.distill --tables DIR``.

Shapes: S starts (tables), C cells (all tables, all levels), N samples of an epoch, B of a batch, V validation
points, d state dimensions, G (table, level) groups.

``DIR`` is a folder of ``python -m precompute.build --starts SPEC --out DIR`` (read by
:func:`cuniform_torch.load_table_set`, which checks it). The network is a
:class:`~cuniform_torch.mlp_start.StartMLPPolicy`: the state features of every cell of every table (each table
is in its start's frame on an SE(2)-invariant system, as the runtime rolls out) plus the features of that
table's start over the start dimensions; the target of a point is its cell's row in its own table. Everything
else is :mod:`training.distill`'s: the jittered points, the level-weighted KL (every (table, level) group
counts equally), Adam with a cosine learning rate, early stopping on fixed validation points, the training
state after every epoch (``--resume``), TensorBoard (``losses/``, ``charts/``; every ``--eval-every`` epochs
``eval/kl_start_<i>``, the mean KL over the levels at the cell centres of start i's table, and the
``rollouts`` and ``coverage`` figures from the middle start) and the progress bar.

Outputs: the checkpoint ``--out`` (``cuniform-policy/1`` with ``start_region``), ``<out>.train.pt`` and
``<out stem>.comparison.json``: per start, :func:`training.evaluate.compare` of the MLP from that start with
that start's table (KL at centres and jittered points, coverage of real rollouts), also printed.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from cuniform_torch.checkpoint import file_sha256, policy_checkpoint, save_policy
from cuniform_torch.fileio import write_json
from cuniform_torch.grid import Grid
from cuniform_torch.metrics import coverage
from cuniform_torch.mlp import MLPConfig, default_feature_scale
from cuniform_torch.mlp_start import StartMLPPolicy, StartRegion, start_dims_of
from cuniform_torch.rollout import rollout
from cuniform_torch.table_set import SET_INDEX, load_table_set

from .evaluate import cell_centres, cell_levels, compare, kl_per_level
from .figures import coverage_figure, trajectory_figure
from .samples import level_weights, make_samples
from .support import pooled_support
from .loop import Progress, kl_epoch, log_epoch_scalars, log_hyperparameters, validate
from .train_state import RESUME_KEYS, UsageError, load_train_state, save_train_state

if TYPE_CHECKING:
    from .distill import DistillConfig

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
    system, T = members[0].system, tables[0].horizon
    grid = Grid.of(system)
    dims = start_dims_of(system)
    if not dims:
        raise UsageError(f"--tables {folder}: {system.name} has no dimension beyond its pose; one table serves "
                         f"every start, distil a table file")
    index = json.loads((folder / SET_INDEX).read_text())
    files = [folder / e["file"] for e in index["tables"]]
    shas = [file_sha256(p) for p in files]
    fingerprint = {**{k: getattr(cfg, k) for k in RESUME_KEYS}, "tables_sha256": [file_sha256(folder / SET_INDEX), *shas]}

    # ---- seeding
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    data_gen = torch.Generator().manual_seed(cfg.seed)
    val_gen = torch.Generator().manual_seed(cfg.seed + 1)

    # ---- data: every cell of every (table, level) group, with its table's start
    centres = torch.cat([cell_centres(tb) for tb in tables])  # [C, d] float64
    probs = torch.cat([torch.from_numpy(tb.action_probs) for tb in tables]).to(device)  # [C, A]
    levels = torch.cat([cell_levels(tb) for tb in tables])  # [C]
    group = torch.cat([cell_levels(tb) + i * (T + 1) for i, tb in enumerate(tables)])  # [C]
    cell_start = torch.repeat_interleave(starts, torch.tensor([tb.cells.shape[0] for tb in tables]), dim=0)
    cell_start = cell_start.to(device=device, dtype=torch.float32)  # [C, d]
    G = len(tables) * (T + 1)
    best_rows = probs >= probs.max(dim=1, keepdim=True).values - 1e-6  # [C, A]
    val_rows, val_x = make_samples(centres, grid, cfg.val_points, False, val_gen)
    val_x = val_x.to(device=device, dtype=torch.float32)  # [V, d]
    val_t, val_w = levels[val_rows].to(device), level_weights(group[val_rows], G).to(device)
    val_rows = val_rows.to(device)

    # ---- model and optimiser
    mlp_config = MLPConfig(state_dim=grid.dim, num_actions=tables[0].actions.shape[0], horizon=T,
                           periodic=list(grid.periodic), feature_scale=default_feature_scale(centres, grid),
                           hidden=cfg.hidden, layers=cfg.layers, start_dims=dims)
    region = StartRegion(starts[:, dims].clone(), dims)
    model = StartMLPPolicy(mlp_config, system, torch.from_numpy(tables[0].actions), region,
                           support=pooled_support(tables, T)).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=cfg.epochs, eta_min=cfg.lr / 100)

    # ---- resume
    progress = Progress.start(model, f"{folder.name}__distill_set__{cfg.seed}__{int(time.time())}")
    if cfg.resume:
        progress.restore(load_train_state(state_path, fingerprint), model, optimizer, scheduler, data_gen, device)

    writer = SummaryWriter(str(Path(cfg.logdir) / progress.run_name),
                           purge_step=progress.epochs_run + 1 if cfg.resume else None)
    try:
        if not cfg.resume:
            log_hyperparameters(writer, cfg)
        mid = len(members) // 2  # the figures' start
        x_mid = starts[mid].to(device=device, dtype=torch.float32)  # [d]
        figure_n = cfg.eval_samples[0]
        table_paths, _ = rollout(system, members[mid], x_mid, 200, T, torch.Generator(device).manual_seed(cfg.seed))
        table_states, _ = rollout(system, members[mid], x_mid, figure_n, T, torch.Generator(device).manual_seed(cfg.seed))
        table_cov = coverage(table_states, grid, members[mid]).in_level_set

        bar = tqdm(range(progress.epochs_run, cfg.epochs), initial=progress.epochs_run, total=cfg.epochs,
                   disable=cfg.quiet or progress.finished,                    desc="distill set", unit="epoch")
        for epoch in bar:
            if progress.finished:
                break
            epoch_start = time.perf_counter()
            model.train()
            train_kl = kl_epoch(lambda x, t, r: model(x, t, cell_start[r]), optimizer, centres, grid, levels, group, G, probs,
                                cfg.jitter, cfg.batch_size, data_gen, device)
            lr = optimizer.param_groups[0]["lr"]
            scheduler.step()

            model.eval()
            with torch.no_grad():
                val_kl, val_acc = validate(model(val_x, val_t, cell_start[val_rows]), probs, best_rows, val_rows, val_w)  # [V, A] logits
            progress.update(val_kl, epoch, model, cfg.patience, cfg.epochs)
            progress.train_seconds += time.perf_counter() - epoch_start

            step = progress.epochs_run = epoch + 1
            log_epoch_scalars(writer, step, train_kl, val_kl, val_acc, lr, epoch_start)
            if step % cfg.eval_every == 0 or progress.finished:
                for i, tb in enumerate(tables):
                    model.for_start(starts[i].to(device=device, dtype=torch.float32))
                    per_level = kl_per_level(model, tb, device=device)
                    writer.add_scalar(f"eval/kl_start_{i}", sum(per_level) / len(per_level), step)
                mlp_paths, _ = rollout(system, model, x_mid, 200, T, torch.Generator(device).manual_seed(cfg.seed))
                writer.add_figure("rollouts", trajectory_figure(table_paths, mlp_paths, f"epoch {step}, start "
                                                                f"{starts[mid].tolist()}"), step)
                mlp_states, _ = rollout(system, model, x_mid, figure_n, T, torch.Generator(device).manual_seed(cfg.seed))
                mlp_cov = coverage(mlp_states, grid, members[mid]).in_level_set
                writer.add_figure("coverage", coverage_figure(table_cov, mlp_cov, tables[mid].level_sizes, figure_n,
                                                              f"epoch {step}"), step)
            bar.set_postfix(train_kl=f"{train_kl:.4f}", val_kl=f"{val_kl:.4f}", best=progress.best_epoch)

            save_train_state(state_path, progress.state(fingerprint, model, optimizer, scheduler, data_gen))
        bar.close()

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
            "best_epoch": progress.best_epoch, "best_val_kl": progress.best_val, "train_seconds": progress.train_seconds,
            "kl_centres_mean_per_start": [r["kl_centres"]["mean"] for r in per_start],
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
            "checkpoint": str(out), "run": str(Path(cfg.logdir) / progress.run_name), "config": dataclasses.asdict(cfg),
            "epochs_run": progress.epochs_run, "best_epoch": progress.best_epoch, "best_val_kl": progress.best_val,
            "wall_seconds": {"train": progress.train_seconds, "total_this_call": time.perf_counter() - wall_start},
            "sizes": {"table_arrays_bytes": arrays, "checkpoint_bytes": ckpt_bytes, "compression_ratio": arrays / ckpt_bytes},
            "per_start": per_start,
        }
        write_json(comparison_path, comparison)
        summary = format_set_comparison(comparison)
        writer.add_text("comparison", "```\n" + summary + "\n```", progress.epochs_run)
    finally:
        writer.close()
    print(summary)
    print(f"wrote {out}, {comparison_path} and {state_path}; TensorBoard: {comparison['run']}")
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
