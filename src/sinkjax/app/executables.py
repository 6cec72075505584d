"""The soft method's traced and lowered functions kept on disk: a new process skips tracing.

JAX's persistent compilation cache (:mod:`sinkjax.app.compile_cache`) skips the backend compile,
but a new process still traces and lowers the whole method to find its cache entry: seconds per
image size, paid again by every run and every worker. Here the method exported with
``jax.export`` (a StableHLO module) is written once per function and argument shapes, and a
later process loads it and goes straight to the (cached) compile. (Serialising the CPU
executable itself, ``jax.experimental.serialize_executable``, crashed on loading with this
jaxlib; ``Exported.serialize`` needs the optional ``flatbuffers``: the Exported is pickled.)

A file is named by a hash of everything that could make it wrong for this process: the jax,
jaxlib and equinox versions, sinkjax's version and the hash of its source files, the backend and
its devices, the function, and the arguments' pytree structure, shapes and dtypes. The file
carries a checksum of its contents; a file that is missing, corrupt, truncated or unreadable is
compiled afresh (with a log line) and rewritten, so a bad cache can cost time but never change a
number or fail a run.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import io
import logging
import os
import pickle
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..xla import jit

log = logging.getLogger("sinkjax")

# The first line of every file; a new layout gets a new number (old files are then ignored).
MAGIC = b"sinkjax-executable 1\n"
# Reported as part of the run's compile time (sinkjax.app.compile_cache.CompileClock).
LOAD_EVENT = "/sinkjax/exported_load_duration"


@functools.cache
def code_hash() -> str:
    """sha256 of sinkjax's Python sources (names and contents): any edit is a new cache key."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


@functools.cache
def _environment() -> str:
    import equinox
    import jax
    import jaxlib

    from .. import __version__

    device = jax.devices()[0]
    return repr(
        (
            jax.__version__,
            jaxlib.__version__,
            equinox.__version__,
            __version__,
            code_hash(),
            device.platform,
            device.client.platform_version,
            device.device_kind,
            jax.device_count(),
        )
    )


def cache_key(name: str, args: tuple[Any, ...]) -> str:
    """The file name (hex) for function ``name`` called on arguments shaped like ``args``."""
    import jax

    leaves, tree = jax.tree_util.tree_flatten(args)
    shapes = [(tuple(x.shape), str(x.dtype), bool(getattr(x, "weak_type", False))) for x in leaves]
    text = repr((_environment(), name, str(tree), shapes, jax.config.read("jax_enable_x64")))
    return hashlib.sha256(text.encode()).hexdigest()


def _missing_sentinel() -> Any:
    # Equinox marks absent module fields in a pytree's auxiliary data with a singleton that
    # plain pickling would copy; the copy breaks unflattening, so it travels by reference.
    try:
        from equinox._module._flatten import MISSING
    except ImportError:
        return None
    return MISSING


class _Pickler(pickle.Pickler):
    def persistent_id(self, obj: Any) -> str | None:
        return "eqx-missing" if obj is _missing_sentinel() and obj is not None else None


class _Unpickler(pickle.Unpickler):
    def persistent_load(self, pid: Any) -> Any:
        if pid == "eqx-missing" and _missing_sentinel() is not None:
            return _missing_sentinel()
        raise pickle.UnpicklingError(f"unknown reference {pid!r}")


class ExecutableCache:
    """A :data:`sinkjax.soft.batch.CompiledProvider`: each measuring function exported
    (``jax.export``: traced and lowered) once per argument shapes and kept in ``directory``
    (created when first written); a later process loads it instead of tracing the method.

    Loaded or fresh, the function runs as ``jax.jit(exported.call)``: one code path, so a run
    with a cache file gives the numbers of a run without one. The compile of that call is then
    a hit in JAX's persistent cache."""

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)
        self._ready: dict[str, Callable[..., Any]] = {}

    def __call__(self, name: str, fn: Any, args: tuple[Any, ...]) -> Callable[..., Any]:
        key = cache_key(name, args)
        ready = self._ready.get(key)
        if ready is None:
            exported = self._load(key, args)
            if exported is None:
                exported = self._export(key, fn, args)
            ready = self._ready[key] = jit(exported.call)
        return ready

    def path(self, key: str) -> Path:
        return self.directory / f"{key}.bin"

    def _load(self, key: str, args: tuple[Any, ...]) -> Any:
        import jax

        path = self.path(key)
        if not path.exists():
            return None
        start = time.time()
        try:
            data = path.read_bytes()
            head, _, body = data[len(MAGIC) :].partition(b"\n")
            if not data.startswith(MAGIC) or head.decode() != hashlib.sha256(body).hexdigest():
                raise ValueError("bad header or checksum")
            stored_key, exported = _Unpickler(io.BytesIO(body)).load()
            avals = tuple(jax.typeof(x) for x in jax.tree_util.tree_leaves(args))
            if (
                stored_key != key
                or exported.in_tree != jax.tree_util.tree_structure((args, {}))
                or tuple(exported.in_avals) != avals
            ):
                raise ValueError("written for other arguments")
        except Exception as e:  # any failure: export afresh instead
            log.info("exported function %s unusable (%s): tracing it again", path, e)
            return None
        jax.monitoring.record_event_time_span(LOAD_EVENT, start, time.time())
        return exported

    def _export(self, key: str, fn: Any, args: tuple[Any, ...]) -> Any:
        import jax

        exported = jax.export.export(fn)(*args)
        try:
            buffer = io.BytesIO()
            # The VJP hook is a closure (not picklable); the command line never differentiates.
            _Pickler(buffer).dump((key, dataclasses.replace(exported, _get_vjp=None)))
            body = buffer.getvalue()
            self.directory.mkdir(parents=True, exist_ok=True)
            # Written under a temporary name and renamed: a reader (another worker) never sees
            # half a file.
            fd, tmp = tempfile.mkstemp(dir=self.directory, suffix=".tmp")
            try:
                with os.fdopen(fd, "wb") as f:
                    f.write(MAGIC + hashlib.sha256(body).hexdigest().encode() + b"\n" + body)
                os.replace(tmp, self.path(key))
            finally:
                Path(tmp).unlink(missing_ok=True)
        except Exception as e:  # the run goes on with the exported function
            log.info("exported function not written to %s (%s)", self.directory, e)
        return exported
