"""Calibration optimiser: Adam on the raw thresholds, with back-off, early stop and a report.

The loss is piecewise smooth (a frame stops measuring when a threshold crosses a point), so the
loop keeps the best point seen, goes back there with a smaller step when a step lands where
frames fail, and stops once the loss has not improved for a while.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, PRNGKeyArray

from ..rig import Rig, SegmentationParams
from ..status import Status
from .augment import DEFAULT_CONFIG, AugmentConfig
from .labels import LabelledFrames
from .loss import LossAndGrad, from_raw, loss_and_grad, to_raw

BACKTRACK = 2.0  # a loss above this times the best so far sends Adam back to the best point
_OK = Status.OK.code


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
        ok = (np.asarray(status) == _OK)[:, None] & np.isfinite(values)
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

    @property
    def loss_before(self) -> float:
        return self.losses[0]

    @property
    def loss_after(self) -> float:
        return self.losses[self.best_step]

    def summary(self) -> str:
        params = ", ".join(f"{k} = {v:.4g}" for k, v in self.rig.segmentation.as_dict().items())
        return "\n".join(
            [
                f"loss {self.loss_before:.4g} -> {self.loss_after:.4g} (best at step "
                f"{self.best_step} of {len(self.losses) - 1}; {self.seconds:.0f} s)",
                f"median |error| before: {self.before.line()}",
                f"median |error| after:  {self.after.line()}",
                f"[segmentation] {params}",
            ]
        )


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
) -> CalibrationResult:
    """Tune ``rig.segmentation`` to labelled frames with Adam; returns the calibrated rig.

    Deterministic (``seed`` only drives the augmentations). Keeps the parameters with the lowest
    loss on the frames as labelled (measured at every step, also under ``augment``); a step that
    more than doubles it (frames stopped measuring) goes back there with half the step size;
    stops after ``patience`` steps without a better loss. With ``augment`` each step's gradient
    averages the frames as labelled and under a random lighting change. Raises ValueError for
    ``steps`` < 0 or ``learning_rate`` <= 0.
    """
    from tqdm import tqdm

    if steps < 0 or not learning_rate > 0:
        raise ValueError(f"need steps >= 0 and learning_rate > 0, got {steps}, {learning_rate}")
    t0 = time.perf_counter()
    images, targets = jnp.asarray(frames.images), jnp.asarray(frames.targets)
    static = dict(
        rect=rig.confidence_rect, travel=rig.travel, wheel_radius_mm=float(rig.wheel_radius_mm)
    )
    key = jax.random.key(seed)

    def call(r: Array, k: PRNGKeyArray = key, **augmenting: object) -> LossAndGrad:
        # Positional arrays, keyword statics: one compiled function for every caller.
        return loss_and_grad(r, images, targets, k, **static, **augmenting)  # type: ignore[arg-type]

    dt = jnp.result_type(float)
    raw = to_raw(rig.segmentation).astype(dt)
    first = out = call(raw)
    opt = optax.adam(optax.cosine_decay_schedule(learning_rate, max(steps, 1), alpha=0.1))
    state = opt.init(raw)
    scale = 1.0
    losses: list[float] = []
    best = (0, raw, out)
    bar = tqdm(total=steps, desc="calibrate", unit="step", disable=not progress)
    for step in range(steps + 1):
        if step > 0:
            out = call(raw)
        losses.append(float(out.loss))
        if losses[-1] < losses[best[0]]:
            best = (step, raw, out)
        if callback is not None:
            callback(step, losses[-1])
        if step == steps or step - best[0] >= patience:
            break
        if losses[-1] > BACKTRACK * losses[best[0]]:
            # The loss is piecewise smooth: a step landed where frames stop measuring. Go back
            # to the best point, forget the momentum that carried us here, take smaller steps.
            _, raw, out = best
            with jax.numpy_dtype_promotion("standard"):
                state = opt.init(raw)
            scale = 0.5 * scale
        grad = out.grad
        if augment:
            noisy = call(
                raw, jax.random.fold_in(key, step), use_augment=True, config=augment_config
            )
            grad = 0.5 * (grad + noisy.grad)
        # optax's schedules mix Python floats with int32 step counts: allow that promotion
        # here even where the user runs JAX with strict dtype promotion.
        with jax.numpy_dtype_promotion("standard"):
            updates, state = opt.update(grad, state, raw)
        raw = raw + scale * updates
        bar.set_postfix(loss=f"{losses[-1]:.4g}", best=f"{losses[best[0]]:.4g}")
        bar.update()
    bar.close()
    step_best, raw_best, out_best = best
    calibrated = Rig(
        wheel_radius_mm=rig.wheel_radius_mm,
        confidence_rect=rig.confidence_rect,
        travel=rig.travel,
        segmentation=_python_floats(from_raw(raw_best)),
    )
    return CalibrationResult(
        rig=calibrated,
        losses=tuple(losses),
        best_step=step_best,
        before=_errors(first, frames.targets),
        after=_errors(out_best, frames.targets),
        seconds=time.perf_counter() - t0,
    )


def _errors(out: LossAndGrad, targets: np.ndarray) -> Errors:
    return Errors.of(np.asarray(out.frames.values), np.asarray(out.frames.status), targets)


def _python_floats(seg: SegmentationParams) -> SegmentationParams:
    # Plain floats: the rig file then holds exactly what was measured with (round trip).
    values: dict[str, Any] = seg.as_dict()
    return SegmentationParams(**values)
