"""Train a map-conditioned policy pi(u | x, t, local map):  python -m training.maps.distill --maps DATASET ...

C-Free-Uniform (arXiv 2510.16905): one network for every map, trained by KL to each map's safe table
(data sets of format ``cuniform-map-dataset/1``, :mod:`training.maps.data`); the loop is :mod:`training.maps.train`.

* **TensorBoard** (``<logdir>/<first data set>__distill_maps__<seed>__<unix time>``; step = epoch):
  ``losses/train_kl`` (the epoch's level-weighted KL), ``losses/val_kl`` (the same at the held-out entries'
  cell centres), ``charts/learning_rate``, ``charts/epoch_seconds``; the config once as a markdown table.
* **Outputs.** The checkpoint ``--out`` (``cuniform-map-policy/1``, :mod:`cuniform_torch.maps.checkpoint`;
  atomic), holding the best validation epoch's weights (the last epoch's with ``--val-fraction 0``);
  ``<out>.train.pt``, the training state after every epoch (atomic): ``--resume`` continues from it and ends at
  the same weights as an uninterrupted run. The training time and the data set's size are printed.

``main(argv)`` returns 0, or 2 after one line ``error: ...`` (bad flags, unreadable data sets, a refused
resume, an output that cannot be written), or 130 on Ctrl-C.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
import typing
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from cuniform_torch.common.fileio import MAX_JSON_BYTES, exclusive_lock, read_capped_text
from cuniform_torch.maps.checkpoint import load_map_policy, map_policy_checkpoint, save_map_policy
from cuniform_torch.maps.policy import MapPolicy
from precompute.api import library_errors
from precompute.cli import (
    OUT,
    RUNS,
    ArgumentParser,
    CLIError,
    add_config_args,
    add_dataclass_args,
    check_output_file,
    check_output_folder,
    cli_main,
    config_text,
    dataclass_from_config,
    device_arg,
    int_in,
    non_negative_int,
    positive_float,
    positive_int,
    threads_arg,
)
from training.maps.data import load_map_data
from training.maps.train import Trainer, make_policy, split_entries
from training.tables.loop import log_hyperparameters
from training.tables.train_state import UsageError, load_train_state, save_train_state

TRAIN_STATE_FORMAT = "cuniform-distill-maps-state/1"


@dataclass
class MapDistillConfig:
    """Settings of one training run; every field is a flag (``--batch-size``, ...)."""

    maps: list[str] = field(default_factory=list)
    """data set folders (cuniform-map-dataset/1); several must share system, grid, actions and patch"""
    out: str | None = None
    """checkpoint to write (default: out/<first data set name>.map_policy.pt)"""
    hidden: int = 128
    """hidden units per layer of the state / map MLP"""
    layers: int = 2
    """hidden layers of that MLP"""
    embed: int = 32
    """map embedding size"""
    channels: int = 8
    """base channel count of the map encoder (c, 2c, 2c)"""
    local_features: int = 0
    """channels of the local feature map sampled at each state and ahead of it (0: none, the embedding only)"""
    epochs: int = 200
    """passes over the training rows"""
    lr: float = 3e-3
    """Adam's initial learning rate, cosine-annealed per epoch to lr / 100"""
    batch_size: int = 2048
    """samples per optimiser step (they mix entries)"""
    jitter: int = 2
    """points per cell per epoch drawn uniformly inside it, on top of its centre"""
    val_fraction: float = 0.1
    """share of the entries held out for the validation KL (0: none)"""
    seed: int = 0
    """seed of the weights, the split, the jitter and the shuffling"""
    device: str = "cpu"
    """torch device (cpu, cuda, cuda:1, ...)"""
    threads: int = 1
    """torch CPU threads (0: torch's choice)"""
    logdir: str = str(RUNS)
    """folder of the TensorBoard runs"""
    quiet: bool = False
    """no progress bar"""
    resume: bool = False
    """continue from <out>.train.pt (refused when the settings or the data sets differ)"""
    skip_deep_checks: bool = False
    """trust the data sets' action rows: skip recomputing every table's propagation (rows permuted within a level
    then go unnoticed; the other checks still run)"""


RESUME_KEYS = ("hidden", "layers", "embed", "channels", "epochs", "lr", "batch_size", "jitter", "val_fraction", "seed")


class _Parser(ArgumentParser):
    def error(self, message: str) -> typing.NoReturn:
        raise CLIError(message)


MAP_DISTILL_TYPES = {**{name: int_in(1, 65536) for name in ("hidden", "layers", "embed", "channels")},
                     "epochs": positive_int, "batch_size": positive_int, "jitter": int_in(0, 1000),
                     "local_features": int_in(0, 65536), "lr": positive_float, "seed": non_negative_int,
                     "device": device_arg, "threads": threads_arg}
"""the :class:`MapDistillConfig` flags' values, checked as they parse (:mod:`precompute.cli`)"""


