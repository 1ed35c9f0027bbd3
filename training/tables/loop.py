"""The epoch loop shared by :mod:`training.distill` and :mod:`training.sets.distill`: one KL training pass over
jittered cells, the validation KL / argmax accuracy, early stopping with the best state, the TensorBoard scalars
and the training state written after every epoch (read back by ``--resume``); :func:`run_epochs` is the loop.

Shapes: C cells, N samples of an epoch, B of a batch, V validation points, d state dimensions, A actions,
G (table, level) groups.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor
from tqdm import tqdm

from cuniform_torch.grid.cells import Grid
from training.tables.evaluate import kl_rows
from training.tables.samples import PooledCells, level_weights, make_samples
from training.tables.train_state import TRAIN_STATE_FORMAT

__all__ = ["Progress", "kl_epoch", "validate", "log_hyperparameters", "log_epoch_scalars", "run_epochs"]

Forward = Callable[[Tensor, Tensor, Tensor], Tensor]
"""``forward(x [B, d], t [B], rows [B])`` -> logits ``[B, A]`` (rows: the samples' cells, for per-cell inputs)."""


def _clone(model: torch.nn.Module) -> dict[str, Tensor]:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


@dataclass
class Progress:
    """Where a run stands: epochs done, the best validation epoch and its weights, early stopping, time."""

    run_name: str
    best_state: dict[str, Tensor]
    epochs_run: int = 0
    best_val: float = math.inf
    best_epoch: int = 0
    bad_epochs: int = 0
    train_seconds: float = 0.0
    finished: bool = False

    @classmethod
    def start(cls, model: torch.nn.Module, run_name: str) -> Progress:
        """A fresh run: the initial weights count as the best so far."""
        return cls(run_name, _clone(model))

    def restore(self, state: dict[str, Any], model: torch.nn.Module, optimizer: torch.optim.Optimizer,
                scheduler: Any, data_gen: torch.Generator, device: torch.device) -> None:
        """Load a saved training state (:func:`training.tables.train_state.load_train_state`) into the run's objects."""
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        torch.set_rng_state(state["rng_torch"])
        data_gen.set_state(state["rng_data"])
        self.best_state = {k: v.to(device) for k, v in state["best_model"].items()}
        self.epochs_run, self.best_val, self.best_epoch = state["epoch"], state["best_val"], state["best_epoch"]
        self.bad_epochs, self.train_seconds, self.finished = state["bad_epochs"], state["train_seconds"], state["finished"]
        self.run_name = state["run_name"]  # the resumed run logs on into the same TensorBoard folder

    def update(self, val_kl: float, epoch: int, model: torch.nn.Module, patience: int, epochs: int) -> None:
        """After 0-based ``epoch``: keep the best weights, count the epochs without improvement, stop or not."""
        if val_kl < self.best_val:
            self.best_val, self.best_epoch, self.bad_epochs = val_kl, epoch + 1, 0
            self.best_state = _clone(model)
        else:
            self.bad_epochs += 1
        self.finished = self.bad_epochs >= patience or epoch + 1 == epochs

    def state(self, fingerprint: dict[str, Any], model: torch.nn.Module, optimizer: torch.optim.Optimizer,
              scheduler: Any, data_gen: torch.Generator) -> dict[str, Any]:
        """The training state to save (format ``cuniform-distill-state/1``)."""
        return {
            "format": TRAIN_STATE_FORMAT, "fingerprint": fingerprint, "run_name": self.run_name,
            "epoch": self.epochs_run, "model": model.state_dict(), "optimizer": optimizer.state_dict(),
            "scheduler": scheduler.state_dict(), "best_model": self.best_state, "best_val": self.best_val,
            "best_epoch": self.best_epoch, "bad_epochs": self.bad_epochs, "train_seconds": self.train_seconds,
            "finished": self.finished, "rng_torch": torch.get_rng_state(), "rng_data": data_gen.get_state(),
        }


def kl_epoch(forward: Forward, optimizer: torch.optim.Optimizer, centres: Tensor, grid: Grid, levels: Tensor,
             group: Tensor, G: int, probs: Tensor, jitter: int, batch_size: int, data_gen: torch.Generator,
             device: torch.device) -> float:
    """One pass over ``centres [C, d]`` plus ``jitter`` fresh points per cell, shuffled; the epoch's exact
    level-weighted KL. A batch's loss is its weighted sum scaled by (epoch samples / batch samples)."""
    rows, x = make_samples(centres, grid, jitter, True, data_gen)
    w = level_weights(group[rows], G).to(device)  # [N], sums to 1
    N = rows.shape[0]
    perm = torch.randperm(N, generator=data_gen).to(device)
    x, t, rows = x.to(device=device, dtype=torch.float32), levels[rows].to(device), rows.to(device)
    train_kl = 0.0
    for lo in range(0, N, batch_size):
        idx = perm[lo:lo + batch_size]
        r = rows[idx]
        log_q = torch.log_softmax(forward(x[idx], t[idx], r), dim=1)  # [B, A]
        weighted = (w[idx] * kl_rows(probs[r], log_q)).sum()
        loss = weighted * (N / idx.shape[0])  # unbiased estimate of the epoch's level-weighted KL
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        train_kl += float(weighted.detach())
    return train_kl


@torch.no_grad()
def validate(logits: Tensor, probs: Tensor, best_rows: Tensor, val_rows: Tensor, val_w: Tensor) -> tuple[float, float]:
    """``logits [V, A]`` at the validation points -> (level-weighted KL, level-weighted share whose argmax is one
    of the table row's most likely actions ``best_rows [C, A]``)."""
    val_kl = float((val_w * kl_rows(probs[val_rows], torch.log_softmax(logits, dim=1))).sum())
    hit = best_rows[val_rows].gather(1, logits.argmax(dim=1, keepdim=True)).squeeze(1)  # [V]
    return val_kl, float((val_w * hit).sum())


def log_hyperparameters(writer: Any, cfg: Any) -> None:
    """The config dataclass ``cfg`` once, as a markdown table (``hyperparameters``)."""
    writer.add_text("hyperparameters", "|param|value|\n|-|-|\n" + "\n".join(
        f"|{k}|{v}|" for k, v in dataclasses.asdict(cfg).items()))


def log_epoch_scalars(writer: Any, step: int, train_kl: float, val_kl: float, val_acc: float, lr: float,
                      epoch_start: float) -> None:
    """The ``losses/`` and ``charts/`` scalars of one epoch (``epoch_start``: its time.perf_counter())."""
    writer.add_scalar("losses/train_kl", train_kl, step)
    writer.add_scalar("losses/val_kl", val_kl, step)
    writer.add_scalar("charts/val_argmax_accuracy", val_acc, step)
    writer.add_scalar("charts/learning_rate", lr, step)
    writer.add_scalar("charts/epoch_seconds", time.perf_counter() - epoch_start, step)


def run_epochs(cfg: Any, progress: Progress, model: torch.nn.Module, forward: Forward,
               optimizer: torch.optim.Optimizer, scheduler: Any, cells: PooledCells, grid: Grid,
               data_gen: torch.Generator, device: torch.device, writer: Any, evaluate: Callable[[int], None],
               save: Callable[[dict[str, Any]], None], fingerprint: dict[str, Any], desc: str) -> None:
    """The epochs from ``progress.epochs_run`` to ``cfg.epochs`` (or early stopping): a KL pass over ``cells``,
    the validation KL and accuracy of ``forward`` at their validation points, the scalars, ``evaluate(step)``
    every ``cfg.eval_every`` epochs and at the last, and ``save(state)`` of the training state after every
    epoch; a progress bar named ``desc``."""
    bar = tqdm(range(progress.epochs_run, cfg.epochs), initial=progress.epochs_run, total=cfg.epochs,
               disable=cfg.quiet or progress.finished, desc=desc, unit="epoch")
    for epoch in bar:
        if progress.finished:
            break
        epoch_start = time.perf_counter()
        model.train()
        train_kl = kl_epoch(forward, optimizer, cells.centres, grid, cells.levels, cells.group, cells.G, cells.probs,
                            cfg.jitter, cfg.batch_size, data_gen, device)
        lr = optimizer.param_groups[0]["lr"]
        scheduler.step()

        # validation: level-weighted KL and argmax agreement on the fixed jittered points
        model.eval()
        with torch.no_grad():
            logits = forward(cells.val_x, cells.val_t, cells.val_rows)  # [V, A]
            val_kl, val_acc = validate(logits, cells.probs, cells.best_rows, cells.val_rows, cells.val_w)
        progress.update(val_kl, epoch, model, cfg.patience, cfg.epochs)
        progress.train_seconds += time.perf_counter() - epoch_start

        step = progress.epochs_run = epoch + 1
        log_epoch_scalars(writer, step, train_kl, val_kl, val_acc, lr, epoch_start)
        if step % cfg.eval_every == 0 or progress.finished:
            evaluate(step)
        bar.set_postfix(train_kl=f"{train_kl:.4f}", val_kl=f"{val_kl:.4f}", best=progress.best_epoch)
        save(progress.state(fingerprint, model, optimizer, scheduler, data_gen))
    bar.close()
