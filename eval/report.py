"""The whole evaluation in one command: tables, distillation, every experiment, figures, dashboards, report.

    python -m eval.report            # about 20-30 minutes on a 2-core CPU
    python -m eval.report --quick    # about a minute: fewer seeds and sizes, 2 s horizon, a briefly trained MLP

Stages (each prints its time; a finished stage is reused on the next run unless ``--force``):

1. tables: the default Dubins preset (2 s) and the 3 s preset of the closed-loop experiments, each built by
   max-flow (the paper) and by the coverage method, with ``python -m precompute.build``, unless present;
2. the distilled MLP (``python -m training.distill`` on the 3 s max-flow table), unless present;
3. experiments: :mod:`eval.coverage`, :mod:`eval.uniformity`, :mod:`eval.sudden_obstacle`, :mod:`eval.cluttered`
   (results as JSON in ``<out>/eval/``);
4. figures (``<out>/figures/*.png``), TensorBoard runs (``<runs>/<method>``, one per method, plus ``figures``),
   and ``<out>/report.md`` with every table beside the paper's values, the machine and the commands.

``--quick`` writes under ``<out>/quick`` and ``<runs>/quick`` so it never mixes with a full run.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable

import torch

from cuniform_torch.cli import ArgumentParser, add_system_module_arg, check_output_folder, cli_main, import_system_modules
from cuniform_torch.fileio import write_bytes, write_json

from . import config
from . import coverage as coverage_exp
from . import uniformity as uniformity_exp
from .figures import coverage_vs_samples, trajectory_fans, uniformity_per_level
from .methods import METHODS, Sources


@dataclass
class Paths:
    out: Path
    runs: Path
    quick: bool

    @property
    def table(self) -> Path:
        return self.out / "dubins.npz"

    @property
    def coverage_table(self) -> Path:
        return self.out / "dubins_cov.npz"

    @property
    def table_cl(self) -> Path:
        """closed-loop max-flow table: 3 s (quick: the 2 s one)"""
        return self.table if self.quick else self.out / "dubins15.npz"

    @property
    def coverage_table_cl(self) -> Path:
        return self.coverage_table if self.quick else self.out / "dubins15_cov.npz"

    @property
    def policy(self) -> Path:
        return self.out / ("dubins.policy.pt" if self.quick else "dubins15.policy.pt")

    @property
    def results(self) -> Path:
        return self.out / "eval"

    @property
    def figures(self) -> Path:
        return self.out / "figures"


def _stage(name: str, timings: dict, fn: Callable[[], object]):
    print(f"\n== {name}", flush=True)
    start = time.perf_counter()
    value = fn()
    timings[name] = time.perf_counter() - start
    print(f"== {name}: {timings[name]:.1f} s", flush=True)
    return value


class StepFailed(Exception):
    """A command the report runs failed; it has printed its own one-line error, the report exits with its code."""

    def __init__(self, code: int) -> None:
        super().__init__(f"exit code {code}")
        self.code = code


def _run_cli(module: str, main: Callable[[list[str]], int], argv: list[str], commands: list[str]) -> None:
    commands.append(f"python -m {module} " + " ".join(argv))
    print("$ " + commands[-1], flush=True)
    code = main(argv)
    if code:
        raise StepFailed(code)


def build_inputs(paths: Paths, quick: bool, commands: list[str], force: bool) -> None:
    """Tables and the distilled policy, each made only when missing (or ``force``)."""
    from precompute.build import main as build_main
    from training.distill import main as distill_main

    tables = [(paths.table, []), (paths.coverage_table, ["--method", "coverage"])]
    if not quick:
        tables += [(paths.table_cl, ["--horizon", "15"]),
                   (paths.coverage_table_cl, ["--method", "coverage", "--horizon", "15"])]
    for path, extra in tables:
        if path.exists() and not force:
            print(f"reusing {path}")
            continue
        _run_cli("precompute.build", build_main, ["--out", str(path), *extra] + (["--quiet"] if quick else []), commands)
    if paths.policy.exists() and not force:
        print(f"reusing {paths.policy}")
        return
    source = paths.table if quick else paths.table_cl
    # 3 s table: 30 606 cells, 150 epochs ~ 5 min on 2 cores; --quick: a brief run, enough to drive a controller
    epochs = ["--epochs", "15", "--eval-samples", "200", "--eval-every", "5"] if quick else ["--epochs", "150"]
    _run_cli("training.distill", distill_main,
             ["--tables", str(source), "--out", str(paths.policy), "--logdir", str(paths.runs / "distill"), *epochs]
             + (["--quiet"] if quick else []), commands)


def _cached(path: Path, cfg: dict, force: bool, compute: Callable[[], dict]) -> dict:
    """Reuse ``path`` when it holds a result of the same config (so an interrupted report resumes)."""
    if path.exists() and not force:
        try:
            old = json.loads(path.read_text())
            if old.get("config") == json.loads(json.dumps(cfg)):
                print(f"reusing {path}")
                return old
        except (OSError, ValueError):
            pass
    result = compute()
    write_json(path, result)
    return result


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none"
    return (f"{platform.system()} {platform.release()}, {cpu}, {os.cpu_count()} CPU cores, GPU: {gpu}; "
            f"Python {platform.python_version()}, torch {torch.__version__}")


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
        per_method.setdefault(r["method"], {})["hparam/mean_tv"] = sum(r["reachable"]["tv"][1:]) / max(1, len(r["reachable"]["tv"]) - 1)
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


def write_markdown(path: Path, sections: list[tuple[str, str]], commands: list[str], timings: dict,
                   quick: bool) -> None:
    lines = ["# cuniform evaluation report", "",
             f"Machine: {machine()}.", "",
             "Produced by `python -m eval.report" + (" --quick`" if quick else "`") + " with these steps:", "",
             "```", *commands, "```", "",
             "Stage times: " + ", ".join(f"{k} {v:.0f} s" for k, v in timings.items()) + ".", ""]
    if quick:
        lines += ["**Quick mode**: few seeds and sizes, the 2 s tables for the closed loop, an MLP trained for a "
                  "few epochs. Numbers here are not the report's.", ""]
    for title, body in sections:
        lines += [f"## {title}", "", body, ""]
    write_bytes(path, "\n".join(lines).encode())


@cli_main()
def main(argv=None) -> int:
    p = ArgumentParser(prog="python -m eval.report", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="about a minute: fewer seeds and sizes")
    p.add_argument("--out", type=Path, default=config.OUT, help="folder of tables, results, figures and the report")
    p.add_argument("--runs", type=Path, default=Path("runs/eval"), help="TensorBoard folder")
    p.add_argument("--device", default="cpu")
    p.add_argument("--force", action="store_true", help="rebuild tables and rerun every stage")
    p.add_argument("--skip-closed-loop", action="store_true", help="only the open-loop experiments")
    p.add_argument("--no-mlp", action="store_true",
                   help="leave the distilled MLP out of the closed-loop experiments (saves several minutes on a CPU: "
                        "its forward pass costs about 10x a table lookup per control cycle)")
    add_system_module_arg(p)
    args = p.parse_args(argv)
    import_system_modules(args.system_module)
    check_output_folder(args.out, "--out")
    check_output_folder(args.runs, "--runs")
    try:
        return _report(args)
    except StepFailed as exc:  # the step printed its error line (or its Ctrl-C line) already
        return exc.code


def _report(args) -> int:
    """Every stage of the report (see the module docstring)."""
    out, runs = (args.out / "quick", args.runs / "quick") if args.quick else (args.out, args.runs)
    paths = Paths(out, runs, args.quick)
    timings: dict[str, float] = {}
    commands: list[str] = []
    torch.manual_seed(0)
    total = time.perf_counter()

    _stage("tables and policy", timings, lambda: build_inputs(paths, args.quick, commands, args.force))
    open_sources = Sources(paths.table, paths.coverage_table, paths.policy, args.device)
    cl_sources = Sources(paths.table_cl, paths.coverage_table_cl, paths.policy, args.device)

    cov_cfg = coverage_exp.CoverageConfig(samples=[250, 1000] if args.quick else [250, 500, 1000, 2500, 5000, 10000],
                                          seeds=2 if args.quick else 5)
    cov = _stage("coverage", timings, lambda: _cached(paths.results / "coverage.json", asdict(cov_cfg), args.force,
                                                      lambda: coverage_exp.run(cov_cfg, open_sources)))
    coverage_exp.print_table(cov)
    uni_cfg = uniformity_exp.UniformityConfig(samples=1000 if args.quick else 10000, seeds=1 if args.quick else 3)
    uni = _stage("uniformity", timings, lambda: _cached(paths.results / "uniformity.json", asdict(uni_cfg), args.force,
                                                        lambda: uniformity_exp.run(uni_cfg, open_sources)))
    closed: dict[str, dict] = {}
    closed_md: list[tuple[str, str]] = []
    closed_figs: list[Path] = []
    if not args.skip_closed_loop:
        from . import cluttered, sudden_obstacle

        for name, module, default in (("sudden_obstacle", sudden_obstacle, sudden_obstacle.SuddenObstacleConfig()),
                                      ("cluttered", cluttered, cluttered.ClutteredConfig())):
            # --quick: the 2 s tables drive the controllers (horizon 10 instead of 15)
            cfg = replace(module.QUICK, horizon=10) if args.quick else replace(default, include_mlp=not args.no_mlp)
            closed[name] = _stage(name, timings, lambda: _cached(
                paths.results / f"{name}.json", asdict(cfg), args.force,
                lambda: module.run(cfg, cl_sources, progress=not args.quick)))
            closed_md.append(module.markdown(closed[name]))
            closed_figs += module.figures(closed[name], paths.figures)

    def make_figures() -> dict:
        figs = {
            "coverage_vs_n": coverage_vs_samples(cov, paths.figures / "coverage_vs_n.png"),
            "uniformity_per_level": uniformity_per_level(uni, paths.figures / "uniformity_per_level.png"),
            "trajectory_fans": trajectory_fans(open_sources, paths.figures / "trajectory_fans.png"),
        }
        log_tensorboard(runs, cov, uni, closed, figs, closed_figs)
        return figs

    _stage("figures and TensorBoard", timings, make_figures)
    figure_list = "\n".join(f"- ![{f.stem}](figures/{f.name})" for f in sorted(paths.figures.glob("*.png")))
    sections = [
        ("Coverage (the paper's Table I)", coverage_exp.markdown(cov) + "\n\n" + config.PAPER_COVERAGE_NOTE + "."),
        ("Uniformity per level", uniformity_exp.markdown(uni)),
        *([("Closed loop (the paper's Tables II and III)", "\n\n".join(closed_md))] if closed_md else []),
        ("Figures", figure_list),
    ]
    timings["total"] = time.perf_counter() - total
    write_markdown(out / "report.md", sections, commands, timings, args.quick)
    print(f"\nwrote {out / 'report.md'}, {len(list(paths.figures.glob('*.png')))} figures in {paths.figures}, "
          f"TensorBoard runs in {runs} (tensorboard --logdir {runs}); total {timings['total']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
