"""The compiled calibration losses: one compile per image size, kept on disk, started early.

:func:`loss_and_grad` and :func:`loss_value` are :func:`~sinkjax.calibration.loss.frame_losses`
compiled with the rig's numbers as traced arrays (:class:`~sinkjax.calibration.loss.LossRig`),
so one compiled function serves every rig of an image size (the gradient: and number of
labelled frames; the loss alone is compiled for one frame and called frame by frame). The
gradient is traced with a failed implicit solve as NaN (:func:`solve_failures_as_nan`):
without a Python callback in it, it enters JAX's persistent compilation cache, and a second
calibration of a size already seen compiles nothing. :func:`compile_in_background` compiles the
loss on another thread while the recording's rim is found, then the gradient while the grid is
scored with the loss alone (the first calibration of a size: compiling beside the work on two
cores).
"""

from __future__ import annotations

import contextlib
import functools
import math
import threading
from collections.abc import Iterator, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray, UInt8

from ..geometry import travel_sign
from ..rig import rect_problem, srgb_flag
from ..soft.rim import RecordingRim
from ..xla import jit
from .augment import DEFAULT_CONFIG, AugmentConfig
from .loss import FrameLoss, LossAndGrad, LossRig, frame_losses


class _OnError:
    """Threads inside :func:`solve_failures_as_nan`, and equinox's setting before the first."""

    lock = threading.Lock()
    depth = 0
    before: Any = None


@contextlib.contextmanager
def solve_failures_as_nan() -> Iterator[None]:
    """While a function is traced under this: a linear solve of the fit's implicit gradient
    that fails (a singular system) gives NaN instead of a runtime error.

    optimistix differentiates the fit through a lineax solve that checks its result with
    ``equinox.error_if``, which by default raises and puts a Python callback into the
    compiled function; a function with a callback never enters JAX's persistent compilation
    cache. Calibration and training drop a frame with a NaN gradient anyway, so they trace
    their gradients under this: equinox's ``EQX_ON_ERROR=nan`` while any thread is inside
    (equinox reuses a check it traced before, so a process's first such trace decides).
    Without that setting in equinox, nothing changes."""
    try:
        import equinox._errors as errors  # the setting equinox reads when it traces error_if

        errors.EQX_ON_ERROR  # noqa: B018 - present in this equinox?
    except (ImportError, AttributeError):  # another equinox: its default behaviour
        yield
        return
    with _OnError.lock:
        if _OnError.depth == 0:
            _OnError.before = errors.EQX_ON_ERROR
            errors.EQX_ON_ERROR = "nan"
        _OnError.depth += 1
    try:
        yield
    finally:
        with _OnError.lock:
            _OnError.depth -= 1
            if _OnError.depth == 0:
                errors.EQX_ON_ERROR = _OnError.before


def loss_rig(
    rect: tuple[int, int, int, int],
    travel: str,
    wheel_radius_mm: float,
    shape: tuple[int, ...] | None = None,
    encoding: str = "linear",
) -> LossRig:
    """:class:`LossRig` of a rig's confidence rectangle, travel and wheel radius, in the default
    float dtype. ``shape``: the frames' (N, H, W, 3), against which the rectangle is checked
    (ValueError if it does not lie inside the images). ``encoding``: the rig's ("srgb": the
    outline is located in linear light, as ``sinkjax estimate`` does)."""
    plain = tuple(int(v) if isinstance(v, np.integer) else v for v in rect)
    if shape is not None:
        problem = rect_problem(plain, int(shape[-3]), int(shape[-2]))
        if problem is not None:
            raise ValueError(problem)
    # Made once per rig and dtype: calibration asks for it in every call (~6 ms each).
    return _loss_rig(plain, travel, float(wheel_radius_mm), encoding, jnp.result_type(float))


@functools.lru_cache(maxsize=64)
def _loss_rig(
    rect: tuple[int, int, int, int], travel: str, wheel_radius_mm: float, encoding: str, dt: Any
) -> LossRig:
    return LossRig(
        rect_px=jnp.asarray(rect, jnp.int32),
        travel_sign=jnp.asarray(travel_sign(travel), dt),
        wheel_radius_mm=jnp.asarray(wheel_radius_mm, dt),
        srgb=jnp.asarray(srgb_flag(encoding), dt),
    )


