"""The flags of ``python -m precompute.build`` (:mod:`precompute.build`): four subcommands, each showing only its
own flags, a config file that is the typed job (``--config FILE``, ``--print-config``), and the checks of their
combination.

* ``maxflow``: one table by the paper's flow network; ``coverage``: one table by the coverage method;
  ``set``: a table set, one table per start, into a folder; ``safe``: one safe table (``--map FILE``). ``set``
  and ``safe`` take ``--method maxflow|coverage`` and the flags of both methods (those of the other method refused).
* A system's parameters are ``--param KEY=VALUE`` (a JSON value, checked against the system dataclass's field
  types); the per-system flags of the old command (``--num-actions 3``) are gone from the parsers.
* ``--print-config`` prints the job the flags describe as JSON and builds nothing; ``--config FILE`` reads such a
  file (JSON, or TOML for ``.toml``) back: :data:`CONFIG_KEYS` are its keys, the fields of
  :class:`~precompute.one_table.TableJob` (``build`` a :class:`~precompute.flow.builder.BuildConfig`, ``coverage``
  a :class:`~precompute.coverage.method.CoverageConfig`, ``system`` the system's name and parameters). The file is
  strict: an unknown key, a wrong type or a key of the other method is one error naming the key. Flags given
  beside ``--config`` override its values.
* The old spelling (flags without a subcommand, ``--method coverage``, ``--starts``, ``--map``, ``--num-actions 3``)
  is translated by :func:`legacy_argv` for one release; the command prints the new spelling as a one-line note.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import types
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

from cuniform_torch.systems import _REGISTRY, DEFAULT_HORIZON, System, known_systems, resolve_system, system_horizon
from precompute.cli import (
    OUT,
    ArgumentParser,
    CLIError,
    add_dataclass_args,
    config_fields,
    config_json,
    config_value,
    dataclass_from_args,
    device_arg,
    field_docs,
    flag_name,
    flags_listing,
    horizon_arg,
    import_system_modules,
    int_in,
    non_negative_int,
    positive_int,
    read_config_file,
    threads_arg,
)
from precompute.flow.builder import BuildConfig
from precompute.levels.safe_map import map_overrides
from precompute.levels.sets import PointMode
from precompute.one_table import TableJob
from precompute.system_args import load_user_systems, make_cli_system, parse_params, register_factory

__all__ = ["make_parser", "check_flags", "parse_build_args", "system_of", "table_job", "job_config", "legacy_argv",
           "COMMANDS", "CONFIG_KEYS", "MAXFLOW_ONLY", "COVERAGE_ONLY", "SetOptions"]

PROG = "python -m precompute.build"

COMMANDS = {
    "maxflow": "one table by the paper's flow network (level sets + exact max-flow)",
    "coverage": "one table by the coverage method: maximize the expected coverage of real rollouts over the reachable "
                "states (precompute/coverage/method.py)",
    "set": "a table set: one table per start, into the folder --out (precompute/table_set.py)",
    "safe": "one safe table (C-Free-Uniform): level sets without the cells within --radius of a local map's obstacles "
            "(precompute/levels/safe_map.py)",
}
"""the subcommands and their one-line descriptions"""

MAXFLOW_ONLY = ("points", "points_per_cell", "ties", "resume", "max_memory_gb")
"""settings of the max-flow method only (refused with the coverage method)"""
COVERAGE_ONLY = ("target_samples", "merge_resolution", "steps", "lr", "state_budget", "tol")
"""flags of the coverage method only: fields of :class:`~precompute.coverage.method.CoverageConfig`"""
COVERAGE_DERIVED = ("horizon", "start", "local_map", "radius")
"""CoverageConfig fields that come from the build's (never a key of the config's ``coverage`` section)"""
REPORT_FIELDS = ("report", "rollouts", "device")
"""TableJob fields of the report of one table (a table set's members have no report)"""


@dataclass(frozen=True)
class SetOptions:
    """The table-set part of ``set`` (the ``set`` section of its config)."""

    starts: str
    """one table per start: a grid 'DIM=LO:HI:N ...' or a seeded sample 'random:N DIM=LO:HI ...' over the non-pose
    dimensions (precompute/table_set.py)"""
    workers: int = 1
    """tables built in parallel processes"""
    ray: str | None = None
    """build the tables as Ray tasks: 'local' (a local runtime) or a cluster address (None: no Ray)"""
    no_limit: bool = False
    """allow a set of more than 10,000 tables (MAX_SET_MEMBERS)"""


CONFIG_KEYS = {
    "system": "object: name (a registered system, or module:factory) and the system's parameters",
    "system_modules": "list of modules to import first (they register user systems)",
    "out": "the table file (the folder of a table set)",
    "build": "object: the BuildConfig fields (horizon, seed, start; points, points_per_cell, ties for the max-flow "
             "method; radius for a safe table)",
    "coverage": "object: the CoverageConfig fields of the coverage method (none of horizon, start, local_map, radius)",
    "map": "the local map file of a safe table",
    "set": "object: starts, workers, ray, no_limit of a table set",
    "report": "measure and print the table's uniformity", "rollouts": "rollouts of the report",
    "device": "torch device of the report", "resume": "continue from the checkpoints (max-flow)",
    "max_memory_gb": "memory budget of the size guidance (max-flow)", "quiet": "no progress bar",
}
"""the keys of a ``--config`` file (what ``--print-config`` writes for each subcommand is a subset)"""


def _system_fields() -> dict[str, dataclasses.Field]:
    """Constructor fields of every registered dataclass system (the old command's per-system flags)."""
    out: dict[str, dataclasses.Field] = {}
    for factory in _REGISTRY.values():
        if dataclasses.is_dataclass(factory):
            for f in dataclasses.fields(factory):
                if f.init:
                    out.setdefault(f.name, f)
    return out


def _methods(command: str) -> tuple[str, ...]:
    return {"maxflow": ("maxflow",), "coverage": ("coverage",)}.get(command, ("maxflow", "coverage"))


class _BuildParser(ArgumentParser):
    """The top parser: an unknown flag that another subcommand has (or an old per-system flag) is named as such."""

    owners: dict[str, list[str]] = {}
    argv: list[str] = []

    def parse_known_args(self, args=None, namespace=None):  # type: ignore[override]
        self.argv = list(args or [])
        return super().parse_known_args(args, namespace)

    def error(self, message: str) -> NoReturn:
        if message.startswith("unrecognized arguments:"):
            command = next((a for a in self.argv if a in COMMANDS), "")
            for word in message.split(":", 1)[1].split():
                flag = word.split("=", 1)[0]
                if flag in self.owners:
                    subs = ", ".join(self.owners[flag])
                    super().error(f"{flag} is not a flag of {command}; it is one of {subs}'s")
                field = flag[2:].replace("-", "_")
                if flag.startswith("--") and field in _system_fields():
                    super().error(f"{flag} is a system parameter: give --param {field}=VALUE")
        super().error(message)


def make_parser() -> argparse.ArgumentParser:
    """The command's parser: a subparser per :data:`COMMANDS`, each with its own flags only; the settings of the
    table are fields of :class:`BuildConfig`, :class:`CoverageConfig` and :class:`TableJob`, whose defaults they
    show (the only copy of each: every such flag's parser default is ``argparse.SUPPRESS``)."""
    parser = _BuildParser(prog=PROG, description="Build a C-Uniform action-probability table and report its "
                          f"uniformity. {PROG} SUB --help lists the flags of a subcommand.")
    subs = parser.add_subparsers(dest="command", required=True, metavar="{" + ",".join(COMMANDS) + "}",
                                 parser_class=ArgumentParser)
    owners: dict[str, list[str]] = {}
    for name, text in COMMANDS.items():
        sub = subs.add_parser(name, help=text, description=text[0].upper() + text[1:] + ".")
        _add_flags(sub, name)
        for action in sub._actions:
            for option in action.option_strings:
                owners.setdefault(option, []).append(name)
    parser.owners = owners
    parser.epilog = flags_listing({name: [f for f, subs in owners.items() if name in subs] for name in COMMANDS})
    parser.formatter_class = argparse.RawDescriptionHelpFormatter  # the listing keeps its lines (flags unbroken)
    return parser


def _add_flags(parser: argparse.ArgumentParser, command: str) -> None:
    """The flags of the subcommand ``command``."""
    from precompute.coverage.method import CoverageConfig

    one_table = command != "set"
    parser.add_argument("--config", type=Path, default=None, metavar="FILE",
                        help="read the job from FILE (JSON, or TOML for .toml: what --print-config writes); flags "
                             "given beside it override its values")
    parser.add_argument("--print-config", action="store_true",
                        help="print the job these flags describe as a --config file (JSON) and build nothing")
    parser.add_argument("--system", default=argparse.SUPPRESS,
                        help=f"system name (known: {', '.join(known_systems())}) or module:factory of a user system "
                             "(default: dubins)")
    parser.add_argument("--system-module", action="append", default=[], metavar="MODULE",
                        help="import MODULE first (repeatable); it registers user systems with register_system")
    parser.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                        help="a system parameter as JSON (repeatable), e.g. --param num_actions=7 --param "
                             "'cell_size=[0.1, 0.1, 0.2]' (the system's fields: cuniform_torch/systems)")
    where = "folder" if command == "set" else "table file"
    default_out = f"{OUT}/<system>_set" if command == "set" else f"{OUT}/<system>.npz"
    parser.add_argument("--out", type=Path, default=argparse.SUPPRESS,
                        help=f"{where} to write (default: {default_out})")
    parser.add_argument("--horizon", type=horizon_arg, default=argparse.SUPPRESS,
                        help=f"number of steps T (default: the system's default_horizon, else {DEFAULT_HORIZON})")
    add_dataclass_args(parser, BuildConfig, only=("seed", "start") if one_table else ("seed",),
                       arg_types={"seed": non_negative_int}, help={
        "start": "the state to build from, one number per state dimension (default: the zero state); an "
                 "SE(2)-invariant system's x, y, theta must be 0 (its table serves every pose), e.g. --system ks_speed "
                 "--start 0 0 0 0.5",
        "seed": "seed of --points random and of the report's rollouts",
    })
    parser.add_argument("--threads", type=threads_arg, default=1,
                        help="torch CPU threads (0: torch's choice, one per core). 1 by default: the build's tensors "
                             "are small, and on a busy machine extra threads only wait for each other")
    add_dataclass_args(parser, TableJob, only=("quiet", *(REPORT_FIELDS if one_table else ())),
                       flags={"report": "--no-report"},
                       arg_types={"rollouts": positive_int, "device": device_arg},
                       help={"report": "skip the uniformity report",
                             "rollouts": "rollouts for the report (default: 10 x largest level)",
                             "device": "device for the report's rollouts (cpu, cuda; default: cpu)",
                             "quiet": "no progress bar"})
    if command == "safe":
        parser.add_argument("--map", dest="map_file", type=Path, default=argparse.SUPPRESS, metavar="FILE",
                            help="the local map in the start frame (precompute/levels/safe_map.py; required): safe "
                                 "level sets without the cells within --radius of its obstacles (SE(2)-invariant "
                                 "systems)")
        add_dataclass_args(parser, BuildConfig, only=("radius",), metavars={"radius": "R"},
                           help={"radius": "the robot's radius (m) the map's obstacles are inflated by"})
    if command == "set":
        docs = field_docs(SetOptions)
        parser.add_argument("--starts", default=argparse.SUPPRESS, metavar="SPEC", help=docs["starts"] + " (required)")
        add_dataclass_args(parser, SetOptions, only=("workers", "no_limit"), arg_types={"workers": int_in(1, 1024)})
        parser.add_argument("--ray", nargs="?", const="local", default=argparse.SUPPRESS, metavar="ADDRESS",
                            help="build the tables as Ray tasks (a local runtime, or the cluster at ADDRESS)")
    methods = _methods(command)
    if len(methods) == 2:
        parser.add_argument("--method", choices=methods, default=argparse.SUPPRESS,
                            help="maxflow: the paper's flow network (default); coverage: the coverage method "
                                 "(its flags below; those of the other method are refused)")
    if "maxflow" in methods:
        group = parser.add_argument_group("max-flow method") if len(methods) == 2 else parser
        add_dataclass_args(group, BuildConfig, only=("points", "points_per_cell", "ties"),
                           arg_types={"points_per_cell": positive_int}, help={
            "points": "sample points per cell: centers (level sets from cell centres, transitions from the 3^d "
                      "lattice), lattice (level sets from all lattice points), random (centre + K random points)",
            "points_per_cell": "K random points per cell for --points random",
            "ties": "symmetric: a step onto a cell boundary rounds away from its source cell (mirror-symmetric level "
                    "sets, the authors' sizes); grid: the state's own cell (the grid offset decides)",
        })
        add_dataclass_args(group, TableJob, only=("resume", "max_memory_gb"), flags={"max_memory_gb": "--max-memory"},
                           metavars={"max_memory_gb": "GB"}, help={
            "resume": "continue an interrupted build from its checkpoints",
            "max_memory_gb": "memory budget of the size guidance (default: the available memory)"})
    if "coverage" in methods:
        group = parser.add_argument_group("coverage method") if len(methods) == 2 else parser
        docs = field_docs(CoverageConfig)
        add_dataclass_args(group, CoverageConfig, only=COVERAGE_ONLY, help={n: docs[n] for n in COVERAGE_ONLY})


