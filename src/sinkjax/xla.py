"""How sinkjax compiles: ``jax.jit`` / ``eqx.filter_jit``, with XLA options that make the soft
method compile faster on a CPU where ``SINKJAX_FAST_COMPILE=1`` asks for them (chosen once per
process, at the first compile). Off by default: they compile faster but run slower. And how a
stack of frames is mapped on each backend (:func:`map_frames`).

The soft method is one large program (segmentation, outline, rim search, two Levenberg-Marquardt
solves, covariance, checks: about 29 000 lines of HLO before optimisation), and on a CPU
most of a cold start is XLA compiling it. XLA's newer CPU fusion emitters
(``xla_cpu_use_fusion_emitters``, on by default) generate each fusion through MLIR, which costs
more compile time than the classic elemental emitters. Measured by
``experiments/compile_options.py`` (one thread, as each ``make test`` worker has; 2 CPU cores,
jax 0.10.2): with the classic emitters the forward pass compiles in 0.70-0.77x the time, its
gradient in 0.73-0.82x, and every output agrees to 6e-14 in float64; in float32 (the command
line's precision) no status of ``experiments/benchmark.py --seed 11 --recordings 5`` changed and
values moved by at most 3e-5 mm (z0), 0.005 deg (angles). But through the pipeline, on both
cores, the frames run slower: ``SINKJAX_FAST_COMPILE=0/1 python experiments/bench.py --one soft W
H 1 N`` taking turns, 60 / 67 ms a 640x480 frame (48 frames, twice each) and 170-198 / 207-216 ms
a 1280x720 one, for about 4 s less compiling (14.5 against 18.5 s). With JAX's persistent cache a
run compiles once per image size and machine and then only runs, so the library keeps XLA's
defaults; the test suite, which compiles a new program in nearly every test, turns the option on
for every compile through ``XLA_FLAGS`` (``tests/conftest.py``: 18 min instead of 23). The
persistent cache keeps the two apart (the options are part of its key).

An XLA that does not know the option (an older or newer jaxlib) gets none: the first compile
probes it with a one-operation function, and an unknown option is a Python error there, not a
crash.
"""

from __future__ import annotations

import functools
import os
import threading
from collections.abc import Callable, Sequence
from typing import Any

#: The XLA debug options sinkjax compiles with, where the installed XLA knows them.
FAST_COMPILE_OPTIONS: dict[str, Any] = {"xla_cpu_use_fusion_emitters": False}
#: Set to "1" to compile with :data:`FAST_COMPILE_OPTIONS` (default: XLA's own).
ENV_SWITCH = "SINKJAX_FAST_COMPILE"


@functools.cache
def compiler_options() -> dict[str, Any]:
    """The options every sinkjax ``jit`` passes to XLA: :data:`FAST_COMPILE_OPTIONS` where
    ``SINKJAX_FAST_COMPILE=1`` asks for them and this XLA accepts them (probed once per
    process), else none. Initialises JAX's backend, so it is called at the first compile, never
    at import."""
    if os.environ.get(ENV_SWITCH, "0").strip() != "1":
        return {}
    import jax
    import numpy as np

    try:
        jax.jit(_probe, compiler_options=FAST_COMPILE_OPTIONS).lower(np.float32(0)).compile()
    except Exception:  # any XLA that refuses the option: compile with none
        return {}
    return dict(FAST_COMPILE_OPTIONS)


def _probe(x: Any) -> Any:
    return x + 1


