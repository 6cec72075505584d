"""Choosing calibration's points: distinct starts; the result as `sinkjax estimate` measures it.

Every point calibration scores is measured with the rim circle the starting rig finds in the
labelled frames; the calibrated rig will be measured with the rim its own thresholds find. These
helpers of :func:`sinkjax.calibration.optimise.calibrate` pick the starts (one of each loss),
score the final candidates again with their own rims, and polish the result by a compass search
in which every candidate is measured with its own rim (:func:`polish`); :class:`FrameCounter`
and :class:`PolishProgress` report the grid's and the polish's progress.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from collections.abc import Callable
from typing import Any

import jax
import numpy as np
from jaxtyping import Array

from ..rig import Rig, SegmentationParams
from ..soft.rim import RecordingRim
from ..xla import side_by_side
from .loss import LossAndGrad, from_raw

# After the descents the grid points are scored again, lowest first, as ``sinkjax estimate``
# measures them (with the rim each finds itself) beside the descents' best, until the next one's
# loss is above the best so far, at most this many.
N_RESCORED = 6
# Points completed together (each with the bound of the points completed before them): the
# same points on any machine, side by side where it has the cores (sinkjax.xla.side_by_side).
SIDE_BY_SIDE = 2
TIE = 1e-4  # points whose losses agree this closely (relative) are taken to be one mask
# The polish: a compass search over the raw thresholds a grid search spans (P_d(H), P_a(H),
# P_d(S), P_a(S); see ``loss.RAW_NAMES``), from steps of POLISH_STEP raw units (about half the
# grid's spacing: logit(0.9) - logit(0.8) = 0.8) down to POLISH_MIN_STEP, in at most
# POLISH_MEASUREMENTS measurements (~0.7 s each for 6 frames at 640x480).
POLISH_COORDS = (0, 1, 2, 3)
POLISH_STEP = 0.5
POLISH_MIN_STEP = 0.125
POLISH_MEASUREMENTS = 32


def _distinct_lowest(points: list[tuple[Array, LossAndGrad]], indices: range, k: int) -> list[int]:
    """The ``k`` lowest of ``points[indices]``, one of each loss: grid points tie where a
    threshold changes nothing (no pixel near P_a(S), say), and three starts of one mask would be
    one start."""
    chosen: list[int] = []
    for i in sorted(indices, key=lambda i: float(points[i][1].loss)):
        loss = float(points[i][1].loss)
        if not any(math.isclose(loss, float(points[j][1].loss), rel_tol=TIE) for j in chosen):
            chosen.append(i)
        if len(chosen) == k:
            break
    return chosen


class FrameCounter:
    """``value`` (a point's loss, frame by frame: ``compiled.loss_value``), calling ``advance``
    with the number of frames each call measured; safe to call from the threads that score
    points side by side."""

    def __init__(self, value: Callable[..., LossAndGrad], advance: Callable[[int], object]) -> None:
        self._value, self._advance, self._lock = value, advance, threading.Lock()

    def __call__(
        self, raw: Array, bound: float = math.inf, given: LossAndGrad | None = None
    ) -> LossAndGrad:
        out = self._value(raw, bound, given)
        new = _measured(out) - (0 if given is None else _measured(given))
        with self._lock:
            self._advance(new)
        return out


class PolishProgress:
    """Called once per polish measurement: advances ``bar`` and reports ("polish", done,
    ``total``) to ``on_stage``."""

    def __init__(
        self, bar: Any, on_stage: Callable[[str, int, int], None] | None, total: int
    ) -> None:
        self._bar, self._on_stage, self._total, self._done = bar, on_stage, total, 0

    def __call__(self, _: object) -> None:
        self._bar.update()
        self._done += 1  # a disabled bar counts nothing
        if self._on_stage is not None:
            self._on_stage("polish", self._done, self._total)


class InOrder:
    """Reports from ``n`` channels fed side by side on threads, passed on to ``report(value,
    first)`` one channel after another (channel 0's, then 1's, ...; a later channel's are
    held until the earlier ones are closed): the descents run side by side, and report their
    steps as one after another would. ``first``: the channel's first value."""

    def __init__(self, report: Callable[[float, bool], None], n: int) -> None:
        self._report, self._n, self._lock = report, n, threading.Lock()
        self._held: list[list[float]] = [[] for _ in range(n)]
        self._seen, self._closed, self._open = [0] * n, [False] * n, 0

    def channel(self, k: int) -> Callable[[float], None]:
        return lambda value: self._feed(k, value)

    def _feed(self, k: int, value: float) -> None:
        with self._lock:
            if k == self._open:
                self._pass(k, value)
            else:
                self._held[k].append(value)

    def _pass(self, k: int, value: float) -> None:
        self._report(value, not self._seen[k])
        self._seen[k] += 1

    def close(self, k: int) -> None:
        with self._lock:
            self._closed[k] = True
            while self._open < self._n and self._closed[self._open]:
                self._open += 1
                if self._open < self._n:
                    for value in self._held[self._open]:
                        self._pass(self._open, value)
                    self._held[self._open].clear()


def _measured(out: LossAndGrad) -> int:
    return int(np.sum(np.asarray(out.frames.status) >= 0))


def score_pruned(
    points: list[tuple[Array, LossAndGrad]],
    raws: list[Array],
    value: Callable[[Array, float, LossAndGrad | None], LossAndGrad],
    exact: int,
) -> list[tuple[Array, LossAndGrad]]:
    """``raws`` scored by ``value(raw, bound, given)`` (``compiled.loss_value``: frames one by
    one, stopping once the loss is above ``bound``, resuming ``given``), in their order, where
    only the ``exact`` lowest (one of each loss, :func:`_distinct_lowest`) among them and
    ``points`` are needed exactly. Each is measured on the first frame (a bound of -inf), then
    completed lowest first, :data:`SIDE_BY_SIDE` at a time, each with the bound the points
    completed before them set: the lowest ``exact`` value. A point above it cannot be among
    them, whatever its other frames measure, and stops there (a lower bound above the bound
    stands for its loss). ``exact`` 0: every point on every frame. Points are measured side by
    side on a CPU's cores (:func:`~sinkjax.xla.side_by_side`; ``value`` has run before, so
    each pair runs together); which are completed does not depend on how many cores there are."""
    if not exact:
        outs = side_by_side(lambda r: value(r, math.inf, None), raws, compiled=True)
        return list(zip(raws, outs, strict=True))
    firsts = side_by_side(lambda r: value(r, -math.inf, None), raws, compiled=True)
    scored: dict[int, LossAndGrad] = {}
    order = sorted(range(len(raws)), key=lambda j: float(firsts[j].loss))
    for pair in (order[k : k + SIDE_BY_SIDE] for k in range(0, len(order), SIDE_BY_SIDE)):
        done = points + [(raws[k], o) for k, o in scored.items()]
        lowest = _distinct_lowest(done, range(len(done)), exact)
        bound = float(done[lowest[-1]][1].loss) if len(lowest) == exact else math.inf
        outs = side_by_side(lambda j, b=bound: value(raws[j], b, firsts[j]), pair, compiled=True)
        scored.update(zip(pair, outs, strict=True))
    return [(r, scored[j]) for j, r in enumerate(raws)]


def _as_estimate_measures(
    points: list[tuple[Array, LossAndGrad]],
    i_best: int,
    n_grid: int,
    loss_with: Callable[[Array, RecordingRim], LossAndGrad],
    rim_of: Callable[[Array], RecordingRim],
    held: RecordingRim,
) -> tuple[int, set[int]]:
    """The point to return, scored as ``sinkjax estimate`` will measure it.

    Every point was scored with the rim the starting rig finds in the labelled frames; a rig
    with other thresholds finds its own rim there, or none (its masks may suit the boundary yet
    hide the rim: rendered hard_cast, the lowest point scored below the grid's 0.21 with the
    start's rim and 35 with its own, every frame failed). So the lowest point, the start and
    the grid points, lowest first, are scored again with the rim each finds itself (in place, in
    ``points``), the grid points until the next one's loss is above the best so far (at most
    :data:`N_RESCORED`). Returns the index of the lowest of those (never worse than the grid's
    best, as the calibrated rig will be used) and the indices scored so."""
    grid_order = sorted(range(n_grid), key=lambda i: float(points[i][1].loss))
    chosen, best = i_best, math.inf
    measured: set[int] = set()

    def rescore(i: int) -> None:
        nonlocal chosen, best
        measured.add(i)
        raw = points[i][0]
        own = rim_of(raw)
        same = all(
            bool(a == b) for a, b in zip(jax.tree.leaves(own), jax.tree.leaves(held), strict=True)
        )
        if not same:
            points[i] = (raw, loss_with(raw, own))
        if float(points[i][1].loss) < best:
            chosen, best = i, float(points[i][1].loss)

    held_losses = [float(points[i][1].loss) for i in (i_best, 0)]
    for i in dict.fromkeys((i_best, 0)):
        rescore(i)
    for i in [g for g in grid_order if g not in (i_best, 0)]:
        loss = float(points[i][1].loss)
        if loss > best or len(held_losses) >= 2 + N_RESCORED:
            break
        # Grid points tie where a threshold changes nothing (no pixel near P_a(S), say): one
        # of each loss is scored again.
        if not any(math.isclose(loss, h, rel_tol=TIE) for h in held_losses):
            held_losses.append(loss)
            rescore(i)
    return chosen, measured


def polish(
    raw: Array,
    out: LossAndGrad,
    score: Callable[[Array, float], LossAndGrad],
    measurements: int = POLISH_MEASUREMENTS,
    on_step: Callable[[float], None] | None = None,
) -> list[tuple[Array, LossAndGrad]]:
    """Every point a compass search from ``raw`` (loss ``out``) measured, in order.

    ``score(raw, bound)`` measures a point as ``sinkjax estimate`` will (with the rim its
    thresholds find); where its loss is above ``bound`` (the best so far: it cannot be chosen)
    it may stop early and return a lower bound above it (``compiled.loss_value``).
    The descents follow the gradient of a loss whose rim is held at the start's; a rig with other
    thresholds finds a rim a pixel larger or smaller, and with it a sinkage off by as much
    (rendered hard_lowlight, seed 20263: the start's rim 183.6 px, the grid's best points' 184.6-
    185.5, truth 184.0; the descents' best, measured with its own rim, was no better than the
    rig's own thresholds, while a 4^4 grid measured so found 0.19 against 0.26). The polish needs
    no gradient: each pass tries a step up and down each threshold of :data:`POLISH_COORDS`,
    moves to the first of the two that lowers the loss (beyond :data:`TIE`), and halves the step
    after a pass without a move, until the step falls below :data:`POLISH_MIN_STEP` or
    ``measurements`` are spent. The lowest point is never above the start.
    """
    best_raw, best = raw, float(out.loss)
    trail: list[tuple[Array, LossAndGrad]] = []
    step = POLISH_STEP
    while step >= POLISH_MIN_STEP and len(trail) < measurements:
        moved = False
        for i in POLISH_COORDS:
            if len(trail) >= measurements:
                break
            up_down = [best_raw.at[i].add(sign * step) for sign in (1.0, -1.0)]
            # Both side by side (as far as measurements are left); the step down counts only
            # where the step up does not lower the loss, as one after another, so the trail is
            # the same. Bound: the best so far, so that a point stopped early is never lowest.
            outs = side_by_side(
                lambda c, b=best: score(c, b), up_down[: measurements - len(trail)], compiled=True
            )
            for cand, o in zip(up_down, outs, strict=False):
                trail.append((cand, o))
                if on_step is not None:
                    on_step(float(o.loss))
                if float(o.loss) < best * (1.0 - TIE):
                    best_raw, best, moved = cand, float(o.loss), True
                    break  # on to the next threshold
        if not moved:
            step /= 2
    return trail


def polish_best(
    points: list[tuple[Array, LossAndGrad]],
    i_best: int,
    score: Callable[[Array, float], LossAndGrad],
    measurements: int = POLISH_MEASUREMENTS,
    on_step: Callable[[float], None] | None = None,
) -> tuple[int, tuple[float, float, int]]:
    """:func:`polish` ``points[i_best]``, appending every point it measured to ``points``;
    returns the lowest point's index and (its loss before, after, measurements)."""
    before = float(points[i_best][1].loss)
    trail = polish(points[i_best][0], points[i_best][1], score, measurements, on_step)
    points += trail
    for i in range(len(points) - len(trail), len(points)):
        if float(points[i][1].loss) < float(points[i_best][1].loss):
            i_best = i
    return i_best, (before, float(points[i_best][1].loss), len(trail))


def _with(rig: Rig, raw: Array) -> Rig:
    """``rig`` with the thresholds of the raw vector ``raw`` (every other field kept: the rim
    hint, the encoding)."""
    return dataclasses.replace(rig, segmentation=_python_floats(from_raw(raw)))


def _python_floats(seg: SegmentationParams) -> SegmentationParams:
    # Plain floats: the rig file then holds exactly what was measured with (round trip).
    values: dict[str, Any] = seg.as_dict()
    return SegmentationParams(**values)