# ------------------------------------------------------------------------------------------ the old spelling

def _legacy_value(field: dataclasses.Field, values: list[str], flag: str) -> str:
    """The JSON ``--param`` value of an old per-system flag's words (``--cell-size 0.1 0.1 0.2`` -> ``[0.1, ...]``)."""
    default = field.default

    def number(text: str, kind: type) -> float | int:
        try:
            return kind(text)
        except ValueError:
            raise CLIError(f"argument {flag}: invalid {kind.__name__} value: {text!r}") from None

    if isinstance(default, tuple):
        if not values:
            raise CLIError(f"argument {flag}: expected at least one argument")
        return json.dumps([number(v, float) for v in values])
    if len(values) != 1:
        raise CLIError(f"argument {flag}: expected one argument")
    (text,) = values
    if isinstance(default, bool):
        return json.dumps(text.lower() in ("1", "true", "yes"))
    if isinstance(default, int):  # the old flags' check: the systems' integer parameters are counts
        try:
            return json.dumps(positive_int(text))
        except argparse.ArgumentTypeError as exc:
            raise CLIError(f"argument {flag}: {exc}") from None
    if isinstance(default, str):
        return json.dumps(text)
    return json.dumps(number(text, float))


def _param_items(argv: Sequence[str]) -> list[str]:
    """The ``KEY=VALUE`` items of ``--param`` in ``argv`` (``--param K=V`` or ``--param=K=V``)."""
    items = []
    for i, word in enumerate(argv):
        if word == "--param" and i + 1 < len(argv):
            items.append(argv[i + 1])
        elif word.startswith("--param="):
            items.append(word[len("--param="):])
    return items


