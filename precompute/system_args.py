"""The system flags of ``python -m precompute.build`` (and the commands that reuse them): user system modules
and ``module:factory`` specs, ``--param KEY=VALUE`` items, and building the named system with one clear error."""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from typing import Any

from cuniform_torch.systems import _REGISTRY, check_system, is_builtin, load_factory, make_system, resolve_system
from precompute.cli import CLIError, import_system_modules, out_of_memory_message

__all__ = ["load_user_systems", "make_cli_system", "parse_params", "register_factory"]


def load_user_systems(argv: Sequence[str] | None) -> None:
    """Import every ``--system-module`` and resolve a ``--system module:factory`` (registering it), before the
    flags are parsed. ValueError when a module or factory cannot be loaded."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--system", default="dubins")
    pre.add_argument("--system-module", action="append", default=[])
    known, _ = pre.parse_known_args(argv)
    import_system_modules(known.system_module)
    if ":" in known.system:
        register_factory(known.system)


def register_factory(spec: str) -> None:
    """``resolve_system`` of a ``--system module:factory`` the user typed, after checking that the factory builds
    a System: what goes wrong (a missing module, ``os:getpid``, a factory that raises) is a CLIError."""
    try:
        factory = load_factory(spec)
    except ValueError as exc:
        raise CLIError(f"--system {spec}: {exc}") from None
    if not isinstance(getattr(factory, "name", None), str):  # resolve_system calls it to learn the name
        try:
            built = factory()
        except Exception as exc:  # the user's callable: any failure is theirs to see, in one line
            raise CLIError(f"--system {spec}: calling it with no arguments failed ({type(exc).__name__}: {exc}); "
                           "give a factory of a System (see cuniform_torch.systems.System)") from None
        try:
            check_system(built)
        except Exception as exc:
            raise CLIError(f"--system {spec} is not a System factory: it built {type(built).__name__} ({exc})") from None
    resolve_system(spec)


def make_cli_system(spec: str, name: str, params: dict[str, Any]):
    """``make_system``, with an allocation failure (``--param num_actions=10**12``) or a user system's own exception
    as a CLIError naming the system and its parameters."""
    try:
        return make_system(name, **params)
    except ValueError:
        raise
    except Exception as exc:
        given = ", ".join(f"{k}={v!r}" for k, v in params.items())
        oom = out_of_memory_message(exc)
        if oom is not None:
            raise CLIError(f"--system {name}" + (f" ({given})" if given else "") + f": {oom}; make num_actions "
                           "(--param num_actions=N) or the grid smaller") from None
        if not is_builtin(_REGISTRY[name]):
            raise CLIError(f"--system {spec}: building or checking it failed ({type(exc).__name__}: {exc})") from None
        raise  # a built-in system that fails is a bug


def parse_params(items: list[str]) -> dict[str, Any]:
    """``--param KEY=VALUE`` items -> ``{key: value}`` (JSON values; anything else a plain string)."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--param needs KEY=VALUE, got {item!r}")
        if key.replace("-", "_") in out:
            raise ValueError(f"--param {key} given twice; give each parameter once")
        try:
            out[key.replace("-", "_")] = json.loads(value)
        except json.JSONDecodeError:
            out[key.replace("-", "_")] = value  # a plain string
    return out
