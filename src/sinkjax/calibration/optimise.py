"""Calibration optimiser: a coarse grid, then Adam from its best points; checks and a report.

The loss is piecewise smooth (a frame stops measuring when a threshold crosses a point) and
gradient descent from a mask that is far off can sit on a plateau. So calibration first scores a
coarse grid over P_d/P_a of hue and saturation (:data:`GRID`, 81 points around the defaults,
plus the rig's own point; its best few again with the soil/background veto relaxed,
:data:`VETO_RELAXED`) by the loss alone (``compiled.loss_value``, while the gradient compiles on
another thread; every point on one frame first, then the lowest completed first, a point whose
frames so far already put it above the lowest it must beat dropped: ``rescore.score_pruned``),
then runs Adam from the best few grid points (a short probe each, the rest of the steps from the
best probe) and keeps the best point seen anywhere, scored as ``sinkjax estimate`` will measure
it (with the rim its own thresholds find), and polishes it by a compass search that measures
every point so (``rescore.polish``): the result is never worse, on the labelled frames, than the
grid's best point. Each descent keeps its best point, goes back there with a smaller step when a
step lands where frames fail, and stops once the loss has not improved for a while.
``checks.py`` then says whether it converged, which labelled frames disagree with the rest, and
the leave-one-out error.
"""

from __future__ import annotations

import functools
import itertools
import math
import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, PRNGKeyArray

from ..rig import Rig, SegmentationParams
from ..soft.batch import SoftRecording
from ..soft.rim import RecordingRim
from ..xla import side_by_side
from .augment import DEFAULT_CONFIG, AugmentConfig
from .checks import CalibrationResult, Errors, run_checks
from .compiled import compile_in_background, complete, loss_and_grad, loss_value
from .labels import LabelledFrames
from .loss import LossAndGrad, raw_values, to_raw
from .rescore import (
    N_RESCORED,
    POLISH_MEASUREMENTS,
    FrameCounter,
    InOrder,
    PolishProgress,
    _as_estimate_measures,
    _distinct_lowest,
    _with,
    polish_best,
    score_pruned,
)

BACKTRACK = 2.0  # a loss above this times the best so far sends Adam back to the best point
# The coarse grid (81 points) around the defaults (P_d(H) 0.9, P_a(H) 1.1, P_d(S) 0.5,
# P_a(S) 1.8): each value, a narrow and a wide band in each direction. The 16 corners alone
# missed the best band on a colour cast (hard_cast, seed 20263: P_d(S) 0.7, loss 0.20, where
# the calibration from the corners ended at the defaults' 0.26).
GRID: dict[str, tuple[float, ...]] = {
    "p_d_hue": (0.8, 0.9, 0.95),
    "p_a_hue": (1.05, 1.1, 1.2),
    "p_d_sat": (0.2, 0.5, 0.7),
    "p_a_sat": (1.4, 1.8, 2.5),
}
N_STARTS = 3
# The best grid points are also scored with the soil/background veto relaxed to this fraction
# (SegmentationParams.veto_fraction; 0.25 by default): dust that blends the wheel's colour
# towards the soil's survives the veto only then (Adam alone would take many steps to get there).
VETO_RELAXED = 1.0
# This many of the lowest grid points (one of each loss) are scored again with the veto relaxed.
N_RELAXED = 6


class _Descent(NamedTuple):
    losses: list[float]
    best_step: int
    raw: Array
    out: LossAndGrad
    trail: list[tuple[Array, LossAndGrad]]  # every point evaluated, for the checks
    stopped_early: bool


def _descend(
    call: Callable[..., LossAndGrad],
    raw: Array,
    out: LossAndGrad,
    steps: int,
    learning_rate: float,
    patience: int,
    augment: Callable[[Array, int], Array] | None,
    on_step: Callable[[float], None],
) -> _Descent:
    """Adam from ``raw`` (whose loss ``out`` is known) for up to ``steps`` steps."""
    opt = optax.adam(optax.cosine_decay_schedule(learning_rate, max(steps, 1), alpha=0.1))
    with jax.numpy_dtype_promotion("standard"):
        state = opt.init(raw)
    scale = 1.0
    losses: list[float] = []
    trail: list[tuple[Array, LossAndGrad]] = []
    best = (0, raw, out)
    early = False
    for step in range(steps + 1):
        if step > 0:
            out = call(raw)
            trail.append((raw, out))
        losses.append(float(out.loss))
        if losses[-1] < losses[best[0]]:
            best = (step, raw, out)
        on_step(losses[-1])
        if step == steps:
            break
        if step - best[0] >= patience:
            early = True
            break
        if losses[-1] > BACKTRACK * losses[best[0]]:
            # The loss is piecewise smooth: a step landed where frames stop measuring. Go back
            # to the best point, forget the momentum that carried us here, take smaller steps.
            _, raw, out = best
            with jax.numpy_dtype_promotion("standard"):
                state = opt.init(raw)
            scale = 0.5 * scale
        grad = out.grad if augment is None else augment(raw, step)
        # optax's schedules mix Python floats with int32 step counts: allow that promotion
        # here even where the user runs JAX with strict dtype promotion.
        with jax.numpy_dtype_promotion("standard"):
            step_grad = grad if augment is None else 0.5 * (out.grad + grad)
            updates, state = opt.update(step_grad, state, raw)
        raw = raw + scale * updates
    return _Descent(losses, best[0], best[1], best[2], trail, early)


