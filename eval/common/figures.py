"""Every figure of the evaluation (matplotlib, Agg backend): trajectory fans, coverage vs N, uniformity per
level, and the closed-loop paths per method.

The open-loop functions save one PNG and return the figure (for TensorBoard's ``add_figure``); :func:`plot_paths`
saves one PNG of closed-loop records and returns its path (the experiments' ``figures`` choose the panels). A
method's colour and line style are its :data:`eval.common.methods.METHODS` entry's, the same in every figure.
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from cuniform_torch.envs import Circle, Environment, Polygon, Rect  # noqa: E402
from eval.common.config import PAPER_COVERAGE  # noqa: E402
from eval.common.methods import PAPER, Sources, methods_of, sample_states  # noqa: E402

__all__ = ["FAN_METHODS", "OUTCOME_COLORS", "method_style", "save_figure", "trajectory_fans", "coverage_vs_samples",
           "uniformity_per_level", "draw_obstacle", "plot_paths"]

FAN_METHODS = ["mppi_high", "log_mppi_high", "uniform", "cu_table", "cu_coverage", "cu_mlp"]
"""the trajectory-fan panels: the paper's Fig. 1 (uniform actions vs C-Uniform) plus the noise baselines"""


OUTCOME_COLORS = {"goal": "tab:green", "collision": "tab:red", "timeout": "tab:orange"}
"""closed-loop paths by outcome"""


def method_style(key: str) -> tuple[str, str]:
    """(colour, line style) of a method, the same in every figure."""
    m = methods_of(PAPER).get(key)  # the navigation benchmark's figures are given their colours
    return (m.color, m.linestyle) if m is not None else ("black", "-")


def save_figure(fig, path: Path, tight: bool = True) -> Path:
    """Write ``fig`` as a PNG (atomically: a temporary file renamed over ``path``), creating the folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=110, **({"bbox_inches": "tight"} if tight else {}))
    tmp.replace(path)
    return path


def trajectory_fans(sources: Sources, path: Path, methods: list[str] | None = None, num_samples: int = 300,
                    seed: int = 0):
    """A panel per method: ``num_samples`` trajectories from the origin (xy), plus the last level's endpoints."""
    paper = methods_of(PAPER)
    keys = [k for k in (methods or FAN_METHODS) if k in paper and paper[k].open_loop]
    T = sources.horizon
    cols = min(3, len(keys))
    rows = -(-len(keys) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.6 * rows), squeeze=False, sharex=True, sharey=True)
    for ax, key in zip(axes.flat, keys):
        states = sample_states(paper[key], sources, num_samples, T, torch.Generator().manual_seed(seed)).cpu()
        xy = states[..., :2].numpy()
        ax.plot(xy[:, :, 0].T, xy[:, :, 1].T, color="tab:blue", alpha=0.12, linewidth=0.8)
        ax.scatter(xy[:, -1, 0], xy[:, -1, 1], s=3, color="tab:red", zorder=3)
        ax.set_title(paper[key].label, fontsize=9)
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(keys):]:
        ax.axis("off")
    fig.suptitle(f"{num_samples} trajectories of {T} steps from (0, 0, 0); red: final states", fontsize=10)
    save_figure(fig, path)
    return fig


def coverage_vs_samples(result: dict, path: Path):
    """Distinct cells vs N (log x) per method, mean +- std; the paper's Table I as hollow markers."""
    rows = result["results"]
    known = methods_of(PAPER)
    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    for m in methods:
        mine = [r for r in rows if r["method"] == m]
        n = [r["samples"] for r in mine]
        mean = [r["cells_mean"] for r in mine]
        std = [r["cells_std"] for r in mine]
        color, style = method_style(m)
        ax.errorbar(n, mean, yerr=std, marker="o", markersize=4, capsize=2, color=color, linestyle=style,
                    label=known[m].label if m in known else m)
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
    save_figure(fig, path)
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
    save_figure(fig, path)
    return fig


# ------------------------------------------------------------------------------------------------ closed loop

def draw_obstacle(ax, obs, **kw) -> None:
    from matplotlib import patches

    if isinstance(obs, Circle):
        ax.add_patch(patches.Circle(obs.center, obs.radius, **kw))
    elif isinstance(obs, Rect):
        ax.add_patch(patches.Rectangle((obs.xmin, obs.ymin), obs.xmax - obs.xmin, obs.ymax - obs.ymin, **kw))
    elif isinstance(obs, Polygon):
        v = torch.as_tensor(obs.vertices).tolist()
        ax.add_patch(patches.Polygon(v, closed=True, **kw))
    else:
        raise ValueError(f"cannot draw obstacle of type {type(obs).__name__}")


def plot_paths(panels: dict[str, list[dict]], envs: dict[str, Environment] | Environment, out: Path,
               title: str = "", xlim: tuple[float, float] | None = None,
               ylim: tuple[float, float] | None = None) -> Path:
    """One subplot per method (``panels``: label -> records with ``path``, ``outcome``, ``goal`` and, when
    ``envs`` is a dict, an ``env`` key naming its environment); paths coloured by outcome (green goal, red
    collision, orange timeout), obstacles grey, starts as dots, goals as stars. Saves a PNG to ``out``."""
    from matplotlib.lines import Line2D

    n = max(1, len(panels))
    ncols = min(4, n)
    nrows = math.ceil(n / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(3.6 * ncols, 3.4 * nrows), squeeze=False)
    for ax in axes.flat[n:]:
        ax.axis("off")
    for ax, (label, recs) in zip(axes.flat, panels.items()):
        drawn = set()
        for r in recs:
            env = envs[r["env"]] if isinstance(envs, dict) else envs
            if id(env) not in drawn:
                drawn.add(id(env))
                alpha = 0.6 if len(drawn) == 1 or not isinstance(envs, dict) else max(0.08, 0.6 / len(recs) * 2)
                for obs in env.obstacles:
                    draw_obstacle(ax, obs, facecolor="0.55", edgecolor="0.3", alpha=alpha, lw=0.5)
                if env.bounds is not None:
                    xmin, ymin, xmax, ymax = env.bounds
                    ax.plot([xmin, xmax, xmax, xmin, xmin], [ymin, ymin, ymax, ymax, ymin], color="k", lw=1)
            p = r.get("path")
            if p:
                xs, ys = zip(*p)
                ax.plot(xs, ys, color=OUTCOME_COLORS.get(r["outcome"], "k"), lw=1.0, alpha=0.8)
                ax.plot(xs[0], ys[0], "o", color="k", ms=2.5)
            ax.plot(*r["goal"], marker="*", color="gold", mec="k", ms=11, zorder=5)
        ok = sum(r["success"] for r in recs)
        ax.set_title(f"{label}\n{ok}/{len(recs)} reached the goal", fontsize=8)
        ax.set_aspect("equal")
        if xlim:
            ax.set_xlim(*xlim)
        if ylim:
            ax.set_ylim(*ylim)
        ax.tick_params(labelsize=6)
    handles = [Line2D([], [], color=c, label=k) for k, c in OUTCOME_COLORS.items()]
    fig.legend(handles=handles, loc="lower right", fontsize=8, ncol=3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    save_figure(fig, out, tight=False)
    plt.close(fig)
    return Path(out)
