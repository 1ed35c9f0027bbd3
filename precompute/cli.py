"""What every ``python -m`` entry point shares: one-line errors, exit codes, output checks, ``--system-module``,
flags made from a config dataclass, and the default output folders.

Decorate an entry point's ``main(argv) -> int`` with :func:`cli_main`. Clear errors -- the library's
``ValueError`` subclasses (``TableError``, ``PolicyCheckpointError``, ``UnknownSystemError``, ...), a
:class:`CLIError`, an ``OSError`` (a missing file, a full disk, a folder one cannot write) and running out of
memory -- print one line ``error: ...`` on stderr and return :data:`EXIT_ERROR` (2); Ctrl-C prints one line and
returns :data:`EXIT_INTERRUPTED` (130). Any other exception is a bug and keeps its traceback.

Config dataclasses are the one home of a setting's default: :func:`add_dataclass_args` makes a flag of every
field (type, help from the field's docstring, the default shown in the help) whose parser default is
``argparse.SUPPRESS``, so a flag that is not given leaves no attribute; :func:`dataclass_from_args` then
builds the config from the flags that were given, over the dataclass defaults or over a base config (a
``--quick`` preset). A default can therefore not drift between the dataclass and the command line.

Flag values are checked when they parse, so that a bad one is one ``error: argument --flag: ...`` line before any
work: :func:`device_arg` (a torch device this machine has), :func:`int_in` / :func:`float_in` and the common cases
:func:`positive_int` (a count, at most :data:`MAX_COUNT`), :func:`non_negative_int`, :func:`threads_arg`,
:func:`horizon_arg` (at most :data:`MAX_HORIZON`), :func:`positive_float`. The rule for modes: **a flag that
does not apply to the chosen mode is refused** (:func:`refuse_flags`), never silently ignored. A product of counts
(tasks x budgets x methods) is checked by :func:`check_work` against :data:`MAX_WORK` unless ``--no-limit``
(:func:`add_no_limit_arg`) is given.

Ctrl-C while a command's modules are still importing (torch takes seconds) is one line and exit 130 as well: the
command packages install :func:`precompute.startup.exit_on_ctrl_c` when run as ``python -m``; :func:`cli_main`
swaps it for Python's ``KeyboardInterrupt`` while ``main`` runs (which may then say what survives) and back after.
"""

from __future__ import annotations

import argparse
import ast
import collections.abc
import dataclasses
import enum
import functools
import inspect
import math
import os
import re
import signal
import sys
import tempfile
import textwrap
import types
import typing
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, NoReturn

from cuniform_torch.systems import import_system_modules

__all__ = ["EXIT_ERROR", "EXIT_INTERRUPTED", "CLIError", "ArgumentParser", "cli_main", "error_message",
           "out_of_memory_message", "add_system_module_arg", "import_system_modules", "check_output_file", "check_output_folder",
           "OUT", "RUNS", "field_docs", "add_dataclass_args", "dataclass_from_args", "given_fields", "flag_name",
           "MAX_HORIZON", "MAX_COUNT", "MAX_WORK", "device_arg", "int_in", "float_in", "positive_int",
           "non_negative_int", "threads_arg", "horizon_arg", "positive_float", "refuse_flags",
           "add_no_limit_arg", "check_work", "config_value", "config_fields", "config_json",
           "read_config_file", "add_config_args", "dataclass_from_config", "config_text", "flags_listing",
           "parser_flags"]

EXIT_ERROR = 2
EXIT_INTERRUPTED = 130

OUT = Path("out")
"""the folder of everything generated (tables, checkpoints, results, figures); git-ignored"""
RUNS = Path("runs")
"""the folder of TensorBoard runs"""


class CLIError(Exception):
    """A clear error a script finds (conflicting flags, an output it cannot write): ``error: <message>``, exit 2."""


class ArgumentParser(argparse.ArgumentParser):
    """argparse that reports a bad flag as one ``error: ...`` line and exits 2 (no usage block)."""

    def error(self, message: str) -> NoReturn:
        print(f"error: {message} (see {self.prog} --help)", file=sys.stderr)
        raise SystemExit(EXIT_ERROR)


