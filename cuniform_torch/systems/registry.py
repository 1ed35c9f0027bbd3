"""The registry of systems by name, factories by ``"module:qualname"`` path, and the system JSON of files.

Trust: reading a table or checkpoint never imports or calls anything its JSON names. :func:`system_from_json`
rebuilds a system from the registry, or from a ``trust_factory`` that the caller names (the file's ``factory``
string is only compared with it). What the *caller* types (``--system module:factory``, ``--system-module``)
is imported: :func:`resolve_system`, :func:`import_system_modules`.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import json
import math
from collections.abc import Callable
from typing import Any

from cuniform_torch.common.checks import positive_int
from cuniform_torch.systems import classic, models, single_track
from cuniform_torch.systems.classic import DoubleIntegrator, MountainCar
from cuniform_torch.systems.models import Dubins, RandomWalk1D
from cuniform_torch.systems.protocol import MAX_HORIZON, System, check_system
from cuniform_torch.systems.single_track import KinematicSingleTrack, KinematicSingleTrackSpeed

__all__ = ["UnknownSystemError", "register_system", "make_system", "known_systems", "is_builtin", "resolve_system",
           "import_system_modules", "factory_path", "load_factory", "system_to_json", "system_from_json"]


class UnknownSystemError(ValueError):
    """A system name that is not registered (a file's system is rebuilt only from the registry or a trusted factory)."""


_REGISTRY: dict[str, Callable[..., System]] = {}
_BUILTIN_MODULES = frozenset({models.__name__, single_track.__name__, classic.__name__})
"""the modules of the built-in systems: a system from elsewhere is a user system (its JSON names its factory)"""


def register_system(name: str, factory: Callable[..., System], *, overwrite: bool = False) -> None:
    """Register ``factory(**params) -> System`` under ``name`` (for ``--system NAME`` and table files).

    ``factory`` is usually the system's class (a dataclass: its fields become the build's flags) or a function
    with keyword arguments. Define it at the top level of an importable module, so tables can name it
    (``"module:qualname"``) and be read in a fresh process. Registering another factory under a taken name is
    an error unless ``overwrite=True``, or unless it comes from the same definition (same module and qualified
    name: a re-run script or notebook cell, a reloaded module), which replaces the old one.
    """
    if not name or not isinstance(name, str):
        raise ValueError(f"a system name must be a non-empty string, got {name!r}")
    if ":" in name:
        raise ValueError(f"a system name must not contain ':' (that marks a module:factory path), got {name!r}")
    if not callable(factory):
        raise ValueError(f"the factory of system {name!r} must be callable, got {type(factory).__name__}")
    old = _REGISTRY.get(name)
    if old is not None and not overwrite and old is not factory and not _same_definition(old, factory):
        raise ValueError(f"a system named {name!r} is already registered; pass overwrite=True to replace it")
    _REGISTRY[name] = factory


def _same_definition(a: Any, b: Any) -> bool:
    """Two objects from the same definition (a re-run notebook cell or script, a reloaded module)."""
    path = _definition_path(a)
    return path is not None and path == _definition_path(b)


def is_builtin(factory: Any) -> bool:
    """Whether ``factory`` is one of the library's own systems (their JSON names no factory)."""
    return getattr(factory, "__module__", None) in _BUILTIN_MODULES


def known_systems() -> list[str]:
    """Names of the registered systems, sorted."""
    return sorted(_REGISTRY)


def make_system(name: str, **params: Any) -> System:
    """Build a registered system by name and check it (:func:`check_system`); unknown names and parameters
    are clear errors."""
    if not isinstance(name, str) or name not in _REGISTRY:
        raise UnknownSystemError(f"unknown system {name!r}; known systems: {', '.join(known_systems())}")
    return _build(name, _REGISTRY[name], params)


def _check_params(name: str, factory: Callable[..., Any], params: dict[str, Any]) -> None:
    """Refuse ``params`` that ``factory`` does not take, before it is called (ValueError naming them)."""
    if dataclasses.is_dataclass(factory):
        valid = {f.name for f in dataclasses.fields(factory) if f.init}
        unknown = sorted(set(params) - valid)
        if unknown:
            raise ValueError(
                f"system {name!r} has no parameter(s) {', '.join(unknown)}; its parameters: {', '.join(sorted(valid))}"
            )
    try:
        signature = inspect.signature(factory)
    except (TypeError, ValueError):  # a builtin without a signature: nothing to bind against
        raise ValueError(f"system {name!r}: its factory {factory!r} has no inspectable signature") from None
    try:
        signature.bind(**params)
    except TypeError as exc:
        raise ValueError(f"system {name!r}: its factory does not accept {sorted(params)} ({exc})") from None


def _build(name: str, factory: Callable[..., Any], params: dict[str, Any]) -> System:
    """``factory(**params)`` once the parameters bind, checked to be a valid System named ``name``."""
    _check_params(name, factory, params)
    try:
        system = factory(**params)
    except TypeError as exc:  # a function factory that rejects a value's type
        raise ValueError(f"system {name!r}: its factory does not accept {sorted(params)} ({exc})") from None
    check_system(system)
    if system.name != name:
        raise ValueError(f"the factory registered as {name!r} built a system named {system.name!r}; "
                         "register it under the system's own name")
    return system


# ---------------------------------------------------------------------------- factories by module path

def factory_path(factory: Any) -> str | None:
    """``"module:qualname"`` of a factory that a fresh process can import, else None (``__main__``, a lambda,
    a class defined inside a function, ...)."""
    module = getattr(factory, "__module__", None)
    qualname = getattr(factory, "__qualname__", None)
    if not module or not qualname or module in ("__main__", "builtins") or "<" in qualname:
        return None
    path = f"{module}:{qualname}"
    try:
        resolved = load_factory(path)
    except ValueError:
        return None
    return path if resolved is factory else None


def load_factory(path: str) -> Callable[..., System]:
    """Import ``"package.module:Name"`` (``Name`` may be dotted) and return the callable it names."""
    if not isinstance(path, str) or path.count(":") != 1:
        raise ValueError(f"a factory path must look like 'package.module:Name', got {path!r}")
    module_name, qualname = path.split(":")
    if not module_name or not qualname:
        raise ValueError(f"a factory path must look like 'package.module:Name', got {path!r}")
    try:
        obj: Any = importlib.import_module(module_name)
    except ImportError as exc:
        raise ValueError(f"cannot import module {module_name!r} of factory {path!r} ({type(exc).__name__}: {exc})") from None
    for part in qualname.split("."):
        if not hasattr(obj, part):
            raise ValueError(f"module {module_name!r} has no {qualname!r} (factory {path!r})")
        obj = getattr(obj, part)
    if not callable(obj):
        raise ValueError(f"factory {path!r} is not callable ({type(obj).__name__})")
    return obj


def import_system_modules(modules: list[str] | tuple[str, ...]) -> None:
    """Import each user module that registers systems (``--system-module``): the caller typed these names, so
    importing them is the caller's decision, never a file's. ValueError naming the module that fails."""
    for module in modules:
        if not isinstance(module, str) or not module or ":" in module:
            raise ValueError(f"--system-module {module!r}: give a module name such as my_robots")
        try:
            importlib.import_module(module)
        except ImportError as exc:
            raise ValueError(f"--system-module {module}: cannot import it ({type(exc).__name__}: {exc})") from None


def resolve_system(spec: str) -> str:
    """The registry name of ``spec``: a registered name, or ``"module:factory"`` that the caller typed (imported,
    built with its defaults and checked, then registered under the built system's name). Returns the name."""
    if not isinstance(spec, str) or not spec:
        raise UnknownSystemError(f"a system must be a name or 'module:factory', got {spec!r}")
    if ":" not in spec:
        if spec not in _REGISTRY:
            raise UnknownSystemError(f"unknown system {spec!r}; known systems: {', '.join(known_systems())} "
                                     "(a user system: --system-module MODULE, or --system module:factory)")
        return spec
    factory = load_factory(spec)
    name = _trusted_name(spec, factory)
    if _REGISTRY.get(name) is not factory:
        register_system(name, factory)
    return name


def _trusted_name(spec: str, factory: Callable[..., Any]) -> str:
    """The name of the system ``factory`` builds with its defaults; ValueError if it builds no valid System."""
    _check_params(spec, factory, {})
    try:
        system = factory()
    except Exception as exc:  # the caller named this factory; whatever it raises is theirs to see, in one line
        raise ValueError(f"factory {spec!r} did not build a system with its defaults ({type(exc).__name__}: {exc})") from None
    name = getattr(system, "name", None)
    if not isinstance(name, str):
        raise ValueError(f"factory {spec!r} built a {type(system).__name__}, not a System (it has no name; "
                         "see cuniform_torch.systems.System)")
    check_system(system)
    return name


# ------------------------------------------------------------------------------------------- system JSON

def system_to_json(system: System, horizon: int) -> str:
    """The table's system JSON: ``{"name", "params", "dt", "horizon"}``, plus ``"factory"``
    (``"module:qualname"``) for a system defined outside this module whose factory a fresh process can import
    (keys sorted, deterministic)."""
    spec: dict[str, Any] = {"name": system.name, "params": system.params(), "dt": float(system.dt),
                            "horizon": int(horizon)}
    factory = _REGISTRY.get(system.name, type(system))
    if not is_builtin(factory):
        path = factory_path(factory)
        if path is not None:
            spec["factory"] = path
    return json.dumps(spec, sort_keys=True)


_MAX_SYSTEM_JSON = 1 << 20  # characters; a system JSON is a few hundred


def system_from_json(text: str, *, trust_factory: str | Callable[..., Any] | None = None) -> tuple[System, int]:
    """Rebuild ``(system, horizon)`` from a table's or checkpoint's system JSON.

    Nothing the JSON names is imported or called: the system comes from the registry, or from ``trust_factory``
    (a ``"module:factory"`` path or the factory itself) that the caller names. The JSON's ``factory`` string is
    only compared: with the trusted path, or (without one) with the registered factory's ``"module:qualname"``;
    a built-in system's JSON names none. Its ``dt`` (redundant with ``params``), if present, must be the rebuilt
    system's. A trusted factory is registered under the system's name once it has built a valid
    system from the JSON's parameters. :class:`UnknownSystemError` says what to pass when the name is unknown.
    """
    if not isinstance(text, str) or len(text) > _MAX_SYSTEM_JSON:
        raise ValueError(f"system JSON must be a string of at most {_MAX_SYSTEM_JSON} characters")
    try:
        spec = json.loads(text)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise ValueError(f"system JSON does not parse: {exc}") from None
    if not isinstance(spec, dict) or not {"name", "params", "horizon"} <= set(spec):
        raise ValueError(f"system JSON must be an object with name, params and horizon; got {text[:200]!r}")
    name, params, horizon = spec["name"], spec["params"], spec["horizon"]
    if not isinstance(name, str) or not name or ":" in name:
        raise ValueError(f"system JSON: name must be a system name (a non-empty string without ':'), got {name!r}")
    if not isinstance(params, dict):
        raise ValueError(f"system JSON: params must be an object of constructor arguments, got {params!r}")
    positive_int("system JSON", "horizon", horizon, at_most=MAX_HORIZON)
    named = spec.get("factory")
    if named is not None and not isinstance(named, str):
        raise ValueError(f"system JSON: factory must be a 'module:factory' string, got {named!r}")
    dt = spec.get("dt")
    if dt is not None and not (isinstance(dt, (int, float)) and not isinstance(dt, bool) and math.isfinite(dt)):
        raise ValueError(f"system JSON: dt must be a finite number (s), got {dt!r}")
    if trust_factory is None:
        if name not in _REGISTRY:
            raise UnknownSystemError(_unknown_message(name, named))
        registered = _REGISTRY[name]
        if named is not None:  # never imported; but a file may only name the factory that rebuilds it
            own = None if is_builtin(registered) else _definition_path(registered)
            if named != own:
                what = "a built-in system (its JSON names no factory)" if own is None else f"registered from {own!r}"
                raise ValueError(f"system JSON: names factory {named!r}, but {name!r} is {what}; a file names "
                                 "only the factory that rebuilds it")
        return _checked_dt(make_system(name, **params), dt), horizon
    factory = load_factory(trust_factory) if isinstance(trust_factory, str) else trust_factory
    if not callable(factory):
        raise ValueError(f"trust_factory must be a 'module:factory' path or a callable, got {trust_factory!r}")
    trusted = trust_factory if isinstance(trust_factory, str) else _definition_path(factory)
    if named is not None and trusted is not None and named != trusted:
        raise UnknownSystemError(f"system {name!r}: the file names factory {named!r}, not the trusted {trusted!r}")
    prior = _REGISTRY.get(name)
    if prior is not None and prior is not factory and not _same_definition(prior, factory):
        raise ValueError(f"system {name!r} is registered with another factory than the trusted {trusted or factory!r}")
    system = _checked_dt(_build(name, factory, params), dt)
    if prior is None:
        register_system(name, factory)
    return system, horizon


def _checked_dt(system: System, dt: float | None) -> System:
    """``system`` if the JSON's ``dt`` (redundant with its params) is absent or the rebuilt system's own."""
    if dt is not None and float(dt) != float(system.dt):
        raise ValueError(f"system JSON dt does not match its params: {dt!r}, but the rebuilt {system.name!r} has "
                         f"dt {float(system.dt)!r}")
    return system


def _definition_path(factory: Any) -> str | None:
    """``"module:qualname"`` of where ``factory`` was defined (importable or not), else None."""
    module, qualname = getattr(factory, "__module__", None), getattr(factory, "__qualname__", None)
    return f"{module}:{qualname}" if module and qualname else None


def _unknown_message(name: str, named: str | None) -> str:
    module = named.split(":")[0] if named else "MODULE"
    where = f"; the file names factory {named!r}" if named else ""
    return (f"unknown system {name!r} (known: {', '.join(known_systems())}){where}. Reading a file never imports "
            f"code it names: register the system first (import the module that calls register_system({name!r}, "
            f"factory)), pass trust_factory={named or 'module:factory'!r}, or on the command line "
            f"--system-module {module}")


for _builtin in (RandomWalk1D, Dubins, KinematicSingleTrack, KinematicSingleTrackSpeed, DoubleIntegrator, MountainCar):
    register_system(_builtin.name, _builtin)
