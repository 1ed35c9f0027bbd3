"""The whole evaluation in one command: tables, distillation, every experiment, figures, dashboards, report.

    python -m eval.report            # about 12 minutes on a 2-core CPU (episodes in --workers processes)
    python -m eval.report --quick    # about 16 s: fewer seeds and sizes, 2 s horizon, a briefly trained MLP

Stages (each prints its time, and the run ends with a table of them, each build's command below its stage: what
cost what; a finished stage is reused on the next run unless ``--force``):

1. tables: the default Dubins preset (2 s) and the 3 s preset of the closed-loop experiments, each built by
   max-flow (the paper) and by the coverage method, with ``python -m precompute.build``, unless present;
2. the distilled MLP (``python -m training.distill`` on the 3 s max-flow table), unless present;
3. experiments: :mod:`eval.paper.coverage`, :mod:`eval.paper.uniformity`, :mod:`eval.paper.sudden_obstacle`,
   :mod:`eval.paper.cluttered` (results as JSON in ``<out>/eval/``), each reused when its JSON holds a result of the same
   config (so an interrupted report resumes), and a short run of the navigation benchmark
   (:func:`eval.navigate.run.short_run`: 10 BARN maps at budgets 64 and 256; resumable, under ``<out>/navigate``);
4. figures (``<out>/figures/*.png``), TensorBoard runs (``<runs>/<method>``, one per method, plus ``figures``;
   :mod:`eval.paper.tensorboard`), and ``<out>/report.md`` with every table beside the paper's values, the machine, the
   commands and which stages were reused.

``--quick`` writes under ``<out>/quick`` and ``<runs>/quick`` so it never mixes with a full run. File names:
:class:`eval.common.paths.OutputPaths`.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch

from cuniform_torch.common.fileio import MAX_JSON_BYTES, read_capped_text, write_bytes, write_json
from eval.common import config
from eval.common.figures import coverage_vs_samples, trajectory_fans, uniformity_per_level
from eval.common.methods import Sources
from eval.common.paths import DEFAULT, RUNS_EVAL, OutputPaths
from eval.paper import coverage as coverage_experiment
from eval.paper import uniformity
from eval.paper.tensorboard import log_tensorboard
from precompute.cli import (
    ArgumentParser,
    add_system_module_arg,
    check_output_folder,
    cli_main,
    device_arg,
    import_system_modules,
    int_in,
)

__all__ = ["Stages", "build_inputs", "machine", "write_markdown", "main"]


@dataclass
class Stages:
    """What one report run did: stage times, the commands it ran, the outputs it reused and those it made."""

    force: bool = False
    """rebuild and rerun everything"""
    timings: dict[str, float] = field(default_factory=dict)
    commands: list[str] = field(default_factory=list)
    reused: list[str] = field(default_factory=list)
    made: list[str] = field(default_factory=list)
    steps: dict[str, list[tuple[str, float]]] = field(default_factory=dict)
    """each stage's commands (:meth:`run_step`) and their seconds"""
    current: str = ""

    def stage(self, name: str, fn: Callable[[], object]):
        print(f"\n== {name}", flush=True)
        self.current = name
        start = time.perf_counter()
        value = fn()
        self.timings[name] = time.perf_counter() - start
        print(f"== {name}: {self.timings[name]:.1f} s", flush=True)
        return value

    def table(self) -> str:
        """What cost what: each stage's seconds and share of the total, its commands indented below it."""
        total = self.timings.get("total") or sum(self.timings.values()) or 1.0
        rows = []
        for name, seconds in self.timings.items():
            if name == "total":
                continue
            rows.append((name, seconds))
            rows += [(f"  {step}", t) for step, t in self.steps.get(name, [])]
        width = max([len(r[0]) for r in rows] + [len("total")])
        lines = [f"{'stage':<{width}}  {'seconds':>8}  {'share':>6}"]
        lines += [f"{name:<{width}}  {t:8.1f}  {100 * t / total:5.1f}%" for name, t in rows]
        lines.append(f"{'total':<{width}}  {total:8.1f}  100.0%")
        return "\n".join(lines)

    def reuse(self, path: Path) -> bool:
        """Whether ``path`` is kept from an earlier run (it exists and there is no ``force``); says so."""
        if path.exists() and not self.force:
            self.reused.append(str(path))
            print(f"reusing {path}")
            return True
        self.made.append(str(path))
        return False

    def run_step(self, module: str, argv: list[str], run: Callable[[list[str]], object]) -> None:
        """Record and print the command ``python -m module argv``, then ``run(argv)``: the library function behind
        it on the same flags (an error propagates as that function raises it)."""
        self.commands.append(f"python -m {module} " + " ".join(argv))
        print("$ " + self.commands[-1], flush=True)
        start = time.perf_counter()
        run(argv)
        out = argv[argv.index("--out") + 1] if "--out" in argv else ""
        self.steps.setdefault(self.current, []).append((f"{module} {Path(out).name}".rstrip(),
                                                        time.perf_counter() - start))

    def cached(self, path: Path, cfg: dict, compute: Callable[[], dict]) -> dict:
        """The result in ``path`` when it holds one of the same config, else ``compute()`` written there."""
        if path.exists() and not self.force:
            try:
                old = json.loads(read_capped_text(path, MAX_JSON_BYTES, "a result file"))
                if old.get("config") == json.loads(json.dumps(cfg)):
                    self.reused.append(str(path))
                    print(f"reusing {path}")
                    return old
            except (OSError, ValueError):
                pass
        result = compute()
        write_json(path, result)
        self.made.append(str(path))
        return result


