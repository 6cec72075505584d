"""Checks on a finished calibration: did it converge, do the labelled frames agree, and how well
does it do on a frame it did not choose with (leave-one-out)? And the result they are reported
in (:class:`CalibrationResult`).

All three are computed from what the optimiser already evaluated (every grid point and every
Adam step keeps each frame's loss and values), so they cost no extra pass through the estimator:

- **convergence**: the last descent either stopped because the loss had not improved for
  ``patience`` steps, or it ran out of steps; then it converged only if its best loss improved
  by less than :data:`CONVERGED_REL` over the last :data:`TAIL_STEPS` steps;
- **disagreeing frames**: at the calibrated point, a frame whose loss per labelled value is far
  above the others' (over :data:`DISAGREE_FACTOR` times their median and more than
  :data:`DISAGREE_MIN` above it) is named: its labels and the rest cannot all be right with one
  set of thresholds (a mislabelled frame, or one with different lighting);
- **leave-one-out**: for each labelled frame, the point (among all evaluated) with the lowest
  loss on the OTHER frames, and this frame's error there. The Adam points were pulled by every
  frame's gradient, so for them this is a little optimistic; the grid points are honest. Above
  :data:`LOO_USABLE_REL` the summary warns that the rig should not be trusted.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..rig import Rig
from ..status import Status
from .labels import LabelledFrames

CONVERGED_REL = 0.01
TAIL_STEPS = 5
DISAGREE_FACTOR = 5.0
DISAGREE_MIN = 2.0  # loss per value: pseudo-Huber of ~2.8 mm or degrees
# Above this leave-one-out median relative sinkage error the summary warns that the calibrated
# thresholds do not carry to frames they were not chosen with (the paper's own method reaches
# about 10 % on its footage).
LOO_USABLE_REL = 0.10


@dataclasses.dataclass(frozen=True)
class Errors:
    """Median absolute errors over measured cells; a frame that is not ok counts as zeros."""

    sinkage_mm: float
    theta1_deg: float
    theta2_deg: float
    sinkage_rel: float  # median of |error| / measured sinkage over frames measured > 0
    n_ok: int
    n_frames: int

    @classmethod
    def of(cls, values: np.ndarray, status: np.ndarray, targets: np.ndarray) -> Errors:
        """``values`` and ``targets`` (N, 3) in mm/deg/deg (NaN target = not measured)."""
        ok = (np.asarray(status) == Status.OK.code)[:, None] & np.isfinite(values)
        err = np.abs(np.where(ok, values, 0.0) - targets)
        med = [
            float(np.median(e[np.isfinite(e)])) if np.isfinite(e).any() else math.nan for e in err.T
        ]
        pos = np.nan_to_num(targets[:, 0]) > 0
        rel = float(np.median(err[pos, 0] / targets[pos, 0])) if pos.any() else math.nan
        return cls(med[0], med[1], med[2], rel, int(np.sum(ok[:, 0])), len(values))

    def line(self) -> str:
        return (
            f"sinkage {self.sinkage_mm:.2f} mm ({100 * self.sinkage_rel:.1f} %), theta1 "
            f"{self.theta1_deg:.2f} deg, theta2 {self.theta2_deg:.2f} deg; "
            f"{self.n_ok}/{self.n_frames} frames ok"
        )


@dataclasses.dataclass(frozen=True)
class Checks:
    """Convergence, disagreeing frames ``(name, loss per value, median of the others)`` and the
    leave-one-out errors: per frame ``(name, |z0 error| mm, relative, |theta1|, |theta2| deg,
    status ok)``, with NaN for cells not labelled."""

    converged: bool
    convergence: str
    disagreeing: tuple[tuple[str, float, float], ...]
    loo: tuple[tuple[str, float, float, float, float, bool], ...]

    @property
    def loo_median_rel(self) -> float:
        rel = [r[2] for r in self.loo if math.isfinite(r[2])]
        return float(np.median(rel)) if rel else math.nan

    @property
    def loo_failed(self) -> int:
        return sum(not r[5] for r in self.loo)

    def lines(self, grid_best_loss: float = math.nan, loss_after: float = math.nan) -> list[str]:
        out = [self.convergence]
        if math.isfinite(grid_best_loss) and not loss_after > grid_best_loss:
            out.append(f"best grid point's loss {grid_best_loss:.4g} (the result is not above)")
        elif math.isfinite(grid_best_loss):
            out.append(
                f"best grid point's loss {grid_best_loss:.4g}, below the result's "
                f"{loss_after:.4g}: the result is not the best point seen"
            )
        for name, loss, others in self.disagreeing:
            out.append(
                f"frame {name} disagrees with the others: loss {loss:.3g} per value vs a median "
                f"of {others:.3g}; check its labels (or its lighting is unlike the others')"
            )
        out.append(
            f"leave-one-out (each frame measured at the thresholds the others choose): median "
            f"sinkage error {100 * self.loo_median_rel:.1f} %, {self.loo_failed} of "
            f"{len(self.loo)} frames not ok"
        )
        if self.loo_median_rel > LOO_USABLE_REL:
            out.append(
                f"WARNING: on frames they were not chosen with, these thresholds miss the "
                f"sinkage by a median {100 * self.loo_median_rel:.0f} %: they cannot tell wheel "
                "from soil on this footage, and its frames measured with this rig may be "
                "reported ok yet be wrong. Label more frames, or train a learned segmenter "
                "(sinkjax train)"
            )
        return out


def run_checks(
    frame_losses: list[np.ndarray],
    frame_values: list[np.ndarray],
    frame_status: list[np.ndarray],
    i_best: int,
    frames: LabelledFrames,
    last_losses: list[float],
    stopped_early: bool,
) -> Checks:
    """The checks, from every evaluated point's per-frame losses (N,), values (N, 3) (mm, deg,
    deg) and status codes (N,); ``i_best`` is the calibrated point's index."""
    targets = np.asarray(frames.targets, float)
    cells = np.maximum(np.isfinite(targets).sum(1), 1)
    losses = np.stack(frame_losses)  # (P, N)
    if len(last_losses) <= 1:
        converged, note = True, "the grid search alone (no descent: --steps 0)"
    elif stopped_early:
        converged, note = True, "converged: no better loss for the last steps"
    else:
        best = np.minimum.accumulate(np.asarray(last_losses, float))
        tail = best[-1 - min(TAIL_STEPS, len(best) - 1)]
        gain = (tail - best[-1]) / max(abs(tail), 1e-12)
        converged = bool(gain < CONVERGED_REL)
        note = (
            f"converged: the loss fell {100 * gain:.1f} % over the last {TAIL_STEPS} steps"
            if converged
            else f"NOT converged: the loss still fell {100 * gain:.1f} % over the last "
            f"{TAIL_STEPS} steps; run again with more --steps"
        )
    per_value = losses[i_best] / cells
    disagreeing = []
    for i, name in enumerate(frames.names):
        others = float(np.median(np.delete(per_value, i))) if len(per_value) > 1 else math.nan
        if per_value[i] > max(DISAGREE_FACTOR * others, others + DISAGREE_MIN):
            disagreeing.append((name, float(per_value[i]), others))
    loo = []
    total = losses.sum(1)
    for i, name in enumerate(frames.names):
        others = (total - losses[:, i]) / max(int(cells.sum() - cells[i]), 1)
        j = int(np.argmin(others))
        v, t = np.asarray(frame_values[j][i], float), targets[i]
        ok = int(frame_status[j][i]) == Status.OK.code
        err = np.abs(np.where(ok, v, 0.0) - t)
        rel = err[0] / t[0] if np.isfinite(t[0]) and t[0] > 0 else math.nan
        loo.append((name, float(err[0]), float(rel), float(err[1]), float(err[2]), ok))
    return Checks(converged, note, tuple(disagreeing), tuple(loo))


