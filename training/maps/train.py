"""The training loop of a map-conditioned policy (what ``python -m training.maps.distill`` runs).

Shapes: R rows, N samples of an epoch, B of a batch, U distinct maps in a batch, d state dimensions, A actions,
E map embedding, H x W patch cells.

* **Split.** ``val_fraction`` of the entries (maps), drawn with the seed, are held out of the training data;
  the validation KL is measured on their cells' centres. The best validation epoch's weights are kept.
* **Samples.** Every epoch: each training row's cell centre plus ``jitter`` points uniform in its cell (angles
  wrapped), shuffled over all entries, so a batch mixes maps; each distinct map of a batch is encoded once
  (its embedding and, with ``local_features``, its local feature map, which each row then samples at its state).
* **Loss.** KL(table row || policy), level-weighted as in ``training.distill``: a sample's weight is 1 / (samples
  of its (entry, level) group) / (groups), so every level of every map counts the same; a batch's loss is its
  weighted sum scaled by (epoch samples / batch samples).
* **Optimiser.** Adam, learning rate cosine-annealed per epoch from ``lr`` to ``lr / 100``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from cuniform_torch.grid.cells import Grid
from cuniform_torch.maps.policy import MapPolicy, MapPolicyConfig
from training.maps.data import MapData

__all__ = ["Split", "split_entries", "make_policy", "level_weights", "kl_rows", "jitter_rows", "Trainer"]


@dataclass
class Split:
    """Rows of the training and the validation entries: ``train [R_t]``, ``val [R_v]`` int64 row indices."""

    train: Tensor
    val: Tensor
    val_entries: list[int]


def split_entries(data: MapData, val_fraction: float, seed: int) -> Split:
    """Hold out ``round(val_fraction * M)`` entries (at least 1 when ``val_fraction > 0``), drawn with ``seed``."""
    M = data.num_entries
    n_val = 0 if val_fraction <= 0 else max(1, round(val_fraction * M))
    if n_val >= M:
        raise ValueError(f"--val-fraction {val_fraction} holds out {n_val} of the {M} entries and leaves none to "
                         f"train on; lower it (0: no validation)")
    held = torch.randperm(M, generator=torch.Generator().manual_seed(seed))[:n_val]
    is_val = torch.zeros(M, dtype=torch.bool)
    is_val[held] = True
    rows_val = is_val[data.entry]  # [R]
    return Split(torch.nonzero(~rows_val).squeeze(1), torch.nonzero(rows_val).squeeze(1), sorted(held.tolist()))


def make_policy(data: MapData, hidden: int, layers: int, embed: int, channels: int,
                local_features: int = 0) -> MapPolicy:
    """A fresh policy for ``data``: feature scales from the largest |cell centre| per non-periodic dimension."""
    grid = Grid.of(data.system)
    scale = data.centres.abs().amax(dim=0).tolist() if data.centres.shape[0] else [1.0] * grid.dim
    scale = [1.0 if (p or s == 0) else float(s) for s, p in zip(scale, grid.periodic)]
    config = MapPolicyConfig(state_dim=grid.dim, num_actions=data.actions.shape[0], horizon=data.horizon,
                             periodic=list(grid.periodic), feature_scale=scale, patch=data.spec.to_dict(),
                             hidden=hidden, layers=layers, embed=embed, channels=channels,
                             local_features=local_features)
    return MapPolicy(config, data.system, data.actions)


def level_weights(group: Tensor) -> Tensor:
    """``group [N]`` -> weights ``[N]`` float64: 1 / (samples of its group) / (groups present); sums to 1."""
    _, inverse, counts = torch.unique(group, return_inverse=True, return_counts=True)
    return 1.0 / (counts[inverse].double() * counts.shape[0])


def kl_rows(p: Tensor, log_q: Tensor) -> Tensor:
    """``[N, A]`` targets and model log-probabilities -> ``[N]`` KL(p || q), 0 log 0 = 0."""
    return (torch.xlogy(p, p) - p * log_q).sum(dim=1)


def jitter_rows(centres: Tensor, grid: Grid, generator: torch.Generator) -> Tensor:
    """``centres [N, d]`` -> points uniform in their cells ``[N, d]`` (angles wrapped to the grid's range)."""
    u = torch.rand(centres.shape, generator=generator, dtype=centres.dtype) - 0.5  # [N, d]
    return grid.wrap(centres + u * torch.tensor(grid.cell_size, dtype=centres.dtype))


class Trainer:
    """One policy, its optimiser and schedule, and the data on the device; :meth:`epoch` trains one pass."""

    def __init__(self, data: MapData, split: Split, policy: MapPolicy, epochs: int, lr: float, batch_size: int,
                 jitter: int, device: torch.device):
        self.data, self.split, self.policy = data, split, policy.to(device)
        self.grid, self.device = Grid.of(data.system), device
        self.batch_size, self.jitter = batch_size, jitter
        self.optimizer = torch.optim.Adam(self.policy.parameters(), lr=lr)
        self.scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(self.optimizer, T_max=epochs, eta_min=lr / 100)
        self.patches = data.patches.to(device=device, dtype=torch.float32)  # [M, H, W]
        self.probs = data.probs.to(device)  # [R, A]

    def _logits(self, x: Tensor, t: Tensor, entry: Tensor) -> Tensor:
        """Logits ``[B, A]``; each distinct map of the batch encoded once (embedding, local feature map)."""
        maps, inverse = torch.unique(entry, return_inverse=True)  # [U], [B]
        patches = self.patches.index_select(0, maps)  # [U, H, W]
        embedding = self.policy.encode(patches)  # [U, E]
        local = self.policy.encode_local(patches) if self.policy.local is not None else None  # [U, C, H, W]
        return self.policy.logits(x, t, embedding.index_select(0, inverse), local, inverse)

    def epoch(self, generator: torch.Generator) -> dict[str, float]:
        """One pass over the training rows (centres + jitter), then the validation KL; the epoch's scalars."""
        self.policy.train()
        data, rows = self.data, self.split.train
        rows = rows.repeat(1 + self.jitter)  # [N]
        x = data.centres[rows]
        n_rows = self.split.train.shape[0]
        if self.jitter:
            x[n_rows:] = jitter_rows(x[n_rows:], self.grid, generator)
        w = level_weights(data.group[rows])  # [N]
        N = rows.shape[0]
        perm = torch.randperm(N, generator=generator)
        x, w = x.to(self.device, torch.float32), w.to(self.device)
        t, entry, rows_d = data.level[rows].to(self.device), data.entry[rows].to(self.device), rows.to(self.device)
        perm = perm.to(self.device)
        train_kl = 0.0
        for lo in range(0, N, self.batch_size):
            idx = perm[lo:lo + self.batch_size]
            log_q = torch.log_softmax(self._logits(x[idx], t[idx], entry[idx]), dim=1)  # [B, A]
            weighted = (w[idx] * kl_rows(self.probs[rows_d[idx]], log_q)).sum()
            self.optimizer.zero_grad(set_to_none=True)
            (weighted * (N / idx.shape[0])).backward()
            self.optimizer.step()
            train_kl += float(weighted.detach())
        lr = self.optimizer.param_groups[0]["lr"]
        self.scheduler.step()
        return {"train_kl": train_kl, "val_kl": self.validate(), "learning_rate": lr}

    @torch.no_grad()
    def validate(self) -> float:
        """Level-weighted KL at the held-out entries' cell centres (NaN without a held-out entry)."""
        rows = self.split.val
        if rows.shape[0] == 0:
            return math.nan
        self.policy.eval()
        data, total = self.data, 0.0
        w = level_weights(data.group[rows]).to(self.device)
        for lo in range(0, rows.shape[0], self.batch_size):
            r = rows[lo:lo + self.batch_size]
            x = data.centres[r].to(self.device, torch.float32)
            log_q = torch.log_softmax(self._logits(x, data.level[r].to(self.device), data.entry[r].to(self.device)), 1)
            total += float((w[lo:lo + self.batch_size] * kl_rows(self.probs[r.to(self.device)], log_q)).sum())
        return total

    def state(self) -> dict[str, Any]:
        return {"model": self.policy.state_dict(), "optimizer": self.optimizer.state_dict(),
                "scheduler": self.scheduler.state_dict()}

    def load_state(self, state: dict[str, Any]) -> None:
        self.policy.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