def add_system_module_arg(parser: argparse.ArgumentParser) -> None:
    """The ``--system-module MODULE`` flag (repeatable) of every entry point that reads a table or checkpoint."""
    parser.add_argument("--system-module", action="append", default=[], metavar="MODULE",
                        help="import MODULE first (repeatable); it registers user systems with register_system, "
                             "which reading a table or checkpoint of a user system needs")


def out_of_memory_message(exc: BaseException) -> str | None:
    """A one-line description when ``exc`` is an allocation failure (Python, numpy or torch), else None."""
    text = str(exc)
    if isinstance(exc, MemoryError):
        return f"out of memory ({text})" if text else "out of memory"
    if isinstance(exc, RuntimeError) and ("can't allocate memory" in text or "out of memory" in text.lower()):
        asked = re.search(r"allocate (\d+) bytes", text)
        if asked:
            return f"out of memory: it tried to allocate {int(asked.group(1)) / 1e9:.3g} GB"
        return "out of memory: " + text.splitlines()[0]
    return None


def error_message(exc: BaseException) -> str | None:
    """The one-line message of a clear error, or None for an exception that is a bug."""
    message = out_of_memory_message(exc)
    if message is None and isinstance(exc, OSError) and exc.strerror and exc.filename is not None:
        message = f"{exc.filename}: {exc.strerror}"
        if exc.filename2 is not None:
            message += f" ({exc.filename2})"
    elif message is None and isinstance(exc, (ValueError, CLIError, OSError)):
        message = str(exc) or type(exc).__name__
    if message is None:
        return None
    return " ".join(line.strip() for line in message.splitlines() if line.strip())  # one line, always


def _swap_import_handler() -> Any:
    """While ``main`` runs, Ctrl-C raises ``KeyboardInterrupt`` (so that ``main`` can clean up and say what survives)
    instead of the import-time handler's immediate exit; returns that handler (to restore), or None."""
    try:
        handler = signal.getsignal(signal.SIGINT)
        if getattr(handler, "exit_on_ctrl_c", False):
            signal.signal(signal.SIGINT, signal.default_int_handler)
            return handler
    except ValueError:  # not the main thread: signals are not ours to set
        pass
    return None


def cli_main(interrupted: str = "interrupted") -> Callable[[Callable[..., int]], Callable[..., int]]:
    """Decorator of ``main(argv) -> int``: clear errors become ``error: ...`` and 2, Ctrl-C one line and 130.

    The Ctrl-C line is the message a ``KeyboardInterrupt`` was raised with (a script re-raises one to say what
    survives, e.g. "rerun with --resume"), else ``interrupted``.
    """

    def wrap(main: Callable[..., int]) -> Callable[..., int]:
        @functools.wraps(main)
        def run(argv: Sequence[str] | None = None) -> int:
            importing = _swap_import_handler()
            try:
                return main(argv)
            except KeyboardInterrupt as exc:
                print(str(exc) or interrupted, file=sys.stderr)
                return EXIT_INTERRUPTED
            except Exception as exc:
                message = error_message(exc)
                if message is None:
                    raise  # a bug: keep the traceback
                print(f"error: {message}", file=sys.stderr)
                return EXIT_ERROR
            finally:
                if importing is not None:  # Ctrl-C after main (on the way out) exits 130 in one line again
                    signal.signal(signal.SIGINT, importing)

        return run

    return wrap


def _nearest_existing(path: Path) -> Path:
    for parent in path.parents:
        if parent.exists():
            return parent
    return Path(".")


def _check_folder_writable(path: Path, flag: str) -> None:
    """CLIError unless files can be created in the nearest existing folder at or above ``path``."""
    folder = path if path.is_dir() else _nearest_existing(path)
    if not folder.is_dir():
        raise CLIError(f"{flag} {path}: {folder} is a file, not a folder")
    try:
        with tempfile.TemporaryFile(dir=folder):  # the one reliable test (os.access ignores root, read-only mounts)
            pass
    except OSError as exc:
        raise CLIError(f"{flag} {path}: cannot create files in {folder} ({exc.strerror or exc})") from None


def _check_not_special(path: Path, flag: str, folder: bool) -> None:
    """CLIError when ``path`` exists and is a device, a FIFO or a socket (or a symlink to one): an output never
    replaces ``/dev/null`` nor writes into ``/dev/stdout`` or ``/dev/full``."""
    from cuniform_torch.common.fileio import FileKindError, check_not_special

    try:
        check_not_special(path, "", folder=folder)
    except FileKindError as exc:
        raise CLIError(f"{flag} {exc}".replace(":  is ", " is ", 1)) from None