@dataclasses.dataclass(frozen=True)
class CalibrationResult:
    """The calibrated rig, the losses, and the labelled frames' errors before and after.

    ``losses`` is the loss at every Adam step (``losses[0]`` that of the rig's own thresholds);
    the calibrated rig is the one of step ``best_step``.
    """

    rig: Rig
    losses: tuple[float, ...]
    best_step: int
    before: Errors
    after: Errors
    seconds: float
    loss_before: float = math.nan  # the rig's own thresholds
    after_loss: float = math.nan
    grid_best_loss: float = math.nan  # the best grid point's (NaN without a grid)
    polished: tuple[float, float, int] | None = None  # the polish's loss from, to; measurements
    checks: Checks | None = None
    rim: str = "per-frame rim"  # what the labelled frames were measured with, in words

    @property
    def loss_after(self) -> float:
        """The calibrated rig's loss (the lowest seen anywhere, grid points included)."""
        return self.after_loss

    def summary(self) -> str:
        params = ", ".join(f"{k} = {v:.4g}" for k, v in self.rig.segmentation.as_dict().items())
        return "\n".join(
            [
                f"loss {self.loss_before:.4g} -> {self.loss_after:.4g} (best at step "
                f"{self.best_step} of {len(self.losses) - 1}; {self.seconds:.0f} s)",
                f"median |error| before: {self.before.line()}",
                f"median |error| after:  {self.after.line()}",
                f"labelled frames measured with the {self.rim}",
                *(
                    []
                    if self.polished is None
                    else [
                        f"polish (each point measured with the rim it finds): loss "
                        f"{self.polished[0]:.4g} -> {self.polished[1]:.4g} in "
                        f"{self.polished[2]} measurements"
                    ]
                ),
                f"[segmentation] {params}",
                *(
                    []
                    if self.checks is None
                    else self.checks.lines(self.grid_best_loss, self.after_loss)
                ),
            ]
        )
