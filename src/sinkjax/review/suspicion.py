"""Which frames to look at first: a score and the reasons, from the results alone.

A reviewer has minutes, not hours, so the frame list opens with the frames most likely wrong:
failed frames, then frames whose uncertainty is unusually large, whose rim circle moved (the
camera is fixed to the wheel, conventions §1, so within one recording the rim should not move),
or whose value jumps away from its neighbours' (sinkage and angles change smoothly as the wheel
rolls). Statistics are robust (medians, MAD) and taken within each recording.
"""

from __future__ import annotations

import itertools
import statistics
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from ..result import FrameResult
from ..status import Status

FAILED_SCORE = 100.0
NO_CONTACT_SCORE = 1.0
SIGMA_Z = 3.0  # robust deviations above the median (at least 3.25x the median sigma) is large
RIM_TOLERANCE_PX = 2.0  # or 1 % of the radius, whichever is larger
NEIGHBOUR_Z = 4.0  # a value this many robust steps away from its neighbours' median jumps
NEIGHBOURS = 3  # measured frames on each side (a median of 3+ shrugs off one outlier)
# Floors of the robust scales (mm or degrees): a perfectly smooth series must not make
# a tenth of a millimetre look like a jump.
SCALE_FLOOR = 1.0
_MAD = 1.4826  # MAD -> standard deviation for normal data
_VALUES = (("sinkage_mm", "z0", "mm"), ("theta1_deg", "θ1", "°"), ("theta2_deg", "θ2", "°"))
_SIGMAS = (("sinkage_std_mm", "σ z0"), ("theta1_std_deg", "σ θ1"), ("theta2_std_deg", "σ θ2"))


@dataclass
class Suspicion:
    """How suspicious a frame looks (0 = nothing noticed) and why, in words."""

    score: float = 0.0
    reasons: list[str] = field(default_factory=list)

    def add(self, score: float, reason: str) -> None:
        self.score += score
        self.reasons.append(reason)

    def as_json(self) -> dict[str, Any]:
        return {"suspicion": round(self.score, 3), "reasons": self.reasons}


def _measured(r: FrameResult | None) -> bool:
    return r is not None and r.status == Status.OK


def suspicion(results: Sequence[FrameResult | None], groups: Sequence[int]) -> list[Suspicion]:
    """One :class:`Suspicion` per frame. ``groups[i]`` is frame i's recording; frames of one
    recording are in time order. Unmeasured frames (None) score 0."""
    out = [Suspicion() for _ in results]
    for i, r in enumerate(results):
        if r is None:
            continue
        if r.status == Status.NO_CONTACT:
            out[i].add(NO_CONTACT_SCORE, "no contact")
        elif r.status != Status.OK:
            out[i].add(FAILED_SCORE, f"{r.status}: {r.message}" if r.message else r.status)
    for group in sorted(set(groups)):
        members = [i for i, g in enumerate(groups) if g == group]
        _large_sigma(results, members, out)
        _rim_jumps(results, members, out)
        _far_from_neighbours(results, members, out)
    return out


def _robust(values: Sequence[float]) -> tuple[float, float]:
    med = statistics.median(values)
    return med, _MAD * statistics.median(abs(v - med) for v in values)


def _large_sigma(results: Sequence[FrameResult | None], members: list[int], out: list) -> None:
    for column, name in _SIGMAS:
        have = [i for i in members if _measured(results[i]) and getattr(results[i], column)]
        if len(have) < 3:
            continue
        sigmas = [float(getattr(results[i], column)) for i in have]
        med, spread = _robust(sigmas)
        scale = max(spread, 0.75 * med, 1e-9)
        for i, s in zip(have, sigmas, strict=True):
            z = (s - med) / scale
            if z > SIGMA_Z:
                out[i].add(z, f"large {name}: {s:.3g} (median {med:.3g})")


def _rim_jumps(results: Sequence[FrameResult | None], members: list[int], out: list) -> None:
    have = [
        i
        for i in members
        if results[i] is not None and results[i].radius_px is not None  # type: ignore[union-attr]
    ]
    if len(have) < 3:
        return
    rims = [(results[i].center_x_px, results[i].center_y_px, results[i].radius_px) for i in have]  # type: ignore[union-attr]
    mx, my, mr = (statistics.median(float(c[j]) for c in rims) for j in range(3))  # type: ignore[arg-type]
    tol = max(RIM_TOLERANCE_PX, 0.01 * mr)
    for i, (cx, cy, r) in zip(have, rims, strict=True):
        moved = max(((cx - mx) ** 2 + (cy - my) ** 2) ** 0.5, abs(r - mr))  # type: ignore[operator]
        if moved > tol:
            out[i].add(moved / tol, f"rim jumps {moved:.1f} px from the recording's usual rim")


def _far_from_neighbours(
    results: Sequence[FrameResult | None], members: list[int], out: list
) -> None:
    have = [i for i in members if _measured(results[i])]
    for column, name, unit in _VALUES:
        series = [(i, getattr(results[i], column)) for i in have]
        series = [(i, float(v)) for i, v in series if v is not None]
        if len(series) < 3:
            continue
        steps = [abs(b[1] - a[1]) for a, b in itertools.pairwise(series)]
        scale = max(_MAD * statistics.median(steps), SCALE_FLOOR)
        for j, (i, v) in enumerate(series):
            near = series[max(0, j - NEIGHBOURS) : j] + series[j + 1 : j + 1 + NEIGHBOURS]
            ref = statistics.median(n for _, n in near)
            z = abs(v - ref) / scale
            if z > NEIGHBOUR_Z:
                out[i].add(z, f"{name} {v:.1f} {unit} far from its neighbours' {ref:.1f} {unit}")
