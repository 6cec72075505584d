"""Loading the soft method's later compiled halves on a thread while the first half runs.

A new process with a warm cache still loads each half's executable from disk (JAX's persistent
cache, or the command line's own copy, :mod:`sinkjax.app.executables`): at 640x480 about 0.5 s
for ``prepare`` and 0.9-1.2 s for ``finish``, one after the other when each is loaded at its
first call. :func:`warm` starts such a load on one background thread as soon as the arguments'
shapes are known (``finish``'s from the exported ``prepare``'s outputs, :func:`placed_like`), so
it overlaps with ``prepare``'s own load and run (which then measures its frames one at a time:
:func:`loading`, so that the load has a core); :func:`warmed` waits for it before the first
call. The compile lands in JAX's own caches (the lowering must be the call's: the abstract
arguments carry the device placement of real ones), or a function with a ``load`` method is
loaded, so the call compiles nothing; should the load fail, the call compiles as it would have.
``experiments/campaign.py`` measures the start-up.
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import jax

log = logging.getLogger("sinkjax")

_started: dict[int, Future[None]] = {}  # by the compiled function's id
_asked: set[int] = set()  # the functions first_time has seen
_pool: ThreadPoolExecutor | None = None


def _forget() -> None:
    # A forked child has none of the parent's threads: a pool inherited from it would never
    # run what is submitted to it.
    global _pool
    _pool = None
    _started.clear()
    _asked.clear()


os.register_at_fork(after_in_child=_forget)


def first_time(fn: Any) -> bool:
    """True the first time it is asked about ``fn`` in this process: what is loaded ahead of a
    function's later halves is decided once, not on every batch."""
    new = id(fn) not in _asked
    _asked.add(id(fn))
    return new


def placed_like(tree: Any, array: jax.Array) -> Any:
    """``tree``'s abstract values (``jax.eval_shape``) placed on ``array``'s device, as the
    outputs of a compiled call on it are."""
    at = jax.sharding.SingleDeviceSharding(next(iter(array.devices())))
    return jax.tree_util.tree_map(
        lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=at, weak_type=a.weak_type), tree
    )


def warm(fn: Any, args: tuple[Any, ...]) -> None:
    """Compile the jitted ``fn`` for the abstract ``args`` (or, for a function with a ``load``
    method, load it) on the background thread, once per function; loads run in the order they
    were asked for."""
    global _pool

    def compile_quietly() -> None:
        try:
            load = getattr(fn, "load", None)  # an executable kept on disk (app.executables)
            if load is not None:
                load()
            else:
                fn.lower(*args).compile()
        except Exception as e:  # the call compiles it again
            log.debug("loading %s ahead failed (%s); it compiles when called", fn, e)

    if id(fn) not in _started:
        if _pool is None:
            _pool = ThreadPoolExecutor(1, thread_name_prefix="sinkjax-warm")
        _started[id(fn)] = _pool.submit(compile_quietly)


def loading() -> bool:
    """Whether a load started by :func:`warm` is still running (it has a core to itself)."""
    return any(not f.done() for f in _started.values())


def warmed(fn: Any) -> Any:
    """``fn``, once a load of it started by :func:`warm` has finished."""
    if id(fn) in _started:
        _started[id(fn)].result()
    return fn
