"""Replay one stored navigation-benchmark episode and draw why it ended the way it did.

    python -m eval.navigate replay --out out/navigate/clutter --key clutter/15/cu_table/256/0

Reads ``DIR/settings.json`` and the record ``KEY`` of ``DIR/episodes.jsonl``
(:func:`eval.navigate.records.load_episode`; read only, so a benchmark still writing the folder is not disturbed),
rebuilds the one task
(:func:`precompute.worlds.tasks.make_task`) and the robot, checks that the source files (the same flags and defaults as
``eval.navigate.run``'s) are the ones the run used (their digests in ``settings["sources"]``), and re-runs the episode
(episodes are deterministic) with a per-command trace (:func:`eval.navigate.episode.run_nav_episode`'s ``trace``):
the share of the controller's proposals that are collision-free (cost < the collision penalty) and the lowest
proposal cost. It says whether the replay reproduces the stored record, prints a summary (for a collision: how
long before it the last command with a collision-free proposal was; the robot was *trapped* from then on, every
proposal colliding) and writes a PNG (the map, the path coloured by free share; free share against time) and,
with ``--json``, the trace and summary.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from cuniform_torch.common.fileio import write_json
from eval.navigate.episode import NavContext, NavJob, run_nav_episode
from eval.navigate.records import load_episode
from eval.navigate.run import NavConfig, input_digest, prepare_sources
from precompute.cli import ArgumentParser, add_system_module_arg, check_output_file, cli_main, import_system_modules
from precompute.worlds.robot import RobotPreset
from precompute.worlds.suites import NavTask
from precompute.worlds.tasks import make_task

__all__ = ["replay_episode", "compare_records", "summarize", "plot_replay", "main"]

PATH_TOLERANCE = 1e-4
"""m: a replayed path length within this of the stored one reproduces it"""


def _barn_file(out: Path, settings: dict, given: Path | None) -> Path | None:
    """The BARN file the run read: ``given`` (checked), else the shipped one, else the folder's converted worlds."""
    if settings["suite"] != "barn":
        return given
    want = settings.get("barn_file")  # None: the shipped file (settings_record digests only a given file)
    converted = Path(out) / "barn.npz"  # where a run with --barn-worlds converted them
    if given is None and want is not None and converted.is_file() and input_digest(converted) == want:
        given = converted
    have = input_digest(given) if given is not None else None
    if have != want:
        there = "the shipped BARN file" if want is None else f"another BARN file (digest {want})"
        here = f"--barn-file {given}" if given is not None else "the shipped BARN file"
        raise ValueError(f"the run used {there}, not {here}: give the run's --barn-file")
    return given


def _gap_count(settings: dict, records: dict[str, dict]) -> int:
    """A sweep length that gives the run's gaps: ``len(offsets) x`` its number of widths, else its largest id + 1."""
    widths = settings.get("gap_widths")
    if not widths:
        return 1 + max(r["task_id"] for r in records.values())
    from precompute.worlds.tasks import GAP_OFFSETS

    return max(len(widths) * len(GAP_OFFSETS) - len(GAP_OFFSETS) + 1, 1 + max(r["task_id"] for r in records.values()))


def _checked_sources(settings: dict, record: dict, robot: RobotPreset, cache: Path,
                     given: dict[str, Path | None]) -> dict[str, str | None]:
    """eval.navigate.run's source files for the record's method, each checked against the run's digest."""
    cfg = NavConfig(suite=settings["suite"], methods=(record["method"],), horizon=settings["horizon"])
    used = settings.get("sources") or {}

    def check(sources: dict) -> None:
        for name, path in sources.items():
            if path is None or used.get(name) is None or not Path(path).exists():
                continue  # a file the run's methods never read matches anything (eval.navigate.records.store)
            have = input_digest(Path(path))
            if have != used[name]:
                flag = f"--{name.replace('_', '-')}"
                what = f"{flag} {path}" if given.get(name) else f"{path} (the default of {flag})"
                raise ValueError(f"{what} is not the file the run used (digest {have}, the run's {used[name]}); "
                                 f"give the run's {flag}")

    check(given)  # a given file first: before it is read, so another file is named as such
    sources = prepare_sources(cfg, robot, cache, given, quiet=True)
    check(sources)
    return sources


