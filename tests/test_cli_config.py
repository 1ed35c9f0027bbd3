"""One config -> CLI path: flags made from config dataclasses (precompute.cli.add_dataclass_args), and no CLI
default that can drift from its dataclass default (every entry point's config flags are checked)."""

from __future__ import annotations

import argparse
import dataclasses
import enum
import importlib
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from precompute.cli import ArgumentParser, add_dataclass_args, dataclass_from_args, field_docs, given_fields


class Color(enum.Enum):
    RED = "red"
    BLUE = "blue"


@dataclass(frozen=True)
class Base:
    seed: int = 0
    """draws everything"""


@dataclass(frozen=True)
class Toy(Base):
    """A config with one field of every kind the helper handles."""

    rate: float = 0.5
    """learning rate, 50%% of nothing"""
    name: str = "x"
    out: Path | None = None
    """where to write (default: next to the input)"""
    sizes: tuple[int, ...] = (1, 2)
    """N values"""
    keys: list[str] = field(default_factory=list)
    color: Color = Color.RED
    quiet: bool = False
    """no progress bar"""
    stop: bool = True
    """stop at the goal"""
    count: int = field(default=3, metadata={"help": "how many, from metadata"})


def _parser(**kwargs) -> argparse.ArgumentParser:
    p = ArgumentParser(prog="toy")
    add_dataclass_args(p, Toy, flags={"stop": "--go-on"}, **kwargs)
    return p


def test_flags_parse_into_the_config():
    args = _parser().parse_args(["--rate", "0.1", "--sizes", "4", "5", "--keys", "a", "b", "--color", "blue",
                                 "--quiet", "--go-on", "--out", "o.json", "--seed", "7"])
    cfg = dataclass_from_args(Toy, args)
    assert cfg == Toy(seed=7, rate=0.1, out=Path("o.json"), sizes=(4, 5), keys=["a", "b"], color="blue", quiet=True,
                      stop=False)
    assert isinstance(cfg.sizes, tuple) and isinstance(cfg.keys, list)


def test_flags_not_given_leave_the_dataclass_default_or_the_base():
    args = _parser().parse_args([])
    assert vars(args) == {} and given_fields(Toy, args) == {}
    assert dataclass_from_args(Toy, args) == Toy()
    quick = Toy(sizes=(9,), rate=0.9)
    assert dataclass_from_args(Toy, _parser().parse_args(["--rate", "0.2"]), base=quick) == Toy(sizes=(9,), rate=0.2)
    assert dataclass_from_args(Toy, args, base=quick, name="y") == Toy(sizes=(9,), rate=0.9, name="y")


def test_help_shows_the_docstring_and_the_dataclass_default():
    text = " ".join(_parser().format_help().split())
    assert "learning rate, 50%% of nothing (default: 0.5)" in text
    assert "N values (default: 1 2)" in text and "draws everything (default: 0)" in text  # a base class's field
    assert "where to write (default: next to the input)" in text  # the docstring already names the default
    assert "how many, from metadata (default: 3)" in text
    assert "{red,blue} default: red" in text  # no docstring: the default alone
    assert "no progress bar" in text and "(default: False)" not in text
    assert field_docs(Toy)["seed"] == "draws everything"


def test_only_exclude_help_and_bad_names():
    p = ArgumentParser(prog="toy")
    assert add_dataclass_args(p, Toy, only=("rate", "seed"), help={"rate": "the rate"}) == ["rate", "seed"]
    assert "--name" not in p.format_help() and "the rate (default: 0.5)" in " ".join(p.format_help().split())
    with pytest.raises(TypeError, match="no field"):
        add_dataclass_args(ArgumentParser(), Toy, only=("nope",))
    with pytest.raises(TypeError, match="defaults to True"):
        add_dataclass_args(ArgumentParser(), Toy, only=("stop",))  # a switch that clears it needs a name


# ------------------------------------------------------------------------------------------ no drifting defaults

def command_parsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """``{"": parser}`` and, for a command with subcommands (``precompute.build maxflow``), each subcommand's."""
    out = {"": parser}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            out.update(action.choices)
    return out


