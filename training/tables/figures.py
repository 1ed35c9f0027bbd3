"""The distillation's TensorBoard figures: rollouts of the table and of the MLP side by side, and coverage."""

from __future__ import annotations

import matplotlib.pyplot as plt
import torch

from cuniform_torch.metrics import uniform_ceiling

__all__ = ["trajectory_figure", "coverage_figure"]

plt.switch_backend("Agg")  # figures are only rendered into TensorBoard


def trajectory_figure(table_states: torch.Tensor, mlp_states: torch.Tensor, title: str) -> plt.Figure:
    """xy paths (or x against t for a 1-D system) of table rollouts and MLP rollouts, side by side."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5))
    for ax, states, name in zip(axes, (table_states, mlp_states), ("table", "MLP")):
        s = states.detach().cpu().numpy()  # [N, T+1, d]
        if s.shape[2] >= 2:
            color = "tab:blue" if name == "table" else "tab:orange"
            ax.plot(s[:, :, 0].T, s[:, :, 1].T, lw=0.5, alpha=0.35, color=color)
            ax.set_xlabel("x")
            ax.set_ylabel("y")
            ax.set_aspect("equal", adjustable="box")
        else:
            ax.plot(s[:, :, 0].T, lw=0.5, alpha=0.35)
            ax.set_xlabel("t")
            ax.set_ylabel("x")
        ax.set_title(f"{name}: {s.shape[0]} rollouts")
    axes[1].set_xlim(axes[0].get_xlim())  # the same view on both sides
    axes[1].set_ylim(axes[0].get_ylim())
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def coverage_figure(table_cov: list[int], mlp_cov: list[int], level_sizes: list[int], n: int, title: str) -> plt.Figure:
    """Cells of L_t reached at step t by n rollouts, table vs MLP, with |L_t| and the uniform-draw ceiling."""
    fig, ax = plt.subplots(figsize=(7, 4.5))
    t = range(len(level_sizes))
    ax.plot(t, level_sizes, "k:", label="|L_t|")
    ax.plot(t, [uniform_ceiling(m, n) for m in level_sizes], "k--", lw=0.8, label=f"{n} uniform draws over L_t")
    ax.plot(t, table_cov, "o-", label=f"table ({sum(table_cov)})")
    ax.plot(t, mlp_cov, "s--", label=f"MLP ({sum(mlp_cov)})")
    ax.set_yscale("log")
    ax.set_xlabel("level t")
    ax.set_ylabel(f"cells of L_t reached by {n} rollouts")
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    return fig
