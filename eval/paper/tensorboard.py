"""TensorBoard runs of the evaluation report: one run per method, so that the same scalar lines up across methods.

Scalars: ``coverage/cells``, ``coverage/pct_reachable``, ``coverage/pct_ceiling`` (against N),
``uniformity/tv``, ``uniformity/entropy_ratio``, ``uniformity/outside`` (against the level t) and
``success/<experiment>/<scenario>`` (against N); a custom-scalars layout that overlays the methods; the figures
under the ``figures`` run; and each method's hyperparameters (family, noise level) with its headline numbers.
"""

from __future__ import annotations

from pathlib import Path

from eval.common.methods import METHODS
from eval.common.stats import mean_over_levels

__all__ = ["log_tensorboard"]


def log_tensorboard(runs: Path, coverage: dict, uniformity: dict, closed_loop: dict[str, dict], figures: dict,
                    images: list[Path] = ()) -> None:
    """One run per method (scalars that line up across methods), a custom-scalars layout, figures, hparams."""
    from torch.utils.tensorboard import SummaryWriter

    per_method: dict[str, dict[str, float]] = {}
    writers: dict[str, SummaryWriter] = {}

    def writer(key: str) -> SummaryWriter:
        if key not in writers:
            writers[key] = SummaryWriter(str(runs / key))
        return writers[key]

    for r in coverage["results"]:
        w = writer(r["method"])
        w.add_scalar("coverage/cells", r["cells_mean"], r["samples"])
        w.add_scalar("coverage/pct_reachable", r["pct_reachable"], r["samples"])
        w.add_scalar("coverage/pct_ceiling", r["pct_ceiling"], r["samples"])
        per_method.setdefault(r["method"], {})[f"hparam/coverage_N{r['samples']}"] = r["cells_mean"]
    for r in uniformity["results"]:
        w = writer(r["method"])
        for t, (tv, ent, out) in enumerate(zip(r["reachable"]["tv"], r["reachable"]["entropy"], r["reachable"]["outside"])):
            w.add_scalar("uniformity/tv", tv, t)
            w.add_scalar("uniformity/entropy_ratio", ent, t)
            w.add_scalar("uniformity/outside", out, t)
        per_method.setdefault(r["method"], {})["hparam/mean_tv"] = mean_over_levels(r["reachable"]["tv"])
    for exp, result in closed_loop.items():
        for row in result.get("summary", []):
            scenario = row["env"] if "env" in row else f"appear_{row['appear']:g}s"
            step = int(row["num_samples"])
            writer(row["method"]).add_scalar(f"success/{exp}/{scenario}", row["success_rate"], step)
            per_method.setdefault(row["method"], {})[f"hparam/{exp}_{scenario}_N{step}"] = row["success_rate"]
    layout = {
        "coverage": {"distinct cells vs N": ["Multiline", ["coverage/cells"]],
                     "% of reachable cells vs N": ["Multiline", ["coverage/pct_reachable"]],
                     "% of uniform ceiling vs N": ["Multiline", ["coverage/pct_ceiling"]]},
        "uniformity": {"TV from uniform vs level": ["Multiline", ["uniformity/tv"]],
                       "entropy ratio vs level": ["Multiline", ["uniformity/entropy_ratio"]]},
        "success": {exp: ["Multiline", [f"success/{exp}/.*"]] for exp in closed_loop},
    }
    fig_writer = writer("figures")
    fig_writer.add_custom_scalars(layout)
    for name, fig in figures.items():
        fig_writer.add_figure(name, fig)
    import matplotlib.image

    for png in images:  # the closed-loop path figures, saved by their experiments
        fig_writer.add_image(png.stem, matplotlib.image.imread(png)[..., :3], dataformats="HWC")
    metric_names = sorted({k for m in per_method.values() for k in m})
    for key, metrics in per_method.items():
        method = METHODS.get(key)
        hparams = {"method": key, "family": method.family if method else "?",
                   "noise_std": float(method.noise_std) if method and method.noise_std is not None else 0.0}
        writer(key).add_hparams(hparams, {k: metrics.get(k, float("nan")) for k in metric_names}, run_name=".")
    for w in writers.values():
        w.close()