def replay_episode(out: Path, key: str, given: dict[str, Path | None] | None = None,
                   cache: Path = Path("out/navigate/cache"), barn_file: Path | None = None) -> dict:
    """Re-run the stored episode ``key`` of the folder ``out`` with a trace: ``dict(settings, stored, replayed,
    task, trace, ctx)`` (``replayed`` holds the driven ``path [[x, y], ...]``; ``trace`` one entry per command;
    ``ctx`` the :class:`~eval.navigate.episode.NavContext` it ran with)."""
    settings, stored, records = load_episode(out, key)
    robot = RobotPreset(**settings["robot"])
    barn_file = _barn_file(out, settings, barn_file)
    suite = settings["suite"]
    # the gap sweep's widths depend on its length: the shortest sweep with the run's widths (settings
    # "gap_widths"; older folders: the run's largest task id + 1)
    count = _gap_count(settings, records) if suite == "gaps" else None
    task = make_task(suite, stored["task_id"], robot.radius, seed=settings["seed"], barn_file=barn_file,
                     sensing_range=settings["sensing_range"], time_limits={suite: settings["time_limit"]},
                     count=count)
    sources = _checked_sources(settings, stored, robot, Path(cache), given or {})
    ctx = NavContext(table=sources["table"], coverage_table=sources["coverage_table"], policy=sources["policy"],
                     map_policy=sources.get("map_policy"), horizon=settings["horizon"], lambda_=settings["lambda_"],
                     collision_penalty=settings["collision_penalty"], cost_resolution=settings["cost_resolution"],
                     record_path=True, cost_to_go=settings.get("cost_to_go"), dynamics=settings.get("dynamics", "true"))
    job = NavJob(task, stored["method"], stored["budget"], seed=stored["seed"], repeat=stored["repeat"])
    trace: list[dict] = []
    replayed = run_nav_episode(job, ctx, trace=trace)
    return dict(settings=settings, stored=stored, replayed=replayed, task=task, trace=trace, ctx=ctx)


def compare_records(stored: dict, replayed: dict, tol: float = PATH_TOLERANCE) -> list[str]:
    """What differs between a stored record and its replay (outcome, steps, path length to ``tol`` m)."""
    differ = [f"{k} {stored[k]!r} stored, {replayed[k]!r} replayed" for k in ("outcome", "steps")
              if stored[k] != replayed[k]]
    if abs(stored["path_length"] - replayed["path_length"]) > tol:
        differ.append(f"path_length {stored['path_length']} stored, {replayed['path_length']} replayed")
    return differ


def summarize(record: dict, trace: list[dict]) -> dict[str, Any]:
    """Outcome, time (s), path length (m), commands, the share of commands with no collision-free proposal and,
    for a collision, ``last_free_s``: how long before it the last command with one was (None: no command had
    one; None too for other outcomes or an untraced controller)."""
    none_free = sum(1 for e in trace if e["free_share"] == 0)
    out: dict[str, Any] = dict(outcome=record["outcome"], time=record["time"], path_length=record["path_length"],
                               commands=record["cycles"], traced=len(trace),
                               no_free_share=none_free / len(trace) if trace else None,
                               mean_free_share=sum(e["free_share"] for e in trace) / len(trace) if trace else None,
                               last_free_s=None, trapped_commands=None)
    if record["outcome"] == "collision" and trace:
        free = [k for k, e in enumerate(trace) if e["free_share"] > 0]
        out["trapped_commands"] = len(trace) - 1 - free[-1] if free else len(trace)
        out["last_free_s"] = round(record["time"] - trace[free[-1]]["t"], 6) if free else None
    return out


def _summary_lines(key: str, s: dict) -> list[str]:
    lines = [f"{key}: {s['outcome']} after {s['time']:g} s, path {s['path_length']:.3f} m, {s['commands']} commands"]
    if not s["traced"]:
        return lines + ["  (this controller has no plan(): no per-command trace)"]
    lines.append(f"  collision-free proposals: {100 * s['mean_free_share']:.1f}% per command on average; none at "
                 f"{round(s['no_free_share'] * s['traced'])} of {s['traced']} commands "
                 f"({100 * s['no_free_share']:.1f}%)")
    if s["outcome"] == "collision":
        if s["last_free_s"] is None:
            lines.append("  collision: no command ever had a collision-free proposal")
        else:
            lines.append(f"  collision: the last command with a collision-free proposal was {s['last_free_s']:g} s "
                         f"before it ({s['trapped_commands']} commands after it had none"
                         + (": trapped)" if s["trapped_commands"] else "; the weighted average still collided)"))
    return lines