def legacy_argv(argv: Sequence[str]) -> tuple[list[str], str | None]:
    """``(argv, note)``: the old spelling (no subcommand) translated, and the one-line deprecation note naming the
    new command (None when ``argv`` already starts with a subcommand). The subcommand follows the old mode flags:
    ``--starts`` (or ``--workers``, ``--ray``, ``--no-limit``) -> set, ``--map`` (or ``--radius``) -> safe, ``--method coverage`` -> coverage, else maxflow; each per-system flag
    (``--num-actions 3``) becomes ``--param num_actions=3``; no flags at all is ``maxflow`` (the old default build)."""
    argv = list(argv)
    if argv and (not argv[0].startswith("-") or argv[0] in ("-h", "--help")):
        return argv, None  # a subcommand (or a misspelt one, which argparse names with the valid choices)
    fields = _system_fields()
    flags = {flag_name(n): n for n in fields}
    out: list[str] = []
    params: list[str] = []
    method: str | None = None
    i = 0
    while i < len(argv):
        option, eq, inline = argv[i].partition("=")
        if option in flags and argv[i] not in ("--",):
            if eq:
                values, i = [inline], i + 1
            else:
                j = i + 1
                while j < len(argv) and not argv[j].startswith("--"):
                    j += 1
                values, i = argv[i + 1:j], j
            params.append(f"{flags[option]}={_legacy_value(fields[flags[option]], values, option)}")
            continue
        if option == "--method" and (eq or i + 1 < len(argv)):
            method = inline if eq else argv[i + 1]
            if method not in ("maxflow", "coverage"):
                raise CLIError(f"argument --method: invalid choice: {method!r} (choose from 'maxflow', 'coverage')")
            i += 1 if eq else 2
            continue
        out.append(argv[i])
        i += 1
    given = {a.partition("=")[0] for a in out}
    explicit = {item.partition("=")[0].replace("-", "_") for item in _param_items(out)}
    for key in sorted(explicit & {p.partition("=")[0] for p in params}):
        raise CLIError(f"{key} given both as a flag and as --param; give it once (--param {key}=VALUE)")
    if "--starts" in given and "--map" in given:
        raise CLIError("--map builds one safe table; a table set (--starts) takes no map (see precompute.maps.farm)")
    if "--starts" in given and "--start" in given:
        raise CLIError("give --start (one table) or --starts (a table set), not both")
    command = ("set" if given & {"--starts", "--workers", "--ray", "--no-limit"} else "safe" if given & {"--map", "--radius"}
               else "coverage" if method == "coverage" else "maxflow")
    if command == "set":
        out = [a for a in out if a != "--no-report"]  # a set's members never had a report
    if command in ("set", "safe") and method is not None:
        out += ["--method", method]
    new = [command, *out, *(w for p in params for w in ("--param", p))]
    note = (f"note: {PROG} without a subcommand is deprecated and goes in the next release; the same build is: "
            f"{PROG} {shlex.join(new)}")
    return new, note