def all_actions(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """The actions of ``parser`` and of its subcommands' parsers."""
    return [a for p in command_parsers(parser).values() for a in p._actions]


DERIVED = {"precompute.build": ("horizon",)}
"""flags whose default is not the dataclass's by design: the build's ``--horizon`` is the system's
``default_horizon`` (the help says so)"""


def _entry_points():
    """(name, parser, config classes whose fields are flags) of every entry point with a config dataclass."""
    from precompute import build
    from precompute.coverage.method import CoverageConfig
    from precompute.flow.builder import BuildConfig
    from precompute.one_table import TableJob
    from training import distill

    out = [("precompute.build", build.make_parser(), (BuildConfig, CoverageConfig, TableJob, build.SetOptions)),
           ("training.distill", distill.make_parser(), (distill.DistillConfig,))]
    for name in EVAL_EXPERIMENTS:
        module = importlib.import_module(name)
        out.append((name, module.make_parser(), (module.CONFIG,)))
    return out


EVAL_EXPERIMENTS = ("eval.paper.coverage", "eval.paper.uniformity", "eval.paper.sudden_obstacle", "eval.paper.cluttered")


def check_no_drift(parser: argparse.ArgumentParser, configs, derived=()) -> list[str]:
    """Problems: a flag of a config field with a parser default of its own (a second copy of the default), or
    whose help names another default than the dataclass's (a None default is explained by the help's words)."""
    from precompute.cli import _show  # the helper's own rendering of a default

    problems = []
    for cls in configs:
        defaults = {f.name: (f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default)
                    for f in dataclasses.fields(cls)}
        for action in all_actions(parser):
            if action.dest not in defaults or action.dest in ("help", "system_module", *derived):
                continue
            if defaults[action.dest] is dataclasses.MISSING:  # a required field (TableJob.out): no default to drift
                continue
            if action.default is not argparse.SUPPRESS:
                problems.append(f"{action.option_strings[0]}: parser default {action.default!r} beside "
                                f"{cls.__name__}.{action.dest} = {defaults[action.dest]!r}")
            text = " ".join((action.help or "").split())
            if "(default: " in text:
                shown = text.rsplit("(default: ", 1)[1].rstrip(")")
                if defaults[action.dest] is not None and shown != _show(defaults[action.dest]):
                    problems.append(f"{action.option_strings[0]}: help says default {shown!r}, "
                                    f"{cls.__name__}.{action.dest} = {defaults[action.dest]!r}")
    return problems


@pytest.mark.parametrize("name, parser, configs", _entry_points(), ids=lambda v: v if isinstance(v, str) else "")
def test_no_cli_default_drifts_from_its_dataclass(name, parser, configs):
    assert check_no_drift(parser, configs, DERIVED.get(name, ())) == []


def test_a_planted_second_default_is_found():
    """The check itself: a flag added by hand with its own default (the old way) is reported."""
    from precompute import build
    from precompute.coverage.method import CoverageConfig

    parser = build.make_parser()
    for action in command_parsers(parser)["coverage"]._actions:
        if action.dest == "steps":
            action.default = 200  # as `add_argument("--steps", type=int, default=200)` would
    (problem,) = check_no_drift(parser, (CoverageConfig,), derived=("horizon",))
    assert "--steps" in problem and "200" in problem and "300" in problem


def test_entry_points_parse_to_the_dataclass_defaults(tmp_path):
    from precompute import build
    from precompute.flow.builder import BuildConfig
    from training import distill

    table = tmp_path / "t.npz"
    table.write_bytes(b"")
    cfg = distill.parse_args(["--tables", str(table), "--out", str(tmp_path / "p.pt"), "--logdir", str(tmp_path)])
    assert cfg == distill.DistillConfig(tables=[str(table)], out=str(tmp_path / "p.pt"), logdir=str(tmp_path))
    for command in build.COMMANDS:
        args = build.make_parser().parse_args([command])
        assert dataclass_from_args(BuildConfig, args, horizon=10) == BuildConfig(), command
    for name in EVAL_EXPERIMENTS:
        module = importlib.import_module(name)
        assert module.config_from_args(module.make_parser().parse_args([])) == module.CONFIG(), name


def test_build_coverage_method_with_its_progress_bar(tmp_path, capsys):
    """The coverage method's settings reach the build through the config (the bar counts levels, then steps)."""
    from precompute import build

    out = tmp_path / "c.npz"
    assert build.main(["coverage", "--system", "random_walk_1d", "--horizon", "2", "--steps", "3",
                       "--target-samples", "50", "--out", str(out), "--no-report"]) == 0
    printed = capsys.readouterr().out
    assert "target N=50" in printed and "levels, then ascent" in printed and out.exists()