def build_inputs(paths: OutputPaths, runs: Path, stages: Stages) -> None:
    """Tables and the distilled policy, each made only when missing (or ``force``)."""
    from cuniform_torch.systems import make_system
    from precompute import BuildConfig, CoverageConfig, build_table
    from precompute.build import with_threads
    from training.distill import distill, parse_args

    def train(argv: list[str]) -> None:
        distill(parse_args(argv))

    quiet = ["--quiet"] if paths.quick else []
    system = make_system("dubins")
    tables = [(paths.table, "maxflow", 10), (paths.coverage_table, "coverage", 10)]
    if not paths.quick:
        tables += [(paths.table_cl, "maxflow", 15), (paths.coverage_table_cl, "coverage", 15)]
    for path, method, horizon in tables:
        if stages.reuse(path):
            continue
        config = BuildConfig(horizon=horizon)
        coverage = CoverageConfig(horizon=horizon) if method == "coverage" else None

        def build(argv: list[str], path: Path = path, config: BuildConfig = config,
                  coverage: CoverageConfig | None = coverage) -> None:
            # the library function the command calls, on the command's one torch thread (its --threads default)
            with_threads(1, lambda: build_table(system, config, coverage=coverage, out=path, report=True,
                                                progress=not paths.quick))

        stages.run_step("precompute.build", [method, "--horizon", str(horizon), "--out", str(path), *quiet], build)
    if stages.reuse(paths.policy):
        return
    # the 3 s table (30 606 cells) at the distillation's default; --quick: a brief run, enough to drive a controller
    epochs = ["--epochs", "15", "--eval-samples", "200", "--eval-every", "5"] if paths.quick else []
    stages.run_step("training.distill", ["--tables", str(paths.table_cl), "--out", str(paths.policy),
                                         "--logdir", str(runs / "distill"), *epochs, *quiet], train)


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none"
    return (f"{platform.system()} {platform.release()}, {cpu}, {os.cpu_count()} CPU cores, GPU: {gpu}; "
            f"Python {platform.python_version()}, torch {torch.__version__}")


def write_markdown(path: Path, sections: list[tuple[str, str]], stages: Stages, quick: bool) -> None:
    lines = ["# cuniform evaluation report", "",
             f"Machine: {machine()}.", "",
             "Produced by `python -m eval.report" + (" --quick`" if quick else "`") + " with these steps:", "",
             "```", *stages.commands, "```", "",
             "Stage times (what cost what):", "", "```", stages.table(), "```", ""]
    if stages.reused:
        lines += [f"Reused from an earlier run ({len(stages.reused)} of {len(stages.reused) + len(stages.made)} "
                  "outputs; `--force` remakes them): " + ", ".join(f"`{p}`" for p in stages.reused) + ".", ""]
    if quick:
        lines += ["**Quick mode**: few seeds and sizes, the 2 s tables for the closed loop, an MLP trained for a "
                  "few epochs. Numbers here are not the report's.", ""]
    for title, body in sections:
        lines += [f"## {title}", "", body, ""]
    write_bytes(path, "\n".join(lines).encode())