# ------------------------------------------------------------------------------------------ the config file

def _config_allowed(command: str, method: str) -> tuple[set[str], set[str]]:
    """``(top-level keys, build keys)`` of a config for ``command`` with ``method``."""
    top = {"system", "system_modules", "out", "build", "quiet"}
    build = {"horizon", "seed"}
    if command != "set":
        top |= set(REPORT_FIELDS)
        build.add("start")
    if method == "maxflow":
        top |= {"resume", "max_memory_gb"}
        build |= {"points", "points_per_cell", "ties"}
    if "coverage" in _methods(command):
        top.add("coverage")
    if command == "safe":
        top.add("map")
        build.add("radius")
    if command == "set":
        top.add("set")
    return top, build


def apply_config(args: argparse.Namespace, data: dict[str, Any]) -> None:
    """Fill ``args`` from the config ``data`` (read from ``args.config``) where a flag was not given (a flag
    beside ``--config`` wins); one CLIError naming the first key that is unknown, of the wrong type, or of another
    subcommand or method."""
    from precompute.coverage.method import CoverageConfig

    command, where = args.command, f"config {args.config}: "
    given_method = getattr(args, "method", None)
    coverage = data.get("coverage")
    if command == "maxflow":
        method = "maxflow"
    elif command == "coverage":
        method = "coverage"
    else:
        method = given_method or ("coverage" if coverage is not None else "maxflow")
    top, build_keys = _config_allowed(command, method)
    for key in data:
        if key not in top:
            if key in CONFIG_KEYS:
                raise CLIError(f"{where}{key} does not apply to {command}" + (f" with --method {method}"
                               if len(_methods(command)) == 2 else "") + "; remove it")
            raise CLIError(f"{where}{key} is not a known key; the known keys of {command}: {', '.join(sorted(top))}")
    if coverage is not None and method != "coverage":
        raise CLIError(f"{where}coverage is the coverage method's section, but --method {method} was given; drop one")
    args.config_keys = {}

    def fill(dest: str, value: Any, key: str) -> None:
        if not hasattr(args, dest):
            setattr(args, dest, value)
            args.config_keys[dest] = key

    modules = config_value(list[str], data.get("system_modules", []), f"{where}system_modules")
    import_system_modules(modules)
    args.system_module = [*modules, *args.system_module]
    if "system" in data:
        system = dict(_section(data["system"], f"{where}system"))
        name = system.pop("name", None)
        if not isinstance(name, str):
            raise CLIError(f"{where}system.name must be a string (a registered system, or module:factory)")
        if hasattr(args, "system") and args.system != name:
            raise CLIError(f"--system {args.system} differs from the config's system.name {name!r}; drop --system or "
                           "edit the config")
        if ":" in name:
            register_factory(name)
        args.system = name
        args.config_params = system
    if "out" in data:
        fill("out", config_value(Path, data["out"], f"{where}out"), "out")
    if "map" in data:
        fill("map_file", config_value(Path, data["map"], f"{where}map"), "map")
    why = {k: f"applies to the max-flow method only, not to {command}" + (f" --method {method}" if command != method
           else "") for k in ("points", "points_per_cell", "ties")}
    why.update({"start": "does not apply to a table set (each member is built from its start)",
                "radius": "applies to a safe table only (the safe subcommand)"})
    for key, value in config_fields(BuildConfig, data.get("build", {}), f"{where}build.", allowed=build_keys,
                                    why=why).items():
        fill(key, value, f"build.{key}")
    if coverage is not None:
        allowed = [f.name for f in dataclasses.fields(CoverageConfig) if f.init and f.name not in COVERAGE_DERIVED]
        for key, value in config_fields(CoverageConfig, coverage, f"{where}coverage.", allowed=allowed,
                                        why={k: "comes from the build section" for k in COVERAGE_DERIVED}).items():
            fill(key, value, f"coverage.{key}")
    if "set" in data:
        for key, value in config_fields(SetOptions, data["set"], f"{where}set.").items():
            fill(key, value, f"set.{key}")
    job_keys = {k: data[k] for k in data if k in {f.name for f in dataclasses.fields(TableJob)}
                and k not in ("system", "out", "build", "coverage")}
    for key, value in config_fields(TableJob, job_keys, where).items():
        fill(key, value, key)
    if len(_methods(command)) == 2 and not hasattr(args, "method"):
        args.method = method