def make_parser() -> ArgumentParser:
    parser = _Parser(prog="python -m training.maps.distill", description=__doc__.splitlines()[0])
    add_dataclass_args(parser, MapDistillConfig, arg_types=MAP_DISTILL_TYPES)
    add_config_args(parser, "the training's settings")
    return parser


def parse_args(argv: Sequence[str] | None = None) -> MapDistillConfig:
    """Flags -> a checked config (``out`` filled); :class:`CLIError` when bad."""
    return check_map_config(dataclass_from_config(MapDistillConfig, make_parser().parse_args(argv), required=("maps",)))


def check_map_config(cfg: MapDistillConfig) -> MapDistillConfig:
    """``cfg`` checked once at the edge (each field as its flag would parse it; the data sets exist; the outputs
    can be written), ``out`` filled: a new config, or :class:`CLIError` naming the field's flag."""
    cfg = dataclasses.replace(cfg, maps=[str(m) for m in cfg.maps])
    if not cfg.maps:
        raise CLIError("--maps: give at least one map-table data set folder")
    for name, parse in MAP_DISTILL_TYPES.items():
        value = getattr(cfg, name)
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise CLIError(f"--{name.replace('_', '-')} must be a {type(getattr(MapDistillConfig(), name)).__name__}, "
                           f"got {value!r}")
        try:
            parse(str(value))
        except (argparse.ArgumentTypeError, ValueError) as exc:
            raise CLIError(f"--{name.replace('_', '-')}: {exc}") from None
    if not 0 <= cfg.val_fraction < 1:
        raise CLIError(f"--val-fraction must be in [0, 1), got {cfg.val_fraction}")
    for folder in cfg.maps:
        if not (Path(folder) / "dataset.json").is_file():
            raise CLIError(f"--maps: no map-table data set (dataset.json) in {folder}")
    if cfg.out is None:
        cfg.out = str(OUT / f"{Path(cfg.maps[0]).name}.map_policy.pt")
    check_output_file(cfg.out, "--out", example="map_policy.pt")
    check_output_folder(cfg.logdir, "--logdir")
    return cfg


def distill_maps(cfg: MapDistillConfig) -> int:
    """Train and checkpoint (module docstring), holding ``<out>.lock``; ``cfg`` checked (:func:`check_map_config`)."""
    assert cfg.out is not None, "check_map_config fills out"
    out = Path(cfg.out)
    with exclusive_lock(out.with_name(out.name + ".lock"), what=f"--out {out}"):
        return _run(cfg, out, out.with_name(out.name + ".train.pt"))