def default_workers() -> int:
    """The CPU cores this process may use (its affinity where the platform has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


@cli_main()
def main(argv=None) -> int:
    p = ArgumentParser(prog="python -m eval.report", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="about 16 s: fewer seeds and sizes")
    p.add_argument("--out", type=Path, default=DEFAULT.root, help="folder of tables, results, figures and the report")
    p.add_argument("--runs", type=Path, default=RUNS_EVAL, help="TensorBoard folder")
    p.add_argument("--device", type=device_arg, default="cpu", help="torch device of the experiments' rollouts")
    p.add_argument("--force", action="store_true", help="rebuild tables and rerun every stage")
    p.add_argument("--skip-closed-loop", action="store_true", help="only the open-loop experiments")
    p.add_argument("--no-mlp", action="store_true",
                   help="leave the distilled MLP out of the closed-loop experiments (saves several minutes on a CPU: "
                        "its forward pass costs about 10x a table lookup per control cycle)")
    p.add_argument("--workers", type=int_in(1, 1024), default=default_workers(),
                   help="processes for the closed-loop episodes, one torch thread each (default: the CPU cores "
                        "this process may use; --quick: 1; the records do not depend on it)")
    add_system_module_arg(p)
    args = p.parse_args(argv)
    import_system_modules(args.system_module)
    check_output_folder(args.out, "--out")
    check_output_folder(args.runs, "--runs")
    return _report(args)


def _report(args) -> int:
    """Every stage of the report (see the module docstring)."""
    # --quick: a few episodes each, so starting worker processes (about 3 s each) would cost more than they save
    workers = 1 if args.quick else args.workers
    paths = OutputPaths(args.out / "quick", quick=True) if args.quick else OutputPaths(args.out)
    runs = args.runs / "quick" if args.quick else args.runs
    stages = Stages(force=args.force)
    torch.manual_seed(0)
    total = time.perf_counter()

    stages.stage("tables and policy", lambda: build_inputs(paths, runs, stages))
    open_sources = Sources(paths.table, paths.coverage_table, paths.policy, args.device)
    cl_sources = Sources(paths.table_cl, paths.coverage_table_cl, paths.policy, args.device)

    def experiment(module, cfg, sources, **kw) -> dict:
        name = module.__name__.split(".")[-1].removesuffix("_experiment")
        return stages.stage(name, lambda: stages.cached(paths.result(name), asdict(cfg),
                                                        lambda: module.run(cfg, sources, **kw)))

    cov = experiment(coverage_experiment, coverage_experiment.QUICK if args.quick else coverage_experiment.CONFIG(),
                     open_sources)
    coverage_experiment.print_table(cov)
    uni = experiment(uniformity, uniformity.QUICK if args.quick else uniformity.CONFIG(), open_sources)
    closed: dict[str, dict] = {}
    closed_md: list[str] = []
    closed_figs: list[Path] = []
    if not args.skip_closed_loop:
        from eval.paper import cluttered, sudden_obstacle

        for module in (sudden_obstacle, cluttered):
            # --quick: the 2 s tables drive the controllers (horizon 10 instead of 15)
            cfg = replace(module.QUICK, horizon=10) if args.quick else replace(module.CONFIG(), include_mlp=not args.no_mlp)
            name = module.__name__.split(".")[-1]
            closed[name] = experiment(module, cfg, cl_sources, progress=not args.quick, workers=workers)
            closed_md.append(module.markdown(closed[name]))
            closed_figs += module.figures(closed[name], paths.figures)

    if not args.skip_closed_loop:
        from eval.navigate import run as navigate

        nav = stages.stage("navigation (short)", lambda: navigate.short_run(paths.root / "navigate", args.quick,
                                                                             progress=not args.quick,
                                                                             workers=workers))
        closed_md.append(navigate.render(nav))

    def make_figures() -> dict:
        figs = {
            "coverage_vs_n": coverage_vs_samples(cov, paths.figures / "coverage_vs_n.png"),
            "uniformity_per_level": uniformity_per_level(uni, paths.figures / "uniformity_per_level.png"),
            "trajectory_fans": trajectory_fans(open_sources, paths.figures / "trajectory_fans.png"),
        }
        log_tensorboard(runs, cov, uni, closed, figs, closed_figs)
        return figs

    stages.stage("figures and TensorBoard", make_figures)
    figure_list = "\n".join(f"- ![{f.stem}](figures/{f.name})" for f in sorted(paths.figures.glob("*.png")))
    sections = [
        ("Coverage (the paper's Table I)", coverage_experiment.markdown(cov) + "\n\n" + config.PAPER_COVERAGE_NOTE + "."),
        ("Uniformity per level", uniformity.markdown(uni)),
        *([("Closed loop (the paper's Tables II and III, then the navigation benchmark's short run)",
             "\n\n".join(closed_md))] if closed_md else []),
        ("Figures", figure_list),
    ]
    stages.timings["total"] = time.perf_counter() - total
    write_markdown(paths.report, sections, stages, args.quick)
    print("\n" + stages.table())
    print(f"\nreused {len(stages.reused)} of {len(stages.reused) + len(stages.made)} outputs of earlier runs")
    print(f"wrote {paths.report}, {len(list(paths.figures.glob('*.png')))} figures in {paths.figures}, "
          f"TensorBoard runs in {runs} (tensorboard --logdir {runs}); total {stages.timings['total']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
