"""Figures of the open-loop experiments (matplotlib, Agg backend): trajectory fans, coverage vs N, uniformity.

Each function saves one PNG and returns the figure (for TensorBoard's ``add_figure``); the closed-loop path
figures live with their experiments (:mod:`eval.sudden_obstacle`, :mod:`eval.cluttered`).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from .config import PAPER_COVERAGE  # noqa: E402
from .methods import METHODS, Sources, sample_states  # noqa: E402

FAN_METHODS = ["mppi_high", "log_mppi_high", "uniform", "cu_table", "cu_coverage", "cu_mlp"]
"""the trajectory-fan panels: the paper's Fig. 1 (uniform actions vs C-Uniform) plus the noise baselines"""


STYLE = {  # method -> (colour, line style): one hue per family, darker = more noise
    "mppi_low": ("#9ecae1", "-"), "mppi_medium": ("#4292c6", "-"), "mppi_high": ("#08519c", "-"),
    "log_mppi_low": ("#fdae6b", "-"), "log_mppi_medium": ("#f16913", "-"), "log_mppi_high": ("#a63603", "-"),
    "uniform": ("#737373", "-"), "cu_table": ("#2ca02c", "-"), "cu_coverage": ("#d62728", "-"),
    "cu_mlp": ("#9467bd", "-"), "cu_graph": ("#8c564b", "--"), "cumppi": ("#e377c2", "-"),
}


def method_style(key: str) -> tuple[str, str]:
    """(colour, line style) of a method, the same in every figure."""
    return STYLE.get(key, ("black", "-"))


def _save(fig, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=110, bbox_inches="tight")
    tmp.replace(path)
    return path


def trajectory_fans(sources: Sources, path: Path, methods: list[str] | None = None, num_samples: int = 300,
                    seed: int = 0):
    """A panel per method: ``num_samples`` trajectories from the origin (xy), plus the last level's endpoints."""
    keys = [k for k in (methods or FAN_METHODS) if k in METHODS and METHODS[k].open_loop]
    T = sources.horizon
    cols = min(3, len(keys))
    rows = -(-len(keys) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.6 * rows), squeeze=False, sharex=True, sharey=True)
    for ax, key in zip(axes.flat, keys):
        states = sample_states(METHODS[key], sources, num_samples, T, torch.Generator().manual_seed(seed)).cpu()
        xy = states[..., :2].numpy()
        ax.plot(xy[:, :, 0].T, xy[:, :, 1].T, color="tab:blue", alpha=0.12, linewidth=0.8)
        ax.scatter(xy[:, -1, 0], xy[:, -1, 1], s=3, color="tab:red", zorder=3)
        ax.set_title(METHODS[key].label, fontsize=9)
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(keys):]:
        ax.axis("off")
    fig.suptitle(f"{num_samples} trajectories of {T} steps from (0, 0, 0); red: final states", fontsize=10)
    _save(fig, path)
    return fig


def coverage_vs_samples(result: dict, path: Path):
    """Distinct cells vs N (log x) per method, mean +- std; the paper's Table I as hollow markers."""
    rows = result["results"]
    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    for m in methods:
        mine = [r for r in rows if r["method"] == m]
        n = [r["samples"] for r in mine]
        mean = [r["cells_mean"] for r in mine]
        std = [r["cells_std"] for r in mine]
        color, style = method_style(m)
        ax.errorbar(n, mean, yerr=std, marker="o", markersize=4, capsize=2, color=color, linestyle=style,
                    label=METHODS[m].label if m in METHODS else m)
        paper = [(N, PAPER_COVERAGE[N][m]) for N in n if m in PAPER_COVERAGE.get(N, {})]
        if paper:
            ax.plot(*zip(*paper), linestyle=":", marker="s", markerfacecolor="none", color=color, alpha=0.8)
    reach = result["reachable"]["total"]
    ax.axhline(reach, color="black", linestyle=":", linewidth=1)
    ax.text(min(r["samples"] for r in rows), reach, f" all {reach} reachable cells", va="bottom", fontsize=8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("trajectories N")
    ax.set_ylabel("distinct cells visited")
    ax.set_title("Coverage (filled: ours, dotted hollow squares: the paper's Table I)", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    _save(fig, path)
    return fig


def uniformity_per_level(result: dict, path: Path, reference: str = "reachable"):
    """TV from uniform, entropy ratio and share outside the reference set, per level, one line per method."""
    rows = result["results"]
    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    for r in rows:
        stats = r[reference]
        t = list(range(len(stats["tv"])))
        color, style = method_style(r["method"])
        for ax, key in zip(axes, ("tv", "entropy", "outside")):
            ax.plot(t[1:], stats[key][1:], marker=".", color=color, linestyle=style, label=r["label"])
    axes[0].plot(t[1:], rows[0][reference]["floor"][1:], color="black", linestyle=":", label="floor (N uniform draws)")
    what = "cells real rollouts can reach" if reference == "reachable" else "the table's level sets L_t"
    for ax, title in zip(axes, ("TV distance from uniform", "entropy / log |S_t|", "share of states outside S_t")):
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("level t")
        ax.grid(alpha=0.3)
    axes[2].legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.suptitle(f"Uniformity per level over S_t = {what}, N = {rows[0]['samples']}", fontsize=10)
    _save(fig, path)
    return fig
