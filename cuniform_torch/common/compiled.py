"""numba's disk cache for the compiled loops, where it can only help: :func:`njit` is ``numba.njit(cache=True)``
that falls back to compiling in memory, with one warning, when the cache cannot be used.

The loop modules (:mod:`cuniform_torch.tables.lookup_loops`, :mod:`cuniform_torch.sampling.frame_loops`,
:mod:`cuniform_torch.maps.rollout_loops`, :mod:`cuniform_torch.maps.sensing_loops`,
:mod:`cuniform_torch.envs.contains_loops`, :mod:`cuniform_torch.systems.dubins_loops`) are imported when a loop is first used; numba then loads each loop
from its cache (``__pycache__`` next to the module, else numba's cache folder in the user's home, or
``NUMBA_CACHE_DIR``) or compiles and saves it. Two things went wrong there with a raw traceback:

* **no cache folder is writable** (a read-only install run by a user whose home is not writable): numba refuses
  to make the function (``RuntimeError: cannot cache function ...: no locator available``). Here the loop is made
  without a disk cache instead (compiled in memory in every process).
* **the cache is damaged** (a truncated index ``*.nbi`` or data file ``*.nbc``): loading it raised
  ``UnpicklingError`` at the first call. Here the damaged loop's index and data files are removed when their folder
  is writable (one warning naming them), and the loop is compiled and saved afresh: the next run loads it from
  disk again. Where they cannot be removed (a read-only install), that cache is set aside for the process (not
  read, not written) and the loop is compiled in memory, in every run, with one warning saying what to do.

Each is one :class:`CompiledCacheWarning` (once per repaired loop, once per cache folder set aside, or once for the
missing folder) naming the files or folder. A data file that unpickles cleanly but holds another loop's code (two
``.nbc`` files swapped) is refused the same way when its function name or argument types differ from the loop's;
numba records no digest of a data file, so one with the same name and types but other code (edited by hand) is not
caught. Deleting the ``__pycache__`` folder named in a warning (or setting ``NUMBA_CACHE_DIR``) rebuilds the cache.
"""

from __future__ import annotations

import functools
import importlib
import os
import re
import threading
import warnings
from collections.abc import Callable
from typing import Any

__all__ = ["njit", "CompiledCacheWarning", "optional_loop"]


class CompiledCacheWarning(UserWarning):
    """numba's disk cache of a compiled loop could not be used: the loop is compiled in memory instead."""


_warned: set[str] = set()
_lock = threading.Lock()


def _warn_once(key: str, where: str, message: str) -> None:
    """One warning per ``key`` and process, attributed to the file ``where`` (line 0: the warning is one line)."""
    with _lock:
        if key in _warned:
            return
        _warned.add(key)
    warnings.warn_explicit(message, CompiledCacheWarning, where, 0, module=__name__)


def njit(**options: Any) -> Callable[[Callable[..., Any]], Any]:
    """``numba.njit(cache=True, **options)`` for a module-level function, guarded: without a writable cache folder
    the function is compiled in memory; a cache that fails to load or save is left alone for this process (see the
    module). Imports numba (call it from a loop module only)."""
    import numba

    def decorate(fn: Callable[..., Any]) -> Any:
        try:
            dispatcher = numba.njit(cache=True, **options)(fn)
        except (RuntimeError, OSError) as exc:  # no locator: no writable folder for the cache
            source = getattr(getattr(fn, "__code__", None), "co_filename", "?")
            _warn_once("no cache folder", source,
                       f"numba cannot cache the compiled loops of cuniform_torch ({exc}); compiling them in memory "
                       f"in this process (seconds). To cache them, make the folder of {source} or your home "
                       "writable, or set NUMBA_CACHE_DIR to a writable folder")
            return numba.njit(cache=False, **options)(fn)
        dispatcher._cache = _GuardedCache(dispatcher._cache, getattr(fn, "__qualname__", repr(fn)),
                                          getattr(fn, "__module__", None))
        return dispatcher

    return decorate