def check_output_file(path: str | os.PathLike, flag: str, example: str = "out.json") -> None:
    """Before long work starts: CLIError unless ``path`` can become a file (not a folder, its folder writable);
    ``example`` is the file name the message suggests inside a folder."""
    path = Path(path)
    if path.is_dir():
        raise CLIError(f"{flag} {path} is a folder; give a file path such as {path / example}")
    _check_not_special(path, flag, folder=False)
    _check_folder_writable(path, flag)


def check_output_folder(path: str | os.PathLike, flag: str) -> None:
    """Before long work starts: CLIError unless ``path`` is, or can become, a writable folder."""
    path = Path(path)
    _check_not_special(path, flag, folder=True)
    if path.exists() and not path.is_dir():
        raise CLIError(f"{flag} {path} is a file; give a folder")
    _check_folder_writable(path, flag)


# ------------------------------------------------------------------------------------------ config -> flags

def flag_name(field: str) -> str:
    """``"batch_size"`` -> ``"--batch-size"``."""
    return "--" + field.replace("_", "-")


def field_docs(cls: type) -> dict[str, str]:
    """The help of each field of a dataclass: ``field(metadata={"help": ...})``, else the string literal under
    the field in the class body (base classes included; a subclass's wins)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass) or klass is object:
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError, SyntaxError):
            continue
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for a, b in zip(body, body[1:]):
            if (isinstance(a, ast.AnnAssign) and isinstance(a.target, ast.Name) and isinstance(b, ast.Expr)
                    and isinstance(b.value, ast.Constant) and isinstance(b.value.value, str)):
                docs[a.target.id] = " ".join(b.value.value.split())
    for f in dataclasses.fields(cls):
        if "help" in f.metadata:
            docs[f.name] = f.metadata["help"]
    return docs


def _default(f: dataclasses.Field) -> Any:
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return f.default


def _unwrap(kind: Any) -> tuple[Any, bool]:
    """``(inner type, optional)`` of ``X | None`` / ``Optional[X]``."""
    if typing.get_origin(kind) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(kind) if a is not type(None)]
        if len(args) == 1:
            return args[0], True
    return kind, False


def _sequence_item(kind: Any) -> Any | None:
    """The item type of ``list[X]`` / ``tuple[X, ...]``, else None."""
    origin = typing.get_origin(kind)
    if origin in (list, tuple, collections.abc.Sequence):
        args = [a for a in typing.get_args(kind) if a is not Ellipsis]
        return args[0] if args else str
    return None


def _show(value: Any) -> str:
    if isinstance(value, enum.Enum):
        return str(value.value)
    if isinstance(value, (list, tuple)):
        return " ".join(_show(v) for v in value) if value else "none"
    if value is None:
        return "none"
    return str(value)


def add_dataclass_args(parser: argparse.ArgumentParser | argparse._ArgumentGroup, cls: type, *,
                       only: Iterable[str] | None = None, exclude: Iterable[str] = (),
                       flags: Mapping[str, str] | None = None, help: Mapping[str, str] | None = None,
                       required: Iterable[str] = (), choices: Mapping[str, Sequence[Any]] | None = None,
                       metavars: Mapping[str, str] | None = None,
                       arg_types: Mapping[str, Callable[[str], Any]] | None = None) -> list[str]:
    """A flag per field of the dataclass ``cls`` (``only`` those, less ``exclude``); returns the field names.

    The flag is ``--field-name`` (or ``flags[name]``); its type comes from the annotation (``int``, ``float``,
    ``str``, ``Path``, an ``Enum`` (its values become the choices), ``list[X]`` / ``tuple[X, ...]`` (one or more
    values), ``X | None``; ``choices``, ``metavars`` and ``arg_types`` per field: ``arg_types[name]`` is the argparse
    ``type=`` of the value (of each item of a sequence), e.g. :func:`positive_int`, checked as the flag parses); a
    ``bool`` field that defaults to False is a switch that sets it, one that defaults to True a switch (named by
    ``flags``) that clears it. The help is
    ``help[name]``, else the field's docstring (:func:`field_docs`), followed by the dataclass default unless the
    text already speaks of the default. Every flag's parser default is ``argparse.SUPPRESS``: only given flags reach
    the namespace (:func:`dataclass_from_args`), so the dataclass holds the only copy of each default.
    """
    flags, help, choices, metavars = dict(flags or {}), dict(help or {}), dict(choices or {}), dict(metavars or {})
    arg_types = dict(arg_types or {})
    required = set(required)
    docs = field_docs(cls)
    hints = typing.get_type_hints(cls)
    wanted = None if only is None else list(only)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = [n for n in [*(wanted or []), *exclude, *flags, *help, *required, *choices, *metavars, *arg_types]
               if n not in fields]
    if unknown:
        raise TypeError(f"{cls.__name__} has no field(s) {', '.join(sorted(set(unknown)))}")
    names = [n for n in (wanted if wanted is not None else fields) if n not in set(exclude)]
    for name in names:
        f = fields[name]
        kind, _ = _unwrap(hints[name])
        default = _default(f)
        text = help.get(name, docs.get(name, ""))
        kwargs: dict[str, Any] = {"dest": name, "default": argparse.SUPPRESS}
        if kind is bool:
            kwargs["action"] = "store_false" if default is True else "store_true"
            if default is True and name not in flags:
                raise TypeError(f"{cls.__name__}.{name} defaults to True: name the switch that clears it in flags")
        else:
            item = _sequence_item(kind)
            base = item if item is not None else kind
            if item is not None:
                kwargs["nargs"] = "+"
            if isinstance(base, type) and issubclass(base, enum.Enum):
                kwargs["choices"] = [m.value for m in base]
                base = str
            kwargs["type"] = arg_types.get(name, base)
            if name in choices:
                kwargs["choices"] = list(choices[name])
            if name in metavars:
                kwargs["metavar"] = metavars[name]
            if name in required:
                kwargs["required"] = True
            elif not (default is None or "default" in text.lower()):
                text = f"{text} (default: {_show(default)})" if text else f"default: {_show(default)}"
        text = re.sub(r":\w+:`~?([^`]+)`", r"\1", text).replace("``", "")  # reST roles and literals, plain
        kwargs["help"] = text.replace("%", "%%")
        parser.add_argument(flags.get(name, flag_name(name)), **kwargs)
    return names


def given_fields(cls: type, args: argparse.Namespace) -> dict[str, Any]:
    """The fields of ``cls`` that ``args`` holds (the flags that were given), lists turned into tuples where the
    field is a tuple."""
    hints = typing.get_type_hints(cls)
    out = {}
    for f in dataclasses.fields(cls):
        if f.init and hasattr(args, f.name):
            value = getattr(args, f.name)
            kind, _ = _unwrap(hints[f.name])
            if isinstance(value, list) and typing.get_origin(kind) is tuple:
                value = tuple(value)
            out[f.name] = value
    return out


def dataclass_from_args(cls: type, args: argparse.Namespace, base: Any = None, **overrides: Any) -> Any:
    """``cls`` from the given flags (see :func:`add_dataclass_args`) over ``base`` (an instance; default: the
    dataclass defaults), then ``overrides``."""
    values = {**given_fields(cls, args), **overrides}
    if base is None:
        return cls(**values)
    return dataclasses.replace(base, **values)


# ------------------------------------------------------------------------------------------ config files

def _type_name(kind: Any) -> str:
    inner, optional = _unwrap(kind)
    item = _sequence_item(inner)
    if item is not None:
        name = f"a list of {_type_name(item)}"
    elif isinstance(inner, type) and issubclass(inner, enum.Enum):
        name = "one of " + ", ".join(repr(m.value) for m in inner)
    elif inner is Path:
        name = "a path (string)"
    elif isinstance(inner, type):
        name = {"int": "an integer", "float": "a number", "str": "a string", "bool": "true or false"}.get(
            inner.__name__, inner.__name__)
    else:
        name = str(inner)
    return f"{name} or null" if optional else name


def config_value(kind: Any, value: Any, key: str) -> Any:
    """``value`` read from a config file (JSON / TOML types) as a field annotated ``kind``: ``int`` (not a bool),
    ``float`` (an integer is widened), ``str``, ``bool``, ``Path``, an ``Enum`` (by value), ``list[X]`` /
    ``tuple[X, ...]`` (from a list), ``X | None``; any other annotation is taken as it is. CLIError naming ``key``
    and the expected type otherwise (never a silent conversion of, say, ``"5"`` to 5)."""
    inner, optional = _unwrap(kind)
    if value is None:
        if optional:
            return None
        raise CLIError(f"{key} is null; give {_type_name(kind)}")
    item = _sequence_item(inner)
    ok: bool
    if item is not None:
        if isinstance(value, list):
            items = [config_value(item, v, f"{key}[{i}]") for i, v in enumerate(value)]
            return tuple(items) if typing.get_origin(inner) is tuple else items
        ok = False
    elif inner is bool:
        ok = isinstance(value, bool)
    elif inner is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif inner is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        ok = False
    elif inner is str:
        ok = isinstance(value, str)
    elif inner is Path:
        if isinstance(value, str):
            return Path(value)
        ok = False
    elif isinstance(inner, type) and issubclass(inner, enum.Enum):
        members = {m.value: m for m in inner}
        if isinstance(value, str) and value in members:
            return members[value]
        ok = False
    else:
        ok = True
    if not ok:
        raise CLIError(f"{key} must be {_type_name(kind)}, got {json_dumps_short(value)}")
    return value


def json_dumps_short(value: Any) -> str:
    """``value`` as JSON, cut to 60 characters (for a message)."""
    import json

    text = json.dumps(value, default=str)
    return text if len(text) <= 60 else text[:57] + "..."


def config_fields(cls: type, data: Any, where: str, allowed: Iterable[str] | None = None,
                  why: Mapping[str, str] | None = None) -> dict[str, Any]:
    """The fields of the dataclass ``cls`` that the config section ``data`` (a mapping read from a file) gives,
    each checked and converted by :func:`config_value`. ``allowed``: the field names this section may set (default:
    every init field); a key outside them is refused by name, with ``why[key]`` when it is a field that does not
    apply here. ``where`` prefixes every key in a message (``"config c.json: build."``)."""
    if not isinstance(data, Mapping):
        raise CLIError(f"{where.rstrip('.')} must be an object (a table of keys), got {json_dumps_short(data)}")
    hints = typing.get_type_hints(cls)
    fields = [f.name for f in dataclasses.fields(cls) if f.init]
    names = fields if allowed is None else [n for n in fields if n in set(allowed)]
    why = dict(why or {})
    out = {}
    for key, value in data.items():
        if key not in names:
            if key in why:
                raise CLIError(f"{where}{key} {why[key]}; remove it")
            raise CLIError(f"{where}{key} is not a known key; the known keys here: {', '.join(names)}")
        out[key] = config_value(hints[key], value, f"{where}{key}")
    return out


def config_json(value: Any) -> Any:
    """A config value as JSON data: enums by value, tuples as lists, paths as strings, dataclasses as objects."""
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, (list, tuple)):
        return [config_json(v) for v in value]
    if isinstance(value, Mapping):
        return {str(k): config_json(v) for k, v in value.items()}
    if isinstance(value, Path):
        return str(value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: config_json(getattr(value, f.name)) for f in dataclasses.fields(value) if f.init}
    return value


def read_config_file(path: str | os.PathLike, flag: str = "--config") -> dict[str, Any]:
    """The object in the config file ``path``: JSON, or TOML when it ends in ``.toml`` (data, never code). A file
    that does not parse, or whose top level is not an object, is one CLIError naming the file and the place."""
    import json

    import tomllib

    path = Path(path)
    text = path.read_text(encoding="utf-8")  # a missing file: OSError, one line through cli_main
    try:
        data = tomllib.loads(text) if path.suffix == ".toml" else json.loads(text)
    except json.JSONDecodeError as exc:
        raise CLIError(f"{flag} {path} is not valid JSON ({exc.msg} at line {exc.lineno} column {exc.colno}); "
                       "a config is what --print-config writes") from None
    except tomllib.TOMLDecodeError as exc:
        raise CLIError(f"{flag} {path} is not valid TOML ({exc})") from None
    if not isinstance(data, dict):
        raise CLIError(f"{flag} {path}: the file must hold one object (keys and values), got {type(data).__name__}")
    return data


def flags_listing(flags: Mapping[str, Sequence[str]], width: int = 98) -> str:
    """The lines ``flags of each subcommand``: per subcommand (``flags``: name -> its flags, in order) its long flags,
    each whole (never split at a hyphen), wrapped at ``width``; so that one ``--help`` shows every flag there is."""
    lines = ["flags of each subcommand (SUB --help explains them):"]
    for name, names in flags.items():
        line = f"  {name}:"
        for flag in (f for f in names if f.startswith("--") and f != "--help"):
            if len(line) + len(flag) > width:
                lines.append(line)
                line = " " * (len(name) + 3)
            line += " " + flag
        lines.append(line)
    return "\n".join(lines)


def parser_flags(parser: argparse.ArgumentParser) -> list[str]:
    """Every option string of ``parser``, in the order they were added."""
    return [option for action in parser._actions for option in action.option_strings]


def add_config_args(parser: argparse.ArgumentParser, what: str = "the settings") -> None:
    """``--config FILE`` (:func:`read_config_file`) and ``--print-config``, for a command whose settings are one
    dataclass (:func:`dataclass_from_config`); flags given beside ``--config`` override its keys."""
    parser.add_argument("--config", type=Path, default=None, metavar="FILE",
                        help=f"read {what} from FILE (JSON, or TOML for .toml: what --print-config writes); flags "
                             "given beside it override its values")
    parser.add_argument("--print-config", action="store_true",
                        help=f"print {what} these flags describe as a --config file (JSON) and do nothing else")


def dataclass_from_config(cls: type, args: argparse.Namespace, required: Iterable[str] = ()) -> Any:
    """``cls`` from the keys of ``--config FILE`` (each checked by :func:`config_fields`), the given flags over them
    (:func:`given_fields`). ``required``: fields that a flag or a key must set (CLIError naming the flag)."""
    values: dict[str, Any] = {}
    if getattr(args, "config", None) is not None:
        values = config_fields(cls, read_config_file(args.config), f"config {args.config}: ")
    values.update(given_fields(cls, args))
    for name in required:
        if not values.get(name):
            raise CLIError(f"--{name.replace('_', '-')} is required (a flag, or the key {name!r} of --config)")
    return cls(**values)


def config_text(cfg: Any) -> str:
    """A dataclass config as the JSON that ``--config`` reads back (``--print-config``)."""
    import json

    return json.dumps(config_json(cfg), indent=2)


# ------------------------------------------------------------------------------------------ flag values

MAX_HORIZON = 1000
"""the largest ``--horizon`` (steps) a command accepts: 200 s at the default dt of 0.2 s, far beyond any table
(a build's levels, a rollout's ``[N, T + 1, d]`` states and a controller's plan all grow with it)"""
MAX_COUNT = 1_000_000
"""the largest count (samples, seeds, episodes, commands, repeats) one flag accepts; a larger one is a typo"""
MAX_WORK = 100_000
"""the most episodes (a product of counts: tasks x repeats x budgets x methods, ...) a run accepts without
``--no-limit`` (:func:`check_work`); a paper experiment or a BARN run is a few thousand"""

_DEVICE_TYPES = ("cpu", "cuda", "mps")


def device_arg(text: str) -> str:
    """argparse ``type=`` of ``--device``: a torch device this machine has (``cpu``, ``cuda``, ``cuda:N`` with N
    below ``torch.cuda.device_count()``, ``mps``); returns its canonical name (``str(torch.device(text))``)."""
    import torch  # here, not at the top: cli is imported by commands before they need torch

    try:
        device = torch.device(text)
    except (RuntimeError, ValueError, TypeError):
        raise argparse.ArgumentTypeError(f"{text!r} is not a torch device (cpu, cuda, cuda:N, mps)") from None
    if device.type not in _DEVICE_TYPES:
        raise argparse.ArgumentTypeError(f"{text!r}: only {', '.join(_DEVICE_TYPES)} devices are supported")
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise argparse.ArgumentTypeError(f"{text!r}: CUDA is not available on this machine (use cpu)")
        if device.index is not None and device.index >= count:
            raise argparse.ArgumentTypeError(f"{text!r}: this machine has {count} CUDA device(s), cuda:0 .. "
                                             f"cuda:{count - 1}")
    if device.type == "mps" and not torch.backends.mps.is_available():
        raise argparse.ArgumentTypeError(f"{text!r}: MPS is not available on this machine (use cpu)")
    return str(device)


def _bounds(low: float | None, high: float | None) -> str:
    if low is not None and high is not None:
        return f"in [{low}, {high}]"
    return f">= {low}" if low is not None else f"<= {high}"


def int_in(low: int | None = None, high: int | None = None, note: str = "") -> Callable[[str], int]:
    """argparse ``type=``: an integer in ``[low, high]`` (a side None: unbounded); ``note`` follows the range in
    the message (what the bound is for)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"invalid int value: {text!r}") from None
        if (low is not None and value < low) or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"must be an integer {_bounds(low, high)}{note}, got {value}")
        return value

    parse.__name__ = f"int {_bounds(low, high)}"  # argparse's fallback message names the type
    return parse


def float_in(low: float | None = None, high: float | None = None, *, open_low: bool = False,
             note: str = "") -> Callable[[str], float]:
    """argparse ``type=``: a finite number in ``[low, high]`` (``(low, high]`` with ``open_low``)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"invalid float value: {text!r}") from None
        too_low = low is not None and (value <= low if open_low else value < low)
        if not math.isfinite(value) or too_low or (high is not None and value > high):
            side = f"> {low}" if open_low and high is None else _bounds(low, high)
            raise argparse.ArgumentTypeError(f"must be a finite number {side}{note}, got {text}")
        return value

    parse.__name__ = "finite number"
    return parse


