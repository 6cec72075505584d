"""The soft method's compiled functions kept on disk: a new process neither traces nor lowers it.

JAX's persistent compilation cache (:mod:`sinkjax.app.compile_cache`) skips the backend compile,
but a new process still traces and lowers the whole method to find its cache entry: seconds per
image size, paid by every run and worker. Here each measuring function is kept per argument
shapes, exported with ``jax.export`` (a StableHLO module: its output shapes, and the call that
runs under tracing; pickled, as ``Exported.serialize`` needs the optional ``flatbuffers``) and
as the compiled executable (``jax.experimental.serialize_executable``). A later process loads
both, skipping tracing, lowering and the cache-key hash (about 0.1 s a function, all of it
holding Python's lock while the other half loads). A deserialised executable needs the CPU's
LAPACK kernels registered, which lowering does as a side effect;
:func:`sinkjax.app.early.backend_ready` lowers a trivial exported call once per process for
that (without it the first call crashed). The command line starts loading the executables while
sinkjax is still being imported (:mod:`sinkjax.app.early`); an export or compile that is needed
is announced to :func:`sinkjax.app.compile_cache.compile_notices` (a run's progress bar).

An export's file is named by a hash of everything that could make it wrong for this process:
the jax, jaxlib and equinox versions, sinkjax's version and the hash of its source files, the
backend and its devices, the function, and the arguments' pytree structure, shapes and dtypes.
A compiled file is named by what it compiles from (:func:`module_key`: the exported module
without its source locations, its pytrees, jax, jaxlib, the devices and the compile options),
so an edit of sinkjax that leaves the computation as it was finds it again. A file that is
missing, corrupt (each carries a checksum), truncated or unreadable is made afresh (with a log
line): a bad cache can cost time but never change a number or fail a run. Only an executable
compiled afresh is kept (:func:`_compile_fresh`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import io
import logging
import os
import pickle
import re
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from ..xla import jit
from . import early
from .compile_cache import LOAD_EVENT, compiling

log = logging.getLogger("sinkjax")

# The first line of every file; a new layout gets a new number (old files are then ignored).
MAGIC = b"sinkjax-executable 2\n"
# Layout 2: the key and the executable, then its pytrees, as two pickles (the first alone is read
# while sinkjax is still being imported: sinkjax.app.early). Layout 1 (one pickle) is converted.
COMPILED_MAGIC = b"sinkjax-compiled 2\n"
_COMPILED_MAGIC_1 = b"sinkjax-compiled 1\n"


@functools.cache
def code_hash() -> str:
    """sha256 of sinkjax's Python sources (names and contents): any edit is a new cache key."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


@functools.cache
def _environment(with_code: bool = True) -> str:
    # with_code=False: what the compile depends on besides the module (a compiled file's key).
    import equinox
    import jax
    import jaxlib

    from .. import __version__
    from ..xla import compiler_options

    device = jax.devices()[0]
    common = (
        jax.__version__,
        jaxlib.__version__,
        device.platform,
        device.client.platform_version,
        device.device_kind,
        jax.device_count(),
    )
    if with_code:
        return repr((*common, equinox.__version__, __version__, code_hash()))
    return repr((*common, sorted(compiler_options().items()), os.environ.get("XLA_FLAGS", "")))


def cache_key(name: str, args: tuple[Any, ...]) -> str:
    """The file name (hex) for function ``name`` called on arguments shaped like ``args``."""
    import jax

    leaves, tree = jax.tree_util.tree_flatten(args)
    shapes = [(tuple(x.shape), str(x.dtype), bool(getattr(x, "weak_type", False))) for x in leaves]
    text = repr((_environment(), name, str(tree), shapes, jax.config.read("jax_enable_x64")))
    return hashlib.sha256(text.encode()).hexdigest()


# MLIR location attributes: loc("name"), loc(#loc12), loc("f.py":3:4 to :9), loc(callsite(...)).
_LOCATION = re.compile(r"\s*\bloc\((?:[^()]|\((?:[^()]|\([^()]*\))*\))*\)")


def module_key(exported: Any) -> str:
    """A hash of what ``exported`` compiles to: its module without source locations (which
    name sinkjax's files and lines), its pytrees and this machine's compile settings. An edit
    of sinkjax that leaves the computation as it was keeps the key (and the compiled file)."""
    text = "\n".join(
        line for line in exported.mlir_module().splitlines() if not line.startswith("#loc")
    )
    parts = (
        _environment(with_code=False),
        _LOCATION.sub("", text),
        str(exported.in_tree),
        str(exported.out_tree),
    )
    return hashlib.sha256(repr(parts).encode()).hexdigest()


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