def plot_replay(task: NavTask, replayed: dict, trace: list[dict], path: Path, title: str = "") -> Path:
    """Two panels into the PNG ``path``: the raw map (discs, walls, bounds), start, goal and tolerance, the path
    coloured by each command's free share (an X at a collision); and free share against time."""
    import matplotlib.pyplot as plt
    from matplotlib import patches
    from matplotlib.collections import LineCollection
    from mpl_toolkits.axes_grid1 import make_axes_locatable

    from eval.common.figures import draw_obstacle, save_figure
    from eval.navigate.episode import sensed_world

    xmin, ymin, xmax, ymax = task.bounds
    width = 11.0 if (xmax - xmin) >= (ymax - ymin) else 7.0
    map_h = min(9.0, max(2.5, 0.92 * width * (ymax - ymin + 0.6) / (xmax - xmin + 0.6)))  # the map's aspect
    fig, (ax, ax_t) = plt.subplots(2, 1, figsize=(width, map_h + 2.6), gridspec_kw=dict(height_ratios=(map_h, 1.8)))
    for obs in sensed_world(task).obstacles:  # raw obstacles, not inflated by the robot's radius
        draw_obstacle(ax, obs, facecolor="0.6", edgecolor="0.3", lw=0.5)
    ax.add_patch(patches.Rectangle((xmin, ymin), xmax - xmin, ymax - ymin, fill=False, edgecolor="k", lw=1))
    gx, gy = task.goal
    ax.add_patch(patches.Circle((gx, gy), task.goal_tolerance, fill=False, edgecolor="gold", lw=1.2, ls="--"))
    ax.plot(gx, gy, marker="*", color="gold", mec="k", ms=13, zorder=5, label="goal")
    ax.plot(*task.start[:2], "o", color="k", ms=5, zorder=5, label="start")
    xy = replayed["path"]  # [S + 1] points: command k drives segment k
    segments = [[xy[k], xy[k + 1]] for k in range(len(xy) - 1)]
    cmap = plt.get_cmap("RdYlGn")
    if trace and len(trace) == len(segments):
        lc = LineCollection(segments, cmap=cmap, norm=plt.Normalize(0, 1), lw=2.2, zorder=4)
        lc.set_array([e["free_share"] for e in trace])
        ax.add_collection(lc)
        cax = make_axes_locatable(ax).append_axes("right", size="1.5%", pad=0.08)  # as tall as the map
        fig.colorbar(lc, cax=cax, label="share of proposals\ncollision-free")
    else:
        ax.add_collection(LineCollection(segments, colors="k", lw=1.5, zorder=4))
    if replayed["outcome"] == "collision":
        ax.plot(*xy[-1], marker="X", color="red", mec="k", ms=12, zorder=6, label="collision")
    ax.set_xlim(xmin - 0.3, xmax + 0.3)
    ax.set_ylim(ymin - 0.3, ymax + 0.3)
    ax.set_aspect("equal")
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title(title, fontsize=10)
    if trace:  # each command's share holds until the next command (the last: until the episode's end)
        ts, shares = [e["t"] for e in trace], [e["free_share"] for e in trace]
        ax_t.step(ts + [replayed["time"]], shares + shares[-1:], where="post", color="tab:blue", lw=1)
    if replayed["outcome"] == "collision":
        ax_t.axvline(replayed["time"], color="red", lw=1, ls="--", label="collision")
        ax_t.legend(fontsize=8, loc="upper right")
    ax_t.set_xlim(0, 1.01 * max(replayed["time"], 1e-9))
    ax_t.set_ylim(-0.03, 1.03)
    ax_t.set_xlabel("time (s)")
    ax_t.set_ylabel("free share")
    ax_t.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path, tight=False)
    plt.close(fig)
    return Path(path)


def make_parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m eval.navigate replay", description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="the benchmark folder (python -m eval.navigate --out)")
    p.add_argument("--key", required=True, help="the episode: suite/task_id/method/budget/repeat")
    p.add_argument("--cache", type=Path, default=Path("out/navigate/cache"),
                   help="where the robot's tables are kept (default: out/navigate/cache)")
    p.add_argument("--barn-file", type=Path, default=None, help="the run's BARN maps (default: the shipped file)")
    p.add_argument("--table", type=Path, default=None, help="the run's max-flow table (default: the robot's, cached)")
    p.add_argument("--coverage-table", type=Path, default=None, help="the run's coverage table (cu_coverage)")
    p.add_argument("--policy", type=Path, default=None, help="the run's distilled MLP (cu_mlp)")
    p.add_argument("--map-policy", type=Path, default=None, help="the run's map-conditioned policy (cfu_mppi)")
    p.add_argument("--png", type=Path, default=None, help="the figure (default: DIR/replay/<key, / as _>.png)")
    p.add_argument("--json", type=Path, default=None, help="also write the trace and summary here")
    add_system_module_arg(p)
    return p


@cli_main()
def main(argv: Sequence[str] | None = None) -> int:
    args = make_parser().parse_args(argv)
    if args.json is not None:
        check_output_file(args.json, "--json", "replay.json")
    import_system_modules(args.system_module)
    given = {"table": args.table, "coverage_table": args.coverage_table, "policy": args.policy,
             "map_policy": args.map_policy}
    got = replay_episode(args.out, args.key, given, args.cache, args.barn_file)
    stored, replayed, trace = got["stored"], got["replayed"], got["trace"]
    summary = summarize(replayed, trace)
    print("\n".join(_summary_lines(args.key, summary)))
    differ = compare_records(stored, replayed)
    if differ:
        print(f"warning: the replay does not reproduce the stored record ({'; '.join(differ)}): a different torch "
              "build or machine, or changed code or files, since the run")
    else:
        print("reproduced (outcome, steps and path length as stored)")
    png = args.png or Path(args.out) / "replay" / (args.key.replace("/", "_") + ".png")
    title = f"{args.key}: {replayed['outcome']} after {replayed['time']:g} s, {replayed['path_length']:.2f} m"
    print(f"wrote {plot_replay(got['task'], replayed, trace, png, title)}")
    if args.json is not None:
        write_json(args.json, dict(key=args.key, reproduced=not differ, differs=differ, summary=summary,
                                   stored=stored, replayed=replayed, trace=trace))
        print(f"wrote {args.json}")
    sys.stdout.flush()
    return 0