def calibrate(
    frames: LabelledFrames,
    rig: Rig,
    *,
    steps: int = 50,
    learning_rate: float = 0.1,
    patience: int = 12,
    augment: bool = False,
    augment_config: AugmentConfig = DEFAULT_CONFIG,
    seed: int = 0,
    progress: bool = False,
    callback: Callable[[int, float], None] | None = None,
    on_stage: Callable[[str, int, int], None] | None = None,
    grid: dict[str, tuple[float, ...]] | None = GRID,
    starts: int = N_STARTS,
    rim: str | RecordingRim = "recording",
    polish_measurements: int = POLISH_MEASUREMENTS,
    prune: bool = True,
) -> CalibrationResult:
    """Tune ``rig.segmentation`` to labelled frames: grid, then Adam; returns the calibrated rig.

    Deterministic (``seed`` only drives the augmentations). Scores the rig's own point and every
    point of ``grid`` (P_d/P_a values; None: no grid, Adam from the rig alone) by the loss
    alone, the best of those (:data:`N_RELAXED`, one of each loss) again with the veto relaxed
    (:data:`VETO_RELAXED`), then runs Adam from the ``starts`` best of them (one of each loss):
    ``steps // (2 starts)`` probe steps each, the remaining steps from the best probe's best
    point. The calibrated rig is the lowest loss seen anywhere (grid points included), as
    ``sinkjax estimate`` measures it: the lowest point, the start and the lowest grid points
    (see :func:`_as_estimate_measures`) are scored again with the rim each finds itself. Each
    descent keeps its best point, goes back there with half the step size after a step that
    more than doubles the loss (frames stopped measuring) and stops after ``patience`` steps
    without improvement. With ``augment`` each step's gradient averages the frames as labelled
    and under a random lighting change; ``steps=0``: the grid search alone (no gradient is
    compiled). After the descents, the chosen point is polished (``rescore.polish``: a compass
    search over P_d/P_a in at most ``polish_measurements`` measurements, each with the rim the
    point finds; 0: none, nor with ``steps=0``). The result's ``checks`` say whether the last
    descent converged, which frames disagree with the rest, and the leave-one-out error.
    ``losses`` is the final descent's loss per step (from its starting point).
    Progress: ``progress`` draws bars on the terminal (the grid's frames measured, Adam's steps,
    the polish's measurements); ``callback(step, loss)`` at each Adam step (in order, maybe
    from a worker thread: descents run side by side), ``on_stage(stage, done, total)`` as the
    grid ("grid": frames measured, of at most ``total``; points that cannot be among the lowest
    stop early, and the last call has ``done == total``) and the polish ("polish":
    measurements, of at most ``total``) go on.
    ``rim``: "recording" (default) takes the labelled frames as frames of one recording, as
    ``sinkjax estimate`` measures them: their rim circle is found once, from
    ``frames.rim_source`` (the recording's first frames where ``frames.rim_images`` holds them,
    else the labelled frames themselves) with ``rig``'s thresholds
    (:class:`~sinkjax.soft.batch.SoftRecording`), and every frame is measured with it at every
    point, so that the loss minimised is the error of the numbers the calibrated rig will report
    (each frame's own rim where the frames show no common circle); "frame": each frame's own rim
    (a camera that moves relative to the wheel); a :class:`~sinkjax.soft.rim.RecordingRim`: that
    rim.
    ``prune``: a grid point (or a polish step) whose frames measured so far already put its loss
    above the lowest it would have to beat stops there (``compiled.loss_value``'s ``bound``):
    the same result, sooner; the checks' leave-one-out then sees only the points measured on
    every frame. False: every point on every frame.
    Raises ValueError for ``steps`` < 0, ``learning_rate`` <= 0, ``starts`` < 1,
    ``polish_measurements`` < 0 or another ``rim``.
    """
    from tqdm import tqdm

    if steps < 0 or not learning_rate > 0 or starts < 1 or polish_measurements < 0:
        raise ValueError(
            "need steps >= 0, learning_rate > 0, starts >= 1, polish_measurements >= 0; got "
            f"{steps}, {learning_rate}, {starts}, {polish_measurements}"
        )
    t0 = time.perf_counter()
    images, targets = jnp.asarray(frames.images), jnp.asarray(frames.targets)
    numbers = dict(
        rect=rig.confidence_rect,
        travel=rig.travel,
        wheel_radius_mm=rig.wheel_radius_mm,
        encoding=rig.encoding,
    )
    key = jax.random.key(seed)
    dt = jnp.result_type(float)
    raw0 = to_raw(rig.segmentation).astype(dt)
    # The loss compiles on another core while the rim is found (every rim has per_frame()'s
    # shapes), then the gradient while the grid is scored with the loss alone.
    compiling = compile_in_background(
        raw0, images, targets, key, RecordingRim.per_frame(), **numbers,
        augment_config=augment_config if augment else None, value=True, gradient=bool(steps),
    )  # fmt: skip
    held = labelled_rim(frames, rig, rim)
    if progress and compiling.loss_pending():
        height, width = frames.images.shape[1:3]
        tqdm.write(
            f"preparing the calibration loss for {width}x{height} frames (compiled once per "
            "image size, then loaded from the compile cache)"
        )
    compiling.loss_ready()

    def call(r: Array, k: PRNGKeyArray = key, **augmenting: object) -> LossAndGrad:
        return loss_and_grad(r, images, targets, k, held, **numbers, **augmenting)  # type: ignore[arg-type]

    def value(r: Array, bound: float = math.inf, given: LossAndGrad | None = None) -> LossAndGrad:
        return loss_value(
            r, images, targets, held, **numbers, bound=bound, order=order, given=given,  # type: ignore[arg-type]
        )  # fmt: skip

    # Frames whose loss was highest at the rig's own point first (rescore.score_pruned).
    order: list[int] | None = None
    exact = max(N_RELAXED, starts, 2 + N_RESCORED) if prune else 0

    def noisy(r: Array, step: int) -> Array:
        k = jax.random.fold_in(key, step)
        return call(r, k, use_augment=True, config=augment_config).grad

    first = value(raw0)
    order = [int(i) for i in np.argsort(-np.asarray(first.frames.loss), kind="stable")]
    points: list[tuple[Array, LossAndGrad]] = [(raw0, first)]

    base = rig.segmentation.as_dict()
    # Each value as SegmentationParams holds it (in the default float dtype), without a JAX
    # call per point.
    held_as = {k: [float(np.asarray(v, dt)) for v in vs] for k, vs in (grid or {}).items()}
    raws = [
        jnp.asarray(raw_values({**base, **dict(zip(held_as, c, strict=True))}), dt)
        for c in itertools.product(*held_as.values())
    ]
    # The grid's frames as measured (at most every point on every frame; pruning stops some).
    n_frames = int(images.shape[0])
    grid_total = (len(raws) + (N_RELAXED if grid else 0)) * n_frames
    grid_bar = tqdm(total=grid_total, desc="grid", unit="frame", disable=not progress or not raws)

    grid_done = [0]  # a disabled bar counts nothing

    def grid_advance(k: int) -> None:
        grid_bar.update(k)
        grid_done[0] += k
        if on_stage is not None:
            on_stage("grid", grid_done[0], grid_total)

    counted = FrameCounter(value, grid_advance)
    points += score_pruned(points, raws, counted, exact)
    n_grid = len(points)
    if grid:
        best = _distinct_lowest(points, range(n_grid), N_RELAXED)
        relaxed = float(to_raw(SegmentationParams(veto_fraction=jnp.asarray(VETO_RELAXED)))[6])
        loosened = [points[i][0].at[6].set(relaxed) for i in best]
        points += score_pruned(points, loosened, counted, exact)
        n_grid = len(points)
    grid_bar.total = grid_done[0]  # points that could not be among the lowest stopped early
    grid_bar.close()
    if on_stage is not None and raws:
        on_stage("grid", grid_done[0], grid_done[0])
    chosen = _distinct_lowest(points, range(n_grid), starts) if grid else [0]
    probe = steps if len(chosen) == 1 else steps // (2 * len(chosen))
    bar = tqdm(total=steps, desc="calibrate", unit="step", disable=not progress)
    counter = [0]
    aug = noisy if augment else None
    compiling.join()
    # Grid points (and the start) were scored without the gradient: the descents take it, the
    # first alone (it may still have to be traced); then the probes run side by side, and
    # report their steps in order (one probe's, then the next's).
    begin = [points[i] for i in chosen]
    if steps:
        raws0 = [r for r, _ in begin]
        begin = list(zip(raws0, side_by_side(call, raws0), strict=True))

    def stepped(loss: float, first: bool) -> None:
        if callback is not None:
            callback(counter[0], loss)
        counter[0] += 1
        bar.update(0 if first else 1)  # the first loss is the start's, not a step

    relay = InOrder(stepped, len(chosen))

    def probe_from(k: int, start: tuple[Array, LossAndGrad]) -> _Descent:
        try:
            return _descend(call, *start, probe, learning_rate, patience, aug, relay.channel(k))
        finally:
            relay.close(k)

    runs = side_by_side(probe_from, range(len(chosen)), begin, compiled=True)
    for d in runs:
        points += d.trail
    last = min(runs, key=lambda d: float(d.out.loss))
    if len(chosen) > 1 and steps - probe * len(chosen) > 0:
        rest = steps - probe * len(chosen)
        relay = InOrder(stepped, 1)
        last = _descend(
            call, last.raw, last.out, rest, learning_rate, patience, aug, relay.channel(0)
        )
        points += last.trail
    bar.close()
    i_best = min(range(len(points)), key=lambda i: float(points[i][1].loss))
    found = functools.cache(
        lambda key: labelled_rim(frames, _with(rig, jnp.asarray(key)), "recording")
    )
    rim_of = lambda r: found(tuple(np.asarray(r).tolist()))  # each point's own rim, found once
    if rim == "recording":
        i_best, measured = _as_estimate_measures(
            points, i_best, n_grid,
            lambda r, h: loss_value(r, images, targets, h, **numbers),  # type: ignore[arg-type]
            rim_of, held,
        )  # fmt: skip
    if rim != "recording":
        measured = set(range(n_grid))
    polished = None
    if steps and polish_measurements:
        own = rim == "recording"
        bar = tqdm(total=polish_measurements, desc="polish", unit="pt", disable=not progress)
        i_best, polished = polish_best(
            points,
            i_best,
            lambda r, b: (
                loss_value(r, images, targets, rim_of(r), **numbers, bound=b, order=order)  # type: ignore[arg-type]
                if own
                else value(r, b)
            ),
            polish_measurements,
            PolishProgress(bar, on_stage, polish_measurements),
        )
        bar.close()
    raw_best, out_best = points[i_best]
    whole = [i for i, (_, o) in enumerate(points) if complete(o) or i == i_best]
    calibrated = _with(rig, raw_best)
    # The best grid point as it will be measured (the start's rim where none was scored again).
    on_grid = [float(points[i][1].loss) for i in range(1, n_grid) if i in measured] or [
        float(points[i][1].loss) for i in range(1, n_grid)
    ]
    grid_best = min(on_grid) if grid and on_grid else math.nan
    return CalibrationResult(
        rig=calibrated,
        losses=tuple(last.losses),
        best_step=int(np.argmin(last.losses)),
        before=_errors(first, frames.targets),
        after=_errors(out_best, frames.targets),
        seconds=time.perf_counter() - t0,
        loss_before=float(first.loss),
        after_loss=float(out_best.loss),
        grid_best_loss=grid_best,
        polished=polished,
        # From the points measured on every frame (the chosen one is).
        checks=run_checks(
            [np.asarray(points[i][1].frames.loss) for i in whole],
            [np.asarray(points[i][1].frames.values) for i in whole],
            [np.asarray(points[i][1].frames.status) for i in whole],
            whole.index(i_best),
            frames,
            last.losses,
            last.stopped_early,
        ),
        rim=(rim_of(raw_best) if rim == "recording" else held).describe(),
    )


def labelled_rim(frames: LabelledFrames, rig: Rig, rim: str | RecordingRim) -> RecordingRim:
    """The rim circle the labelled frames are measured with (see :func:`calibrate`)."""
    if isinstance(rim, RecordingRim):
        return rim
    if rim == "frame":
        return RecordingRim.per_frame()
    if rim != "recording":
        raise ValueError(f"rim must be 'recording', 'frame' or a RecordingRim, got {rim!r}")
    return SoftRecording().find_rim([np.asarray(im) for im in frames.rim_source], rig)


def _errors(out: LossAndGrad, targets: np.ndarray) -> Errors:
    return Errors.of(np.asarray(out.frames.values), np.asarray(out.frames.status), targets)