positive_int = int_in(1, MAX_COUNT)
"""argparse ``type=`` of a count: an integer in [1, :data:`MAX_COUNT`]"""
non_negative_int = int_in(0, MAX_COUNT)
"""argparse ``type=``: an integer in [0, :data:`MAX_COUNT`] (0 usually meaning "all" or "none")"""
threads_arg = int_in(0, 4096, note=" (0: torch's choice)")
"""argparse ``type=`` of ``--threads``: torch CPU threads, 0 for torch's choice"""
horizon_arg = int_in(1, MAX_HORIZON, note=" (precompute.cli.MAX_HORIZON)")
"""argparse ``type=`` of ``--horizon``: steps in [1, :data:`MAX_HORIZON`]"""
positive_float = float_in(0.0, open_low=True)
"""argparse ``type=``: a finite number > 0"""


def _option(parser: argparse.ArgumentParser, dest: str) -> str:
    for action in parser._actions:
        if action.dest == dest and action.option_strings:
            return action.option_strings[0]
    return flag_name(dest)


def refuse_flags(parser: argparse.ArgumentParser, args: argparse.Namespace, dests: Iterable[str], why: str) -> None:
    """The rule for modes: a flag that does not apply to the chosen mode is refused, never silently ignored.

    ``dests`` are the flags (argparse ``dest`` names) that ``why`` (e.g. ``"with --checkpoint (the checkpoint
    sets the sizes)"``) makes meaningless; the first one that was given -- present while its default is
    ``argparse.SUPPRESS``, else different from its parser default -- is one ``error:`` line and exit 2."""
    for dest in dests:
        if not hasattr(args, dest):
            continue
        value, default = getattr(args, dest), parser.get_default(dest)
        if default is argparse.SUPPRESS or value != default:
            parser.error(f"{_option(parser, dest)} does not apply {why}")


def add_no_limit_arg(parser: argparse.ArgumentParser) -> None:
    """The ``--no-limit`` switch that lifts :func:`check_work`'s :data:`MAX_WORK`."""
    parser.add_argument("--no-limit", action="store_true",
                        help=f"allow a run of more than {MAX_WORK:,} episodes (a product of counts)")


def check_work(counts: Mapping[str, int], what: str, no_limit: bool = False, limit: int = MAX_WORK) -> int:
    """The product of ``counts`` (``{"--tasks": 50, "budgets": 2, ...}``): ``what`` a run will do; CLIError when it
    exceeds ``limit`` unless ``no_limit`` (the ``--no-limit`` flag). Counts multiply: each may be fine alone."""
    total = math.prod(int(v) for v in counts.values())
    if total > limit and not no_limit:
        shown = " x ".join(f"{v:,} {k}" for k, v in counts.items())
        raise CLIError(f"{shown} = {total:,} {what}, more than {limit:,}: lower a count, or give --no-limit")
    return total