class _GuardedCache:
    """A numba ``FunctionCache`` whose load and save failures turn it off (for this process) with one warning: the
    dispatcher then compiles in memory, as it does on a cache miss. Everything else is the wrapped cache's."""

    def __init__(self, inner: Any, name: str, module: str | None = None):
        self._inner = inner
        self._name = name
        self._module = module

    def __getattr__(self, attr: str) -> Any:
        return getattr(self._inner, attr)

    def _index_path(self) -> str:
        cache_file = getattr(self._inner, "_cache_file", None)
        return str(getattr(cache_file, "_index_path", None) or getattr(self._inner, "cache_path", "?"))

    def _repair(self, exc: BaseException) -> bool:
        """Remove this loop's index and data files (``<base>.nbi``, ``<base>.<n>.nbc``) after a failed load, when
        their folder is writable, so that the compile which follows saves a fresh cache; True if removed (one
        warning naming them), False where they cannot be (the caller then sets the cache aside)."""
        cache_file = getattr(self._inner, "_cache_file", None)
        folder = getattr(cache_file, "_cache_path", None)
        index_name = getattr(cache_file, "_index_name", None)
        if not folder or not index_name or not index_name.endswith(".nbi") or not os.access(folder, os.W_OK | os.X_OK):
            return False
        base = index_name[: -len(".nbi")]
        ours = re.compile(rf"{re.escape(base)}(?:\.nbi|\.\d+\.nbc)")  # this loop's files, not its neighbours'
        removed = []
        try:
            for entry in os.scandir(folder):
                if ours.fullmatch(entry.name):
                    try:
                        os.unlink(entry.path)
                    except FileNotFoundError:  # another process repairing it at the same time
                        continue
                    removed.append(entry.name)
        except OSError:
            return False
        _warn_once(f"repaired {folder}/{base}", self._index_path(),
                   f"numba's cache of the compiled loop {self._module}.{self._name} in {folder} could not be read "
                   f"({type(exc).__name__}: {exc}); removed its damaged files ({', '.join(sorted(removed)) or 'none left'}) "
                   "and compiling it again, saved there for the next run")
        return True

    def _give_up(self, doing: str, exc: BaseException) -> None:
        self._inner.disable()
        path = self._index_path()
        folder = str(getattr(self._inner, "cache_path", None) or os.path.dirname(path))
        _warn_once(folder, path,
                   f"numba's cache of the compiled loops in {folder} could not be {doing} (first {path}: "
                   f"{type(exc).__name__}: {exc}); compiling what it cannot read in memory in this process. Delete that folder to "
                   "rebuild the cache, or set NUMBA_CACHE_DIR to another folder")

    def load_overload(self, sig: Any, target_context: Any) -> Any:
        try:
            cres = self._inner.load_overload(sig, target_context)
            if cres is not None:
                self._check_loaded(cres, sig)
            return cres
        except Exception as exc:  # a damaged index or data file: unpickling, rebuilding, reading, another loop's
            if not self._repair(exc):
                self._give_up("read", exc)
            return None  # a cache miss: the dispatcher compiles (and, once repaired, saves afresh)

    def _check_loaded(self, cres: Any, sig: Any) -> None:
        """ValueError unless the loaded code is this function's, for ``sig`` (a data file of another loop, put in
        this one's place, would be called with the wrong arguments)."""
        from numba.core import sigutils

        args, _ = sigutils.normalize_signature(sig)
        fndesc = getattr(cres, "fndesc", None)
        qualname = getattr(fndesc, "qualname", None)
        module = getattr(fndesc, "modname", self._module)
        loaded = tuple(getattr(getattr(cres, "signature", None), "args", ()))
        if qualname != self._name or module != self._module or loaded != tuple(args):
            raise ValueError(f"a data file holds the code of {module}.{qualname} for {len(loaded)} argument(s), "
                             f"not of {self._module}.{self._name} for these {len(args)}")

    def save_overload(self, sig: Any, data: Any) -> None:
        try:
            self._inner.save_overload(sig, data)
        except Exception as exc:  # an unwritable or full folder, a damaged index that the save reads first
            self._give_up("written", exc)


@functools.cache
def optional_loop(module: str, name: str) -> Callable[..., Any] | None:
    """The compiled loop ``name`` of ``module`` (imported once, on first use), or None when numba is missing or
    broken against this numpy: the caller then takes its torch path."""
    try:
        return getattr(importlib.import_module(module), name)
    except Exception:  # numba missing or broken: any import error means no compiled loop
        return None
