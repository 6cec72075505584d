"""JAX's persistent compilation cache for runs of the command line, and the run's compile time.

The soft method compiles once per image size (the rig's numbers are traced, see
:class:`sinkjax.soft.estimator.RigArrays`). Within a process that compile is reused; the
persistent cache keeps it on disk so that the next run, or the next worker process of a
parallel run, loads it in about a second instead of compiling for tens; the soft method's
exported and compiled functions are kept there too (:mod:`sinkjax.app.executables`), so that a
new process need not even trace or lower it. The cache is set up by the command line
(``sinkjax estimate``, ``sinkjax demo``), never on importing the library: a program that uses
sinkjax keeps its own JAX configuration.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

CACHE_ENV = "SINKJAX_CACHE_DIR"
OFF = ("off", "none", "0", "")

# The time a process spends loading the soft method's exported functions from disk
# (sinkjax.app.executables): reported as part of the run's compile time (CompileClock).
LOAD_EVENT = "/sinkjax/exported_load_duration"
# JAX events whose time spans make up "compiling": tracing to a jaxpr, lowering to MLIR, and
# the backend's compile or its load from the persistent cache.
_COMPILE_EVENTS = frozenset(
    {
        "/jax/core/compile/jaxpr_trace_duration",
        "/jax/core/compile/jaxpr_to_mlir_module_duration",
        "/jax/core/compile/backend_compile_duration",
        LOAD_EVENT,
    }
)


# Called with (frame size (width, height) or None, True) as a measuring function starts being
# compiled (or loaded from JAX's cache) for a new shape, and with False when it is ready.
CompileListener = Callable[[tuple[int, int] | None, bool], None]
_listeners: list[CompileListener] = []


@contextlib.contextmanager
def compile_notices(listener: CompileListener) -> Iterator[None]:
    """While inside, ``listener`` hears of every compile of the soft method's measuring
    functions (:class:`sinkjax.app.executables.ExecutableCache`): a run's progress bar says
    why it waits, and leaves that wait out of its rate and ETA."""
    _listeners.append(listener)
    try:
        yield
    finally:
        _listeners.remove(listener)


@contextlib.contextmanager
def compiling(size: tuple[int, int] | None) -> Iterator[None]:
    """Tell the listeners of :func:`compile_notices` that a compile for ``size`` runs inside."""
    for listener in list(_listeners):
        listener(size, True)
    try:
        yield
    finally:
        for listener in list(_listeners):
            listener(size, False)


def cache_dir(enabled: bool = True) -> Path | None:
    """Where the compiled functions are kept: ``$SINKJAX_CACHE_DIR`` (``off`` turns the cache
    off), else ``$XDG_CACHE_HOME/sinkjax/jax`` or ``~/.cache/sinkjax/jax``. None when off."""
    if not enabled:
        return None
    value = os.environ.get(CACHE_ENV)
    if value is not None:
        return None if value.strip().lower() in OFF else Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "sinkjax" / "jax"


def enable_compile_cache(path: str | Path | None) -> Path | None:
    """Turn on JAX's persistent compilation cache in ``path`` (created); None leaves it off.

    Returns the directory in use, or None if it could not be created (the run goes on without).
    """
    if path is None:
        return None
    import jax

    target = Path(path)
    try:
        target.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(target))
    # Keep every soft-method compile (the default skips those under a second).
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    # And the soft method's executables themselves, which a new process loads without tracing.
    from ..soft.batch import set_compiled_provider
    from .executables import ExecutableCache

    set_compiled_provider(ExecutableCache(target / "executables"))
    return target


class CompileClock:
    """Wall time spent compiling (tracing, lowering, compiling or loading from the cache) while
    it runs, in this process: the union of JAX's compile events' time spans, so nested traces
    count once. Use as a context manager; read :attr:`seconds` after."""

    def __init__(self) -> None:
        self._spans: list[tuple[float, float]] = []
        self._lock = threading.Lock()
        self._open = False

    def _listen(self, event: str, start_time: float, end_time: float, **kwargs: str | int) -> None:
        if self._open and event in _COMPILE_EVENTS:
            with self._lock:
                self._spans.append((start_time, end_time))

    def __enter__(self) -> CompileClock:
        import jax.monitoring

        self._open = True
        jax.monitoring.register_event_time_span_listener(self._listen)
        return self

    def __exit__(self, *exc: object) -> None:
        import jax.monitoring

        self._open = False
        # Older JAX versions cannot unregister; the listener then just keeps appending.
        unregister = getattr(jax.monitoring, "unregister_event_time_span_listener", None)
        if unregister is not None:
            try:
                unregister(self._listen)
            except (AssertionError, ValueError):
                pass

    @property
    def seconds(self) -> float:
        total, reach = 0.0, float("-inf")
        with self._lock:
            spans = sorted(self._spans)
        for start, end in spans:
            if end > reach:
                total += end - max(start, reach)
                reach = end
        return total