def _section(data: Any, where: str) -> dict[str, Any]:
    """A config section that must be an object, as a dict (its values checked later, by their owner)."""
    if not isinstance(data, dict):
        raise CLIError(f"{where} must be an object (a table of keys), got {type(data).__name__}")
    return data


def job_config(args: argparse.Namespace, job: TableJob, table_set: dict) -> dict[str, Any]:
    """The config (``--print-config``) of the job the parsed ``args`` describe: ``--config`` of it builds the same
    :class:`TableJob` (and table set)."""
    command = args.command
    system = job.system
    params = system.params() if callable(getattr(system, "params", None)) else {}
    top, build_keys = _config_allowed(command, job.method)
    out: dict[str, Any] = {"system": {"name": getattr(args, "system", "dubins"), **config_json(params)}}
    if args.system_module:
        out["system_modules"] = list(args.system_module)
    out["out"] = str(table_set["out"] if table_set else job.out)
    out["build"] = {k: config_json(getattr(job.build, k)) for k in ("horizon", "seed", "start", "points",
                                                                    "points_per_cell", "ties", "radius")
                    if k in build_keys}
    if job.build.points is not PointMode.RANDOM:
        out["build"].pop("points_per_cell", None)  # it applies to --points random only (check_flags)
    if job.coverage is not None:
        out["coverage"] = {k: v for k, v in config_json(job.coverage).items()
                           if k not in COVERAGE_DERIVED}
    if command == "safe":
        out["map"] = str(args.map_file)
    if table_set:
        out["set"] = {"starts": args.starts, "workers": table_set["workers"], "ray": table_set["ray_address"],
                      "no_limit": bool(getattr(args, "no_limit", False))}
    for key in ("report", "rollouts", "device", "resume", "max_memory_gb", "quiet"):
        if key in top:
            out[key] = config_json(getattr(job, key))
    return out