class _LazyJit:
    """A jitted function built at its first use (call or attribute, e.g. ``lower``), when the
    compile options can be probed without initialising JAX at import."""

    def __init__(self, make: Callable[[dict[str, Any]], Any], fun: Callable[..., Any]) -> None:
        self._make = make
        self._jitted: Any = None
        self._lock = threading.Lock()  # two threads' first calls build one jitted function
        functools.update_wrapper(self, fun)

    def _get(self) -> Any:
        if self._jitted is None:
            with self._lock:
                if self._jitted is None:
                    self._jitted = self._make(compiler_options())
        return self._jitted

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self._get()(*args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__") or name in ("_make", "_jitted", "_lock"):
            raise AttributeError(name)
        return getattr(self._get(), name)


def jit(fun: Callable[..., Any] | None = None, /, **kwargs: Any) -> Any:
    """``jax.jit(fun, **kwargs)`` with :func:`compiler_options`; as a decorator too, with or
    without keyword arguments (``@jit``, ``@jit(static_argnames=...)``)."""
    if fun is None:
        return functools.partial(jit, **kwargs)
    f = fun

    def make(options: dict[str, Any]) -> Any:
        import jax

        return jax.jit(f, compiler_options=options or None, **kwargs)

    return _LazyJit(make, f)


def filter_jit(fun: Callable[..., Any] | None = None, /, **kwargs: Any) -> Any:
    """``eqx.filter_jit(fun, **kwargs)`` with :func:`compiler_options`."""
    if fun is None:
        return functools.partial(filter_jit, **kwargs)
    f = fun

    def make(options: dict[str, Any]) -> Any:
        import equinox as eqx

        filter_jit_: Any = eqx.filter_jit  # its stub lists no jax.jit keywords
        return filter_jit_(f, compiler_options=options or None, **kwargs)

    return _LazyJit(make, f)


def frames_in_lockstep() -> bool:
    """Whether a stack of frames is measured as one vmapped batch (accelerators) rather than
    one frame after another (a CPU). Under ``vmap`` the fit's Levenberg-Marquardt loops of all
    frames run in lockstep until the slowest converges and both sides of every branch run: on
    a CPU frame by frame is faster (:func:`map_frames`). Decided when a function is traced."""
    import jax

    return jax.default_backend() != "cpu"


def map_frames(fun: Callable[[Any], Any], frames: Any) -> Any:
    """``fun`` of each frame of ``frames`` (a pytree whose leaves share a leading frame axis),
    stacked: ``jax.vmap`` on an accelerator, ``jax.lax.map`` (one frame after another, each
    loop stopping when its own frame converges) on a CPU. The same numbers either way (to
    float rounding); jit-able, vmap-able and differentiable alike. Measured by
    ``experiments/frame_map.py`` (6 labelled 640x480 frames, float64, 2 cores): the calibration
    loss runs in 0.42x the vmapped time, its gradient in 0.37x, both compile in 0.72x, and a
    first calibration takes 165 s against 317 s."""
    import jax

    if frames_in_lockstep():
        return jax.vmap(fun)(frames)
    return jax.lax.map(fun, frames)


# Frames measured side by side on a CPU (side_by_side); SINKJAX_FRAME_THREADS overrides it.
_DEFAULT_FRAME_THREADS = 2
_frame_pool: Any = None  # (threads, ThreadPoolExecutor)
_POOL_NAME = "sinkjax-side-by-side"
_POOL_LOCK = threading.Lock()


def frame_threads() -> int:
    """How many frames a CPU measures side by side (:func:`side_by_side`):
    ``SINKJAX_FRAME_THREADS`` if set (1: one after another), else 2 where the process may use
    two cores or more."""
    text = os.environ.get("SINKJAX_FRAME_THREADS", "").strip()
    if text:
        try:
            return max(1, int(text))
        except ValueError:
            problem = f"SINKJAX_FRAME_THREADS must be a whole number, got {text!r}"
            raise ValueError(problem) from None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return min(_DEFAULT_FRAME_THREADS, cores or 1)


def _forget_pool() -> None:
    # A forked child has none of its parent's threads: a pool inherited from it would hang.
    global _frame_pool, _POOL_LOCK
    _frame_pool, _POOL_LOCK = None, threading.Lock()


os.register_at_fork(after_in_child=_forget_pool)


def side_by_side(
    fun: Callable[..., Any], *columns: Sequence[Any], alone: bool = False, compiled: bool = False
) -> list[Any]:
    """``[fun(*row) for row in zip(*columns)]`` (frames, or calibration's candidate points),
    each result computed (blocked on), the rows after the first on :func:`frame_threads`
    threads. One compiled call leaves a CPU's second core mostly idle (most of XLA's fused
    loops run on one thread), so two frames side by side take 0.75-0.85x the time of one after
    the other (640x480 on 2 cores). The first row runs alone, so that a function that still has
    to compile compiles once; with ``compiled`` (it has run on these shapes before) every row
    runs on the pool, so that two rows run together (2026-12-08: calibration's grid points in
    pairs had run one after another). The same numbers as one after another: each call is the
    same compiled function on its own inputs. Called from the pool's own threads, or with
    ``alone`` (the other core is busy, e.g. loading the next function): one after another."""
    import concurrent.futures

    import jax

    global _frame_pool
    rows = list(zip(*columns, strict=True))

    def run(row: tuple[Any, ...]) -> Any:
        return jax.block_until_ready(fun(*row))

    threads = frame_threads()
    # Called from one of the pool's own threads (frames of a point measured side by side):
    # one after another there, or the pool would wait on itself.
    nested = threading.current_thread().name.startswith(_POOL_NAME)
    if len(rows) < 2 or threads < 2 or nested or alone:
        return [run(r) for r in rows]
    with _POOL_LOCK:
        if _frame_pool is None or _frame_pool[0] != threads:
            _frame_pool = (threads, concurrent.futures.ThreadPoolExecutor(threads, _POOL_NAME))
        pool = _frame_pool[1]
    if compiled:
        return list(pool.map(run, rows))
    first = run(rows[0])
    return [first, *pool.map(run, rows[1:])]
