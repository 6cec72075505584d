"""Choosing calibration's points: distinct starts; the result as `sinkjax estimate` measures it.

Every point calibration scores is measured with the rim circle the starting rig finds in the
labelled frames; the calibrated rig will be measured with the rim its own thresholds find. These
helpers of :func:`sinkjax.calibration.optimise.calibrate` pick the starts (one of each loss) and
score the final candidates again with their own rims.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
from jaxtyping import Array

from ..soft.rim import RecordingRim
from .loss import LossAndGrad

# After the descents the grid points are scored again, lowest first, as ``sinkjax estimate``
# measures them (with the rim each finds itself) beside the descents' best, until the next one's
# loss is above the best so far, at most this many.
N_RESCORED = 6
TIE = 1e-4  # points whose losses agree this closely (relative) are taken to be one mask


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