# ------------------------------------------------------------------------------------------ checks and the job

def _name(args: argparse.Namespace, dest: str) -> str:
    """How the user gave ``dest``: its flag, or its config key."""
    key = getattr(args, "config_keys", {}).get(dest)
    return f"{key} in {args.config}" if key else {"max_memory_gb": "--max-memory", "report": "--no-report"}.get(
        dest, flag_name(dest))


def check_flags(args: argparse.Namespace) -> None:
    """Refuse settings that the chosen method or points mode would ignore (naming both), and a missing ``--starts``
    / ``--map``."""
    method = getattr(args, "method", args.command if args.command in ("maxflow", "coverage") else "maxflow")
    args.method = method
    other, foreign = ("coverage", COVERAGE_ONLY) if method == "maxflow" else ("maxflow", MAXFLOW_ONLY)
    for name in foreign:
        if hasattr(args, name):
            hint = f" (give --method {other})" if len(_methods(args.command)) == 2 else ""
            raise CLIError(f"{_name(args, name)} applies to the {other} method only, not to {method}{hint}")
    points = getattr(args, "points", BuildConfig().points)
    points = PointMode.parse(points).value
    if hasattr(args, "points_per_cell") and points != PointMode.RANDOM.value:
        raise CLIError(f"{_name(args, 'points_per_cell')} applies to --points random only, not to --points {points}")
    if getattr(args, "rollouts", None) is not None and getattr(args, "report", True) is False:
        raise CLIError(f"{_name(args, 'rollouts')} sets the report's rollouts, but {_name(args, 'report')} skips "
                       "the report")
    if args.command == "set" and not hasattr(args, "starts"):
        raise CLIError("set needs --starts SPEC, the starts of its tables (or set.starts in the --config file): give "
                       "--starts too")
    if args.command == "safe" and not hasattr(args, "map_file"):
        raise CLIError("safe needs --map FILE, the local map whose obstacles --radius inflates (or map in the --config "
                       "file): give --map too")


