"""Distil a C-Uniform table into an MLP policy pi(u | x, t):  python -m training.distill --tables out/dubins.npz

The file reads top to bottom: config, seeding, data, model, loop, checkpoint, final comparison.
Shapes: C cells (all levels, all tables), N samples of an epoch, B of a batch, V validation points, d state
dimensions, A actions, G (table, level) groups.

* **Data.** For every level t of every table: the centre of every cell of L_t plus ``--jitter`` points drawn
  uniformly inside each cell (+-0.5 cell on every dimension, angles wrapped to [-pi, pi)), drawn afresh every
  epoch; the target of a point is its cell's row of ``action_probs``, its time feature is t. Validation uses
  ``--val-points`` jittered points per cell drawn once from a fixed seed (``seed + 1``).
* **Model.** :class:`~cuniform_torch.policies.mlp.MLPPolicy`, ``--layers`` x ``--hidden`` (3 x 128), on the scaled
  state and time features and their sin / cos encoding at ``--frequencies`` octaves (6; 0: the plain features);
  the encoding is what lets the default 100 epochs fit a table's cell-to-cell detail.
* **Loss.** KL(table || model) = sum_u p (log p - log q) (0 log 0 = 0), level-weighted: a sample's weight is
  1 / (samples of its level), averaged over the levels (of all tables), so a level of 30 000 cells counts as
  much as a level of 10. A minibatch's loss is its weighted sum scaled by (epoch samples / batch samples), an
  unbiased estimate of the epoch's loss; ``losses/train_kl`` is the epoch's exact weighted sum.
* **Optimiser.** Adam; the learning rate starts at ``--lr`` and follows a cosine per epoch down to lr / 100 at
  ``--epochs``. Early stopping: training ends when the validation KL has not improved for ``--patience``
  epochs; the weights of the best validation epoch are the ones saved.
* **TensorBoard** (``<logdir>/<table stem>__distill__<seed>__<unix time>``; global step = epoch):
  ``losses/train_kl``, ``losses/val_kl`` (level-weighted KL), ``charts/val_argmax_accuracy`` (level-weighted share of
  validation points whose most likely model action is one of the table row's most likely actions),
  ``charts/learning_rate``, ``charts/epoch_seconds``; every ``--eval-every`` epochs ``eval/kl_level_<t>`` (mean KL
  at the cell centres of level t) and two figures: ``rollouts`` (200 rollouts from the origin, table vs MLP, fixed
  seed) and ``coverage`` (cells of L_t reached by N = first ``--eval-samples`` rollouts, MLP vs table vs |L_t|).
  The config is logged once as a markdown table (``hyperparameters``).
* **Outputs.** The policy checkpoint ``--out`` (``cuniform-policy/1``, see :mod:`cuniform_torch.policies.mlp`; written
  atomically); ``<out>.train.pt``, the training state after every epoch (``--resume`` continues from it and ends
  at the same weights as an uninterrupted run); ``<out stem>.comparison.json``, the final comparison of
  :func:`training.tables.evaluate.compare` with sizes and wall times, also printed.

``main(argv)`` returns 0, or 2 after printing one line ``error: ...`` (bad flags, unreadable tables, an output
path that cannot be written, checked before training starts, a full disk, a refused resume, another run holding
``<out>.lock``), or 130 after one line on Ctrl-C (see :mod:`precompute.cli`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
import typing
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from cuniform_torch.common.fileio import exclusive_lock
from cuniform_torch.grid.cells import Grid
from cuniform_torch.policies.checkpoint import load_policy, policy_checkpoint, save_policy
from cuniform_torch.policies.mlp import MAX_FREQUENCIES, MLPConfig, MLPPolicy, default_feature_scale
from cuniform_torch.policies.table import TablePolicy
from cuniform_torch.tables.file import Table, read_table_sha256
from precompute.api import library_errors
from precompute.cli import (
    OUT,
    ArgumentParser,
    add_config_args,
    add_dataclass_args,
    add_system_module_arg,
    check_output_file,
    check_output_folder,
    cli_main,
    config_text,
    dataclass_from_config,
    device_arg,
    import_system_modules,
    int_in,
    non_negative_int,
    positive_float,
    positive_int,
    threads_arg,
)
from training.sets.distill import distill_set
from training.tables.config import DistillConfig, with_epochs
from training.tables.evaluate import compare, kl_per_level, sizes
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


class _Parser(ArgumentParser):
    def error(self, message: str) -> typing.NoReturn:  # main returns 2 rather than exiting
        raise UsageError(message)


def make_parser() -> ArgumentParser:
    """A flag per :class:`DistillConfig` field (:func:`precompute.cli.add_dataclass_args`: its type, its
    docstring and its default, which lives only in the dataclass)."""
    parser = _Parser(prog="python -m training.distill", description=__doc__.splitlines()[0])
    add_dataclass_args(parser, DistillConfig, exclude=("system_module",), arg_types={
        **{name: int_in(1, 65536) for name in ("hidden", "layers")}, "frequencies": int_in(0, MAX_FREQUENCIES),
        "epochs": positive_int,
        "batch_size": positive_int, "val_points": positive_int, "patience": positive_int, "eval_every": positive_int,
        "seed": non_negative_int, "jitter": int_in(0, 1000), "threads": threads_arg, "device": device_arg,
        "lr": positive_float})
    add_system_module_arg(parser)  # repeatable, as in every entry point
    add_config_args(parser, "the distillation's settings")
    return parser


def parse_args(argv: Sequence[str] | None = None) -> DistillConfig:
    """Flags -> a :class:`DistillConfig` (each flag's type checked as it is parsed; :class:`UsageError` when bad).
    :func:`distill`, the library edge, checks the whole config once (:func:`check_config`)."""
    return dataclass_from_config(DistillConfig, make_parser().parse_args(argv), required=("tables",))


def check_config(cfg: DistillConfig) -> DistillConfig:
    """``cfg`` checked (:class:`UsageError` naming the bad setting by its flag), its derived fields filled."""
    for name in ("hidden", "layers", "epochs", "batch_size", "val_points", "patience", "eval_every"):
        if getattr(cfg, name) is not None and getattr(cfg, name) < 1:
            raise UsageError(f"--{name.replace('_', '-')} must be a positive integer, got {getattr(cfg, name)}")
    if cfg.threads < 0:
        raise UsageError(f"--threads must be >= 0, got {cfg.threads}")
    if not 0 <= cfg.frequencies <= MAX_FREQUENCIES:
        raise UsageError(f"--frequencies must be in 0..{MAX_FREQUENCIES}, got {cfg.frequencies}")
    if cfg.jitter < 0:
        raise UsageError(f"--jitter must be >= 0, got {cfg.jitter}")
    if not (math.isfinite(cfg.lr) and cfg.lr > 0):
        raise UsageError(f"--lr must be a positive number, got {cfg.lr}")
    if any(n < 1 for n in cfg.eval_samples):
        raise UsageError(f"--eval-samples must be positive integers, got {cfg.eval_samples}")
    try:
        device = torch.device(cfg.device)
    except RuntimeError as exc:
        raise UsageError(f"--device {cfg.device!r}: {exc}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise UsageError(f"--device {cfg.device}: CUDA is not available here")
    if any(Path(p).is_dir() for p in cfg.tables) and len(cfg.tables) > 1:
        raise UsageError("--tables: a table-set folder is distilled alone (give the folder, or table files)")
    for path in cfg.tables:
        if not Path(path).is_file() and not Path(path).is_dir():
            raise UsageError(f"--tables: no table file at {path}")
    if cfg.out is None:
        cfg.out = str(OUT / f"{Path(cfg.tables[0]).stem}.policy.pt")
    check_outputs(cfg)
    return cfg


def output_paths(cfg: DistillConfig) -> tuple[Path, Path, Path]:
    """``(checkpoint, training state, comparison JSON)`` of a config whose ``out`` is filled."""
    assert cfg.out is not None
    out = Path(cfg.out)
    return out, out.with_name(out.name + ".train.pt"), out.with_name(out.stem + ".comparison.json")


def check_outputs(cfg: DistillConfig) -> None:
    """Before training: every output can be written (a folder named like a file, an unwritable folder, a file
    as ``--logdir`` would otherwise surface after the training only)."""
    out, state_path, comparison_path = output_paths(cfg)
    check_output_file(out, "--out", example="policy.pt")
    for path in (state_path, comparison_path):
        if path.is_dir():
            raise UsageError(f"--out {out}: {path}, which distillation writes, is a folder")
    check_output_folder(cfg.logdir, "--logdir")


def read_tables(paths: Sequence[str]) -> tuple[list[Table], list[str]]:
    """Read every table (:class:`TableError` when one is bad) and check they share the system and the actions:
    ``(tables, their files' sha256)``, each file read once (the digest is of the bytes the table came from)."""
    read = [read_table_sha256(p, graph=False) for p in paths]  # the flow graph is not distilled
    tables = [t for t, _ in read]
    for path, table in zip(paths[1:], tables[1:]):
        if json.loads(table.system) != json.loads(tables[0].system):
            raise UsageError(f"{path} was built for {table.system}, but {paths[0]} for {tables[0].system}; "
                             "tables distilled together must share the system JSON")
        if table.actions.shape != tables[0].actions.shape or (table.actions != tables[0].actions).any():
            raise UsageError(f"{path} and {paths[0]} have different action sets")
    return tables, [sha for _, sha in read]


def distill(cfg: DistillConfig) -> int:
    """Train, checkpoint and compare (see the module docstring): the library function behind the command. 0, or
    a clear error (:class:`UsageError`, :class:`TableError`) before training starts."""
    import_system_modules(cfg.system_module)
    return _distill_checked(check_config(dataclasses.replace(cfg)))


def _distill_checked(cfg: DistillConfig) -> int:
    """:func:`distill` of a config :func:`check_config` has checked (each config is checked once)."""
    out = output_paths(cfg)[0]
    with exclusive_lock(out.with_name(out.name + ".lock"), what=f"--out {out}"):
        if Path(cfg.tables[0]).is_dir():
            return distill_set(cfg, *output_paths(cfg))  # a table set: pi(u | x, t, x0)
        return _distill(cfg)


def _distill(cfg: DistillConfig) -> int:
    """:func:`distill`, holding the lock of ``--out``."""
    wall_start = time.perf_counter()
    out, state_path, comparison_path = output_paths(cfg)
    device = torch.device(cfg.device)

    # ---- tables
    tables, table_shas = read_tables(cfg.tables)
    table = tables[0]
    cfg = with_epochs(cfg, sum(int(t.cells.shape[0]) for t in tables))
    system, T = table.make_system(), table.horizon
    grid = Grid.of(system)
    fingerprint = {**{k: getattr(cfg, k) for k in RESUME_KEYS}, "tables_sha256": table_shas}

    data_gen, val_gen = seed_run(cfg)

    # ---- data: every cell of every (table, level) group; the group of a cell sets its weight
    cells = pool_cells(tables, T, grid, cfg.val_points, val_gen, device)

    # ---- model and optimiser
    mlp_config = MLPConfig(state_dim=grid.dim, num_actions=table.actions.shape[0], horizon=T,
                           periodic=list(grid.periodic), feature_scale=default_feature_scale(cells.centres, grid),
                           hidden=cfg.hidden, layers=cfg.layers, frequencies=cfg.frequencies)
    model = MLPPolicy(mlp_config, system, torch.from_numpy(table.actions),
                      support=pooled_support(tables, T)).to(device)  # the cells it may answer confidently
    optimizer, scheduler = adam_cosine(model, cfg)

    # ---- resume, TensorBoard
    progress, writer = open_run(cfg, f"{Path(cfg.tables[0]).stem}__distill__{cfg.seed}__{int(time.time())}",
                                state_path, fingerprint, model, optimizer, scheduler, data_gen, device)
    try:
        table_policy = TablePolicy(table, device=device)
        x0 = table_policy.build_start.to(device=device, dtype=torch.float32)  # [d] the table's start
        figures = TableFigures(system, grid, table_policy, x0, T, cfg.eval_samples[0], cfg.seed, table.level_sizes)

        def evaluate(step: int) -> None:
            for level, kl in enumerate(kl_per_level(model, table, device=device)):
                writer.add_scalar(f"eval/kl_level_{level}", kl, step)
            figures.log(writer, model, step, f"epoch {step}")

        # ---- training loop; save looks save_train_state up here at each call (a test wraps it)
        run_epochs(cfg, progress, model, lambda x, t, r: model(x, t), optimizer, scheduler, cells, grid, data_gen,
                   device, writer, evaluate, lambda state: save_train_state(state_path, state), fingerprint,
                   "distill")

        # ---- checkpoint: the best validation state, with the final comparison as its metrics
        model.load_state_dict(progress.best_state)
        model.eval()
        report = compare(model, table, cfg.eval_samples, seed=cfg.seed, jitter_per_cell=cfg.jitter or 4, device=device)
        metrics: dict[str, Any] = {
            **best_metrics(progress), "kl_centres_mean": report["kl_centres"]["mean"],
            "kl_jitter_mean": report["kl_jitter"]["mean"], "kl_centres_per_level": report["kl_centres"]["per_level"],
        }
        for n, cov in report["coverage"].items():
            metrics[f"coverage_ratio_total_{n}"] = cov["ratio"]["total"]
            metrics[f"coverage_ratio_in_level_set_{n}"] = cov["ratio"]["in_level_set_sum"]
            metrics[f"coverage_ratio_min_level_{n}"] = cov["ratio"]["min_level"]
        source = {"path": str(cfg.tables[0]), "sha256": table_shas[0]}
        if len(cfg.tables) > 1:
            source["all_tables"] = json.dumps([{"path": str(p), "sha256": s} for p, s in zip(cfg.tables, table_shas)])
        save_policy(out, policy_checkpoint(model, table.system, source=source, metrics=metrics))

        # ---- final comparison: sizes, KL, coverage, fallbacks, wall time
        comparison = {
            "tables": [{"path": str(p), "sha256": s} for p, s in zip(cfg.tables, table_shas)],
            **run_facts(cfg, progress, out, wall_start), "sizes": sizes(table, cfg.tables[0], out), **report,
        }
        summary = write_comparison(writer, comparison_path, comparison, format_comparison, progress.epochs_run)
    finally:
        writer.close()
    say_written(summary, out, comparison_path, state_path, comparison["run"])
    return 0


def distill_policy(config: DistillConfig, *, progress: bool = False) -> MLPPolicy:
    """Distil ``config.tables`` into an MLP (module :mod:`training.distill`): pi(u | x, t) from table files, or
    the start-conditioned pi(u | x, t, x0) from one table-set folder. Writes the checkpoint ``config.out``
    (default ``out/<first table stem>.policy.pt``) atomically, its training state and comparison JSON beside it,
    and a TensorBoard run under ``config.logdir``. ``progress``: the epoch bar (``config.quiet=True`` keeps it off).

    :return: the trained policy, read back from its checkpoint (:func:`cuniform_torch.load_policy`)
    """
    if not isinstance(config, DistillConfig):
        raise ValueError(f"config must be a DistillConfig, got {type(config).__name__}")
    cfg = dataclasses.replace(config, quiet=config.quiet or not progress)

    def run() -> str:
        import_system_modules(cfg.system_module)
        checked = check_config(dataclasses.replace(cfg, tables=[str(t) for t in cfg.tables]))  # out filled
        _distill_checked(checked)
        assert checked.out is not None
        return checked.out

    if not cfg.tables:
        raise ValueError("DistillConfig.tables is empty: give table files, or one table-set folder")
    out = library_errors(run)
    return load_policy(out, device=cfg.device)


def format_comparison(c: dict[str, Any]) -> str:
    """A short human-readable summary of the comparison dict."""
    s = c["sizes"]
    lines = [
        f"distilled in {c['wall_seconds']['train']:.1f}s of training ({c['epochs_run']} epochs, best "
        f"{c['best_epoch']}, val KL {c['best_val_kl']:.4f})",
        f"sizes: table arrays {s['table_arrays_bytes']:,} B (file {s['table_file_bytes']:,} B), checkpoint "
        f"{s['checkpoint_bytes']:,} B: ratio {s['compression_ratio']:.2f}x (file {s['file_ratio']:.2f}x)",
        "level   cells  KL centres  KL jitter",
    ]
    for t, (n, a, b) in enumerate(zip(c["coverage"][next(iter(c["coverage"]))]["level_sizes"],
                                      c["kl_centres"]["per_level"], c["kl_jitter"]["per_level"])):
        lines.append(f"{t:5d} {n:7d} {a:11.4f} {b:10.4f}")
    lines.append(f" mean         {c['kl_centres']['mean']:11.4f} {c['kl_jitter']['mean']:10.4f}")
    for n, cov in c["coverage"].items():
        mlp, tab, ratio = cov["policy"], cov["table"], cov["ratio"]
        lines.append(f"coverage of {n} rollouts: total cells MLP {mlp['total']} / table {tab['total']} = "
                     f"{ratio['total']:.3f}; cells of L_t MLP {mlp['in_level_set_sum']} / table "
                     f"{tab['in_level_set_sum']} = {ratio['in_level_set_sum']:.3f}; "
                     f"worst level {ratio['min_level']:.3f}")
        lines.append("  per level (MLP/table): " + " ".join(f"{r:.2f}" for r in cov["ratio"]["in_level_set"]))
        lines.append(f"  table fallbacks: nearest {cov['table']['nearest_rate']:.2%}, "
                     f"uniform {cov['table']['miss_rate']:.2%} (MLP: 0, 0)")
    return "\n".join(lines)


@cli_main(interrupted="interrupted: no checkpoint written; rerun with --resume to continue from the last "
                      "finished epoch")
def main(argv: Sequence[str] | None = None) -> int:
    """Distil from the flags ``argv`` through the library function (:func:`training.distill_policy`): 0, or 2
    after one ``error: ...`` line, or 130 on Ctrl-C."""
    args = make_parser().parse_args(argv)
    cfg = dataclass_from_config(DistillConfig, args, required=("tables",))
    if args.print_config:  # the settings as a --config file, nothing run
        print(config_text(cfg))
        return 0
    distill_policy(cfg, progress=True)  # the library function a Python user calls
    return 0


if __name__ == "__main__":
    sys.exit(main())