# No rig statics: compiled once per image size, frame count and augmentation setting (the loss
# alone: loss_value calls it with one frame at a time).
@jit(static_argnames=("use_augment", "config"))
def _loss_and_grad(
    raw: Array, images_u8: Array, targets: Array, key: PRNGKeyArray, rim: RecordingRim | None,
    rig: LossRig, use_augment: bool, config: AugmentConfig,
) -> LossAndGrad:  # fmt: skip
    return frame_losses(
        raw, images_u8, targets, key, rim, rig, use_augment=use_augment, config=config,
        with_grad=True,
    )  # fmt: skip


@jit
def _loss_value(
    raw: Array, images_u8: Array, targets: Array, rim: RecordingRim | None, rig: LossRig
) -> LossAndGrad:
    return frame_losses(
        raw, images_u8, targets, jax.random.key(0), rim, rig, use_augment=False,
        config=DEFAULT_CONFIG, with_grad=False,
    )  # fmt: skip


def loss_and_grad(
    raw: Float[Array, " 7"],
    images_u8: UInt8[Array, "N H W 3"],
    targets: Float[Array, "N 3"],
    key: PRNGKeyArray,
    rim: RecordingRim | None = None,
    *,
    rect: tuple[int, int, int, int],
    travel: str,
    wheel_radius_mm: float,
    use_augment: bool = False,
    config: AugmentConfig = DEFAULT_CONFIG,
    encoding: str = "linear",
) -> LossAndGrad:
    """The calibration loss of a stack of labelled frames and its gradient, taken frame by
    frame (:func:`~sinkjax.calibration.loss.frame_losses`, over
    :func:`~sinkjax.xla.map_frames`). With ``use_augment`` each
    frame first gets a random lighting change from ``key``. ``rim`` (traced; None: each frame's
    own) is the recording's rim every frame is measured with. The rig's numbers reach the
    compiled function as arrays (:class:`~sinkjax.calibration.loss.LossRig`): one compile per
    image size and frame count, whatever the rig, cached on disk where JAX's persistent
    compilation cache is on (:func:`solve_failures_as_nan`). Compiled for one frame and called
    frame by frame instead, 6 frames at 640x480 took 1.2-1.35x as long (2026-12-07: each call
    repeats work that a stack of frames does once). Raises ValueError if ``rect`` does not lie
    inside the frames.
    """
    rig = loss_rig(rect, travel, wheel_radius_mm, images_u8.shape, encoding)
    with solve_failures_as_nan():  # no callback: the compiled loss can be cached on disk
        return _loss_and_grad(raw, images_u8, targets, key, rim, rig, use_augment, config)


def loss_value(
    raw: Float[Array, " 7"],
    images_u8: UInt8[Array, "N H W 3"],
    targets: Float[Array, "N 3"],
    rim: RecordingRim | None = None,
    *,
    rect: tuple[int, int, int, int],
    travel: str,
    wheel_radius_mm: float,
    encoding: str = "linear",
    bound: float = math.inf,
    order: Sequence[int] | None = None,
    given: LossAndGrad | None = None,
) -> LossAndGrad:
    """:func:`loss_and_grad`'s loss and frames without the gradient (``grad`` is zeros): the
    forward pass alone, for scoring a grid (6 frames at 640x480 on 2 cores, 2026-12-07: 0.55-0.95 s
    against 0.75-1.0 s with the gradient).

    Compiled for one frame and called frame by frame, in ``order`` (default: as given), as a CPU
    measures them anyway (6 frames: the same time within 5 %, a compile of 42 s against 48 s):
    one compile per image size, whatever the number of frames. Every frame's loss is >= 0 and the
    loss is their sum over the number of labelled cells, so once the frames measured so far sum
    to more than ``bound`` the loss is above it whatever the rest measure: the rest are skipped
    (their ``frames`` entries NaN, status -1) and ``loss`` is that partial sum, a lower bound
    (:func:`complete` says which); a ``bound`` of -inf measures the first frame of ``order``
    alone. ``given``: an earlier call's result for the same point, whose measured frames are
    taken as they are (a point measured on one frame first, then completed). Calibration scores
    its grid and polish so: a point that cannot be among the lowest is dropped after a frame or
    two."""
    rig = loss_rig(rect, travel, wheel_radius_mm, images_u8.shape, encoding)
    n = int(images_u8.shape[0])
    if n == 0:
        raise ValueError("loss_value needs at least one frame")
    # Frames in and results out as NumPy: op-by-op JAX calls here (slices, concatenations) cost
    # about 0.5 ms each, 5-10 s over a calibration's 200 calls.
    images, labels = np.asarray(images_u8), np.asarray(targets)
    n_cells = max(int(np.isfinite(labels).sum()), 1)
    outs: dict[int, FrameLoss] = {}
    if given is not None:
        for k in np.flatnonzero(np.asarray(given.frames.status) >= 0).tolist():
            outs[k] = jax.tree.map(lambda a, k=k: np.asarray(a)[k : k + 1], given.frames)
    total = sum(float(f.loss[0]) for f in outs.values())
    for i in range(n) if order is None else order:
        if outs and total / n_cells > bound:
            break
        if i not in outs:
            out = _loss_value(raw, images[i : i + 1], labels[i : i + 1], rim, rig)
            outs[i] = jax.tree.map(np.asarray, out.frames)
            total += float(outs[i].loss[0])
    first = next(iter(outs.values()))
    skipped = jax.tree.map(
        lambda a: np.full_like(a, -1 if np.issubdtype(a.dtype, np.integer) else np.nan), first
    )
    frames = jax.tree.map(lambda *a: np.concatenate(a), *(outs.get(i, skipped) for i in range(n)))
    dt = np.asarray(raw).dtype
    loss, zeros = np.asarray(total / n_cells, dt), np.zeros(np.shape(raw), dt)
    return LossAndGrad(loss=loss, grad=zeros, frames=frames)  # type: ignore[arg-type]