# An executable JAX loaded from its persistent cache does not serialise whole (with this jaxlib it
# lost kernels: "Function ... not found" at its first call), so only a fresh compile is kept. JAX
# records USE_EVENT when a compile asks its persistent cache, then HIT_EVENT if the cache had it
# (FRESH_EVENT: a miss it writes, which a compile under its time threshold never is). A compile
# that JAX answers from memory records neither, and is not taken for fresh either.
USE_EVENT = "/jax/compilation_cache/compile_requests_use_cache"
HIT_EVENT = "/jax/compilation_cache/cache_hits"
FRESH_EVENT = "/jax/compilation_cache/cache_misses"
_EVENTS = (USE_EVENT, HIT_EVENT, FRESH_EVENT)
_fresh = threading.local()  # per thread: how often each of _EVENTS was recorded


def _count_fresh(event: str, **kwargs: object) -> None:
    if event in _EVENTS:
        counts = _fresh.__dict__
        counts[event] = counts.get(event, 0) + 1


@functools.cache
def _listen_for_fresh() -> None:
    import jax

    jax.monitoring.register_event_listener(_count_fresh)


def _compile_fresh(jitted: Any, args: tuple[Any, ...]) -> tuple[Any, bool]:
    """``jitted`` compiled for ``args``, and whether this thread compiled it afresh (rather than
    loading it from JAX's persistent cache, or from its memory)."""
    _listen_for_fresh()
    lowered = jitted.lower(*args)
    before = dict(_fresh.__dict__)  # counted over this module's compile alone
    compiled = lowered.compile()
    seen = {e: _fresh.__dict__.get(e, 0) - before.get(e, 0) for e in _EVENTS}
    fresh = seen[FRESH_EVENT] > 0 or (seen[USE_EVENT] > 0 and seen[HIT_EVENT] == 0)
    return compiled, fresh


def _has_tracer(args: tuple[Any, ...]) -> bool:
    import jax

    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(args))


def frame_size(args: tuple[Any, ...]) -> tuple[int, int] | None:
    """The frames' (width, height) where the first argument is a frame (the hint, the notice)."""
    shape: tuple[int, ...] = tuple(getattr(args[0], "shape", ())) if args else ()
    return (int(shape[1]), int(shape[0])) if len(shape) == 3 and shape[2] == 3 else None


class Loaded:
    """One measuring function for one argument shape: the compiled executable, loaded from
    disk or compiled (and then written) at the first call or :meth:`load`, whichever comes
    first (thread-safe: a load started ahead on another thread is waited for, not repeated).
    Under tracing (``jax.eval_shape``, an enclosing ``jit``) it is the exported call."""

    def __init__(self, cache: ExecutableCache, key: str, exported: Any, args: tuple[Any, ...]):
        # key: the compiled file's (module_key), shared by every export that compiles alike.
        self._cache, self.key, self.args, self.size = cache, key, args, frame_size(args)
        self.jitted = jit(exported.call)
        self._compiled: Any = None
        self._lock = threading.Lock()
        self._noted = False  # early.note: once, at the first call

    def load(self) -> Any:
        """The compiled executable (a ``jax.stages.Compiled``)."""
        with self._lock:
            if self._compiled is None:
                self._compiled = self._cache.compiled(self)
            return self._compiled

    def __call__(self, *args: Any) -> Any:
        if _has_tracer(args):
            return self.jitted(*args)
        if not self._noted:  # what the next run loads ahead, in the order first called
            self._noted = True
            early.note(self._cache.directory, self.key, self.size)
        return self.load()(*args)