def _run(cfg: MapDistillConfig, out: Path, state_path: Path) -> int:
    device = torch.device(cfg.device)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    data = load_map_data(cfg.maps, deep_checks=not cfg.skip_deep_checks)
    fingerprint = {**{k: getattr(cfg, k) for k in RESUME_KEYS}, "maps_sha256": [s["sha256"] for s in data.sources]}
    if cfg.local_features:  # only when used, so a training state written before the option still resumes
        fingerprint["local_features"] = cfg.local_features
    torch.manual_seed(cfg.seed)
    split = split_entries(data, cfg.val_fraction, cfg.seed)
    policy = make_policy(data, cfg.hidden, cfg.layers, cfg.embed, cfg.channels, cfg.local_features)
    trainer = Trainer(data, split, policy, cfg.epochs, cfg.lr, cfg.batch_size, cfg.jitter, device)
    gen = torch.Generator().manual_seed(cfg.seed)
    epoch, best_val, best_epoch, seconds = 0, math.inf, 0, 0.0
    best = {k: v.detach().clone() for k, v in trainer.policy.state_dict().items()}
    run_name = f"{Path(cfg.maps[0]).name}__distill_maps__{cfg.seed}__{int(time.time())}"
    if cfg.resume:
        state = load_train_state(state_path, fingerprint, TRAIN_STATE_FORMAT)
        saved_local = state["fingerprint"].get("local_features", 0)
        if saved_local != cfg.local_features:  # the check above only sees the keys this run's fingerprint has
            raise UsageError(f"--resume: {state_path} was written by a different run (local_features: saved "
                             f"{saved_local!r}, now {cfg.local_features!r})")
        trainer.load_state(state["trainer"])
        gen.set_state(state["rng_data"])
        torch.set_rng_state(state["rng_torch"])
        best = {k: v.to(device) for k, v in state["best_model"].items()}
        epoch, best_val, best_epoch, seconds = state["epoch"], state["best_val"], state["best_epoch"], state["seconds"]
        run_name = state["run_name"]
    say = (lambda *a, **k: None) if cfg.quiet else print  # a library call is quiet unless asked
    say(f"data: {data.num_entries} entries ({len(split.val_entries)} held out), {data.centres.shape[0]:,} rows, "
          f"patches {list(data.spec.shape)} at {data.spec.resolution} m, {data.nbytes:,} bytes in "
          f"{len(data.sources)} data set(s); policy: {trainer.policy.num_parameters:,} parameters", flush=True)
    writer = SummaryWriter(str(Path(cfg.logdir) / run_name), purge_step=epoch + 1 if cfg.resume else None)
    try:
        if not cfg.resume:
            log_hyperparameters(writer, cfg)
        bar = tqdm(range(epoch, cfg.epochs), initial=epoch, total=cfg.epochs, disable=cfg.quiet, desc="distill_maps",
                   unit="epoch")
        for epoch_index in bar:
            start = time.perf_counter()
            scalars = trainer.epoch(gen)
            seconds += time.perf_counter() - start
            epoch = epoch_index + 1
            score = scalars["val_kl"] if not math.isnan(scalars["val_kl"]) else scalars["train_kl"]
            if score < best_val or not split.val_entries:
                best_val, best_epoch = score, epoch
                best = {k: v.detach().clone() for k, v in trainer.policy.state_dict().items()}
            for key in ("train_kl", "val_kl"):
                if not math.isnan(scalars[key]):
                    writer.add_scalar(f"losses/{key}", scalars[key], epoch)
            writer.add_scalar("charts/learning_rate", scalars["learning_rate"], epoch)
            writer.add_scalar("charts/epoch_seconds", time.perf_counter() - start, epoch)
            bar.set_postfix(train_kl=f"{scalars['train_kl']:.4f}", val_kl=f"{scalars['val_kl']:.4f}")
            save_train_state(state_path, {
                "format": TRAIN_STATE_FORMAT, "fingerprint": fingerprint, "run_name": run_name, "epoch": epoch,
                "trainer": trainer.state(), "best_model": best, "best_val": best_val, "best_epoch": best_epoch,
                "seconds": seconds, "rng_data": gen.get_state(), "rng_torch": torch.get_rng_state()})
        bar.close()
    finally:
        writer.close()
    trainer.policy.load_state_dict(best)
    metrics = {"best_epoch": best_epoch, "best_val_kl": best_val if split.val_entries else math.nan,
               "train_seconds": seconds, "entries": data.num_entries, "rows": int(data.centres.shape[0])}
    radii = {json.loads(read_capped_text(Path(src["path"]) / "dataset.json", MAX_JSON_BYTES, "the data-set manifest")).get("radius") for src in data.sources}
    if len(radii) == 1 and isinstance(next(iter(radii)), (int, float)):
        metrics["robot_radius"] = float(next(iter(radii)))  # the obstacles' inflation the tables were built with
    metrics = {k: v for k, v in metrics.items() if not (isinstance(v, float) and math.isnan(v))}
    source = {f"map_{i}": f"{s['path']} sha256={s['sha256']}" for i, s in enumerate(data.sources)}
    save_map_policy(out, map_policy_checkpoint(trainer.policy.cpu(), data.system_json, source, metrics))
    kind = "val KL" if split.val_entries else "train KL"
    say(f"trained in {seconds:.1f} s ({epoch} epochs; best epoch {best_epoch}, {kind} {best_val:.4f}); "
          f"wrote {out} and {state_path}; TensorBoard: {Path(cfg.logdir) / run_name}")
    return 0


def train_map_policy(config: MapDistillConfig, *, progress: bool = False) -> MapPolicy:
    """Train a map-conditioned policy on ``config.maps`` (map-table data sets, :mod:`training.maps.distill`).
    Writes the checkpoint ``config.out`` (default ``out/<first data set>.map_policy.pt``) atomically, the
    training state beside it and a TensorBoard run under ``config.logdir``. ``progress``: the epoch bar and the
    summary lines (``config.quiet=True`` keeps them off).

    :return: the trained policy, read back from its checkpoint (:func:`cuniform_torch.maps.load_map_policy`)
    """
    if not isinstance(config, MapDistillConfig):
        raise ValueError(f"config must be a MapDistillConfig, got {type(config).__name__}")
    cfg = dataclasses.replace(config, quiet=config.quiet or not progress)

    def run() -> str:
        checked = check_map_config(cfg)
        distill_maps(checked)
        assert checked.out is not None
        return checked.out

    out = library_errors(run)
    return load_map_policy(Path(out), device=cfg.device)


@cli_main(interrupted="interrupted: no checkpoint written; rerun with --resume to continue from the last "
                      "finished epoch")
def main(argv: Sequence[str] | None = None) -> int:
    """Train from the flags ``argv``: 0, or 2 after one ``error: ...`` line, or 130 on Ctrl-C."""
    args = make_parser().parse_args(argv)
    cfg = dataclass_from_config(MapDistillConfig, args, required=("maps",))
    if args.print_config:  # the settings as a --config file, nothing run
        print(config_text(cfg))
        return 0
    train_map_policy(cfg, progress=True)  # the library function a Python user calls (it checks cfg)
    return 0


if __name__ == "__main__":
    sys.exit(main())