def parse_build_args(argv: Sequence[str]) -> argparse.Namespace:
    """The flags ``argv`` of a build (the old spelling translated silently: :func:`legacy_argv`), user system modules
    imported first, the ``--config`` file read under the flags and combinations checked."""
    argv = list(argv)
    load_user_systems(argv)
    argv, _ = legacy_argv(argv)
    args = make_parser().parse_args(argv)
    if args.config is not None:
        apply_config(args, read_config_file(args.config))
    check_flags(args)
    return args


def _typed_params(name: str, params: dict[str, Any], where: str) -> dict[str, Any]:
    """``params`` of the system ``name`` checked against its dataclass field types (a user factory's are passed as
    they are); an unknown parameter is left to :func:`make_system`'s message, which lists the known ones."""
    import typing

    factory = _REGISTRY.get(name)
    if factory is None or not dataclasses.is_dataclass(factory):
        return dict(params)
    hints = typing.get_type_hints(factory)
    return {k: config_value(hints[k], v, f"{where}{k}") if k in hints else v for k, v in params.items()}


def system_of(args: argparse.Namespace) -> tuple[str, System]:
    """The registry name and the system the flags describe: ``--system`` (default dubins), the config's parameters,
    then ``--param`` (which wins)."""
    spec = getattr(args, "system", None) or "dubins"
    name = resolve_system(spec)
    params = _typed_params(name, getattr(args, "config_params", {}), f"config {getattr(args, 'config', '')}: system.")
    params.update(_typed_params(name, parse_params(getattr(args, "param", [])), "--param "))
    return name, make_cli_system(spec, name, params)


def table_job(args: argparse.Namespace, system: System, out: Path) -> TableJob:
    """The :class:`TableJob` that the parsed flags ``args`` describe (the one path from flags to a job, so each
    default lives in its dataclass only)."""
    from precompute.coverage.method import CoverageConfig

    horizon = getattr(args, "horizon", None) or system_horizon(system)
    maps = types.SimpleNamespace(map_file=getattr(args, "map_file", None), map_radius=getattr(args, "radius", None))
    map_fields = map_overrides(maps, system)
    build = dataclass_from_args(BuildConfig, args, horizon=horizon, **map_fields)
    coverage = None
    if getattr(args, "method", "maxflow") == "coverage":
        coverage = dataclass_from_args(CoverageConfig, args, horizon=horizon, local_map=build.local_map,
                                       radius=build.radius)
    return dataclass_from_args(TableJob, args, system=system, out=out, build=build, coverage=coverage)