def complete(out: LossAndGrad) -> bool:
    """Whether every frame of ``out`` was measured (:func:`loss_value` with a ``bound`` may
    skip some)."""
    return bool(np.all(np.asarray(out.frames.status) >= 0))


class Compiling:
    """Compiles running on daemon threads (:func:`compile_in_background`): the loss's, then the
    gradient's. Two calls of one function would compile it twice at once: wait first."""

    def __init__(self, loss: threading.Thread | None, gradient: threading.Thread | None) -> None:
        self._loss, self._gradient = loss, gradient

    def loss_pending(self) -> bool:
        """Whether the loss is still being compiled."""
        return self._loss is not None and self._loss.is_alive()

    def loss_ready(self) -> None:
        """Wait until the loss alone is compiled (or its compile failed)."""
        if self._loss is not None:
            self._loss.join()

    def join(self) -> None:
        """Wait until everything asked for is compiled (or failed)."""
        self.loss_ready()
        if self._gradient is not None:
            self._gradient.join()


def compile_in_background(
    *args: object,
    augment_config: AugmentConfig | None = None,
    value: bool = False,
    gradient: bool = True,
    **rig: object,
) -> Compiling:
    """Start compiling :func:`loss_and_grad` for its arguments ``args`` and ``rig`` (its rig
    keywords ``rect``, ``travel``, ``wheel_radius_mm``; and its augmented variant, with
    ``augment_config``) on a daemon thread, which ends when it is compiled; with ``value``
    :func:`loss_value` before it, on a thread of its own (calibration compiles it while the rim
    is found); without ``gradient`` that alone. ``rim`` (the fifth of ``args``) need only have
    the shapes of the rim the calls will get (``RecordingRim.per_frame()`` has them). A later
    call with arguments of the same shapes then finds them compiled (in memory). Only the time
    changes: a compile that fails here fails again, with its error, in the call."""
    raw, images_u8, targets, key, rim = args
    arrays = loss_rig(
        rig["rect"], rig["travel"], rig["wheel_radius_mm"], None, rig.get("encoding", "linear"),  # type: ignore[arg-type]
    )  # fmt: skip
    variants = [(False, DEFAULT_CONFIG)] + ([(True, augment_config)] if augment_config else [])

    def loss() -> None:
        try:
            # One frame's shapes: loss_value calls it frame by frame.
            _loss_value.lower(raw, images_u8[:1], targets[:1], rim, arrays).compile()  # type: ignore[index]
        except Exception:  # reported by the call that needs it
            return

    def work() -> None:
        if first is not None:
            first.join()  # one compile at a time: the rim is being found on the other core
        try:
            with solve_failures_as_nan():
                for use_augment, config in variants:
                    _loss_and_grad.lower(
                        raw, images_u8, targets, key, rim, arrays, use_augment, config
                    ).compile()
        except Exception:  # reported by the call that needs it
            return

    first = (
        threading.Thread(target=loss, name="sinkjax-compile-loss", daemon=True) if value else None
    )
    second = (
        threading.Thread(target=work, name="sinkjax-compile-gradient", daemon=True)
        if gradient
        else None
    )
    for thread in (first, second):
        if thread is not None:
            thread.start()
    return Compiling(first, second)