class ExecutableCache:
    """A :data:`sinkjax.soft.batch.CompiledProvider`: each measuring function exported
    (``jax.export``: traced and lowered) and compiled once per argument shapes and kept in
    ``directory`` (created when first written); a later process loads both instead of tracing
    and lowering the method (:class:`Loaded`).

    Loaded or fresh, the function runs the executable that ``jax.jit(exported.call)`` compiles
    to (through JAX's persistent cache, where that is on): one code path, so a run with cache
    files gives the numbers of a run without them."""

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)
        self._ready: dict[str, Loaded] = {}

    def __call__(self, name: str, fn: Any, args: tuple[Any, ...]) -> Loaded:
        key = cache_key(name, args)
        ready = self._ready.get(key)
        if ready is None:
            if (loaded := self._load(key, args)) is None:
                with compiling(frame_size(args)):  # tracing and lowering: seconds
                    loaded = self._export(key, fn, args)
            exported, module = loaded
            ready = self._ready[key] = Loaded(self, module, exported, args)
        return ready

    def path(self, key: str) -> Path:
        return self.directory / f"{key}.bin"

    def compiled_path(self, key: str) -> Path:
        return compiled_file(self.directory, key)

    def compiled(self, fn: Loaded) -> Any:
        """``fn``'s executable: loaded from :meth:`compiled_path`, else compiled (announced; a
        hit in JAX's persistent cache where that has it) and, where compiled afresh, kept."""
        if (loaded := self._load_compiled(fn.key)) is not None:
            return loaded
        with compiling(fn.size):
            compiled, fresh = _compile_fresh(fn.jitted, fn.args)
        if not fresh:  # loaded by JAX from its cache (or memory): not kept
            return compiled
        try:
            from jax.experimental import serialize_executable

            self._write_compiled(fn.key, *serialize_executable.serialize(compiled))
        except Exception as e:  # the run goes on with the executable compiled here
            log.info("compiled function not written to %s (%s)", self.directory, e)
        return compiled

    def _write_compiled(self, key: str, blob: bytes, in_tree: Any, out_tree: Any) -> None:
        buffer = io.BytesIO()
        _Pickler(buffer).dump((key, blob))
        _Pickler(buffer).dump((in_tree, out_tree))
        self._write(self.compiled_path(key), COMPILED_MAGIC, buffer.getvalue())

    def _load_compiled(self, key: str) -> Any:
        import jax
        from jax.experimental import serialize_executable

        path = self.compiled_path(key)
        start = time.time()
        compiled = self._loaded_ahead(key)
        if compiled is not None:
            jax.monitoring.record_event_time_span(LOAD_EVENT, start, time.time())
            early.backend_ready()
            return compiled
        if not path.exists():
            return None
        early.get_ready_ahead()
        try:
            with path.open("rb") as f:
                old = f.read(len(_COMPILED_MAGIC_1)) == _COMPILED_MAGIC_1
            stream = io.BytesIO(read_checked(path, _COMPILED_MAGIC_1 if old else COMPILED_MAGIC))
            if old:
                stored_key, blob, in_tree, out_tree = _Unpickler(stream).load()
            else:
                stored_key, blob = _Unpickler(stream).load()
                in_tree, out_tree = _Unpickler(stream).load()
            if stored_key != key:
                raise ValueError("written for other arguments")
            device = jax.devices()[0]
            compiled = serialize_executable.deserialize_and_load(
                blob, in_tree, out_tree, backend=device.client, execution_devices=[device]
            )
        except Exception as e:  # any failure: compile afresh instead
            log.info("compiled function %s unusable (%s): compiling it again", path, e)
            # Removed: a compile that JAX loads from its own cache does not rewrite it.
            with contextlib.suppress(OSError):  # a folder not writable: left as it is
                path.unlink(missing_ok=True)
            return None
        if old:  # the same executable in the current layout (a folder not writable: kept as is)
            try:
                self._write_compiled(key, blob, in_tree, out_tree)
            except OSError as e:
                log.info("compiled function %s not rewritten (%s)", path, e)
        jax.monitoring.record_event_time_span(LOAD_EVENT, start, time.time())
        # Only running it needs the platform ready (a compile in this process did that as it
        # lowered): set up on its own thread while this one deserialised (early.get_ready_ahead).
        early.backend_ready()
        return compiled

    @staticmethod
    def _loaded_ahead(key: str) -> Any:
        """The executable :mod:`sinkjax.app.early` loaded for ``key`` while sinkjax was being
        imported, or None (none, or it cannot be assembled: the file is read again)."""
        parts = early.take(key)
        if parts is None:
            return None
        try:
            return parts.compiled()
        except Exception as e:
            log.info("compiled function %s loaded ahead unusable (%s)", key, e)
            return None

    def _write(self, target: Path, magic: bytes, body: bytes) -> None:
        self.directory.mkdir(parents=True, exist_ok=True)
        # Written under a temporary name and renamed: a reader (another worker) never sees
        # half a file.
        fd, tmp = tempfile.mkstemp(dir=self.directory, suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(magic + hashlib.sha256(body).hexdigest().encode() + b"\n" + body)
            os.replace(tmp, target)
        finally:
            Path(tmp).unlink(missing_ok=True)

    def _load(self, key: str, args: tuple[Any, ...]) -> tuple[Any, str] | None:
        import jax

        path = self.path(key)
        if not path.exists():
            return None
        start = time.time()
        try:
            body = read_checked(path, MAGIC)
            stored_key, exported, module = _Unpickler(io.BytesIO(body)).load()
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
        return exported, module

    def _export(self, key: str, fn: Any, args: tuple[Any, ...]) -> tuple[Any, str]:
        """``fn`` exported for ``args`` and its :func:`module_key`, both kept on disk."""
        import jax

        exported = jax.export.export(fn)(*args)
        module = module_key(exported)
        try:
            buffer = io.BytesIO()
            # The VJP hook is a closure (not picklable); the command line never differentiates.
            _Pickler(buffer).dump((key, dataclasses.replace(exported, _get_vjp=None), module))
            self._write(self.path(key), MAGIC, buffer.getvalue())
        except Exception as e:  # the run goes on with the exported function
            log.info("exported function not written to %s (%s)", self.directory, e)
        return exported, module


def compiled_file(directory: Path, key: str) -> Path:
    """Where :class:`ExecutableCache` keeps the compiled executable of module ``key``."""
    return directory / f"{key}.exe"


def read_checked(path: Path, magic: bytes) -> bytes:
    """The body of a file written by :class:`ExecutableCache` with first line ``magic``; a
    ValueError if that line or the body's checksum is wrong."""
    data = path.read_bytes()
    head, _, body = data[len(magic) :].partition(b"\n")
    if not data.startswith(magic) or head.decode() != hashlib.sha256(body).hexdigest():
        raise ValueError("bad header or checksum")
    return body
