"""Calibration stage: tune the segmentation thresholds to a few hand-labelled frames by gradient.

The soft estimator is differentiable in the segmentation parameters (through the optimistix fit,
by implicit differentiation), so instead of trying P_a/P_d by hand, calibration minimises a robust
loss between the estimated and the measured z0, theta1, theta2 of labelled frames with Adam.

Parameters live in an unconstrained *raw* space that keeps them valid by construction:
``P_d = sigmoid(raw)`` in (0, 1), ``P_a = 1 + softplus(raw)`` > 1, temperatures
``scale * softplus(raw)`` > 0 (scale 1 degree of hue, 0.01 of saturation, so that one Adam step
moves every parameter by a comparable amount).

Loss of one labelled cell: pseudo-Huber of the error in units of 1 mm (sinkage) or 1 degree
(angles); empty cells are masked out; the total is the mean over measured cells. A frame whose
status is not ``ok`` counts as measuring zeros (what ``no_contact`` reports), which is flat in the
thresholds; so a frame labelled with contact that does not measure also gets a surrogate term with
a gradient: how far the soft mask is from having an edge at the labelled soil line inside the rim
(:func:`boundary_contrast`), plus a term rewarding boundary weight when the fit sees too little.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import dataclasses
import functools
import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float, Int, PRNGKeyArray, UInt8

from ..geometry import travel_sign
from ..rig import Rig, RigError, SegmentationParams, load_rig, save_rig
from ..soft import fit as _fit, model as _model
from ..soft.estimator import MIN_BOUNDARY_POINTS, measure
from ..soft.segmentation import wheel_mask
from ..status import Status
from .augment import DEFAULT_CONFIG, AugmentConfig, augment

LABEL_COLUMNS = ("image", "sinkage_mm", "theta1_deg", "theta2_deg")
QUANTITIES = LABEL_COLUMNS[1:]
LOSS_SCALES = (1.0, 1.0, 1.0)  # 1 mm of sinkage weighs as much as 1 degree of angle
HUBER_DELTA = 1.0  # pseudo-Huber corner in those units: quadratic below, linear above
# A frame labelled with contact needs this much boundary weight before the deficit term is 0.
BOUNDARY_TARGET = 4.0 * MIN_BOUNDARY_POINTS
# Surrogate for frames that do not measure: strips between STRIP_NEAR and STRIP_FAR rim radii
# above / below the labelled soil line, weighted like CONTRAST_WEIGHT mm (or deg) of error.
STRIP_NEAR, STRIP_FAR = 0.03, 0.12
CONTRAST_WEIGHT = 5.0
RAW_NAMES = ("p_d_hue", "p_a_hue", "p_d_sat", "p_a_sat", "temperature_hue_deg", "temperature_sat")
RAW_LIMIT = 12.0
BACKTRACK = 2.0  # a loss above this times the best so far sends Adam back to the best point
_TEMPERATURE_UNIT_HUE_DEG = 1.0
_TEMPERATURE_UNIT_SAT = 0.01
_OK = Status.OK.code


class LabelError(RigError):
    """LABELS.csv is unusable; the message names the row (1 = header), the column and the fix."""


# ----------------------------------------------------------------------------- labels


@dataclasses.dataclass(frozen=True)
class LabelledFrames:
    """Checked labelled frames. ``images`` uint8 (N, H, W, 3); ``targets`` (N, 3) float64 as
    (sinkage_mm, theta1_deg, theta2_deg), NaN = not measured; ``names`` the ``image`` cells."""

    images: UInt8[np.ndarray, "N H W 3"]
    targets: Float[np.ndarray, "N 3"]
    names: tuple[str, ...]


def read_labels(path: str | Path, rig: Rig | None = None) -> LabelledFrames:
    """Read, validate and load LABELS.csv (conventions §3), all before any other work.

    Image paths are relative to the CSV's folder; an empty cell means "not measured". Raises
    :class:`LabelError` naming the row and column for: missing columns, an empty, missing or
    unreadable image, a number that does not parse or is out of range, no measured cell at all,
    images of different sizes, or a confidence rectangle of ``rig`` that lies off the images.
    """
    from ..app.frames import read_image

    p = Path(path)
    if not p.is_file():
        raise LabelError(f"labels file {str(p)!r} does not exist")
    try:
        text = p.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise LabelError(f"{p}: cannot read it as UTF-8 text ({e})") from e
    reader = csv.reader(text.splitlines())
    header = [h.strip() for h in next(reader, [])]
    missing = [c for c in LABEL_COLUMNS if c not in header]
    if missing:
        raise LabelError(
            f"{p}: row 1 (header): missing column(s) {', '.join(missing)}; the header must "
            f"name {','.join(LABEL_COLUMNS)} (got {','.join(header) or 'an empty line'!r})"
        )
    col = {name: header.index(name) for name in LABEL_COLUMNS}
    names, targets, rows = [], [], []
    for row_no, row in enumerate(reader, start=2):
        if not any(cell.strip() for cell in row):
            continue
        cells = {name: (row[i].strip() if i < len(row) else "") for name, i in col.items()}
        where = f"{p}: row {row_no}, column"
        if not cells["image"]:
            raise LabelError(f"{where} image: empty; write the image file name")
        if not (p.parent / cells["image"]).is_file():
            raise LabelError(
                f"{where} image: {str(p.parent / cells['image'])!r} does not exist "
                "(image paths are relative to the folder of the labels file)"
            )
        targets.append([_parse_cell(cells[q], where, q) for q in QUANTITIES])
        names.append(cells["image"])
        rows.append(row_no)
    if not names:
        raise LabelError(f"{p}: no labelled rows after the header")
    t = np.asarray(targets, dtype=np.float64)
    if not np.isfinite(t).any():
        raise LabelError(
            f"{p}: rows {rows[0]}-{rows[-1]}, columns {', '.join(QUANTITIES)}: every cell is "
            "empty; measure at least one quantity in one frame"
        )
    images: list[np.ndarray] = []
    for row_no, name in zip(rows, names, strict=True):
        try:
            image = read_image(p.parent / name)
        except (OSError, ValueError) as e:
            reason = getattr(e, "strerror", None) or str(e)
            raise LabelError(
                f"{p}: row {row_no}, column image: cannot read {name!r}: {reason}"
            ) from e
        if images and image.shape != images[0].shape:
            raise LabelError(
                f"{p}: row {row_no}, column image: {name!r} is {image.shape[1]}x{image.shape[0]}"
                f" px but row {rows[0]} is {images[0].shape[1]}x{images[0].shape[0]} px; "
                "calibrate one camera set-up (one image size) at a time"
            )
        images.append(image)
    if rig is not None:
        x, y, w, h = rig.confidence_rect
        height, width = images[0].shape[:2]
        if x + w > width or y + h > height:
            raise LabelError(
                f"the rig's confidence_rect [{x}, {y}, {w}, {h}] lies off the {width}x{height} "
                f"images of {p}; fix confidence_rect in the rig file"
            )
    return LabelledFrames(np.stack(images), t, tuple(names))


def _parse_cell(cell: str, where: str, column: str) -> float:
    if not cell:
        return math.nan
    try:
        value = float(cell)
    except ValueError:
        raise LabelError(
            f"{where} {column}: {cell!r} is not a number; write it with '.' decimals and no "
            "unit, or leave the cell empty if it was not measured"
        ) from None
    limit = math.inf if column == "sinkage_mm" else 180.0
    if not 0.0 <= value <= limit:
        unit = "mm >= 0" if column == "sinkage_mm" else "degrees in [0, 180]"
        raise LabelError(f"{where} {column}: {cell!r} is out of range ({unit})")
    return value


# ----------------------------------------------------------------------------- parameters


def _logit(p: float) -> float:
    p = min(max(p, 1e-6), 1.0 - 1e-6)  # a rig may say P_d = 0 (no lower saturation bound)
    return math.log(p / (1.0 - p))


def _inv_softplus(y: float) -> float:
    return y + math.log(-math.expm1(-y))


def to_raw(seg: SegmentationParams) -> Float[Array, " 6"]:
    """Unconstrained raw vector (order :data:`RAW_NAMES`) of valid segmentation parameters."""
    d = seg.as_dict()
    return jnp.asarray(
        [
            _logit(d["p_d_hue"]),
            _inv_softplus(d["p_a_hue"] - 1.0),
            _logit(d["p_d_sat"]),
            _inv_softplus(d["p_a_sat"] - 1.0),
            _inv_softplus(d["temperature_hue_deg"] / _TEMPERATURE_UNIT_HUE_DEG),
            _inv_softplus(d["temperature_sat"] / _TEMPERATURE_UNIT_SAT),
        ]
    )


def from_raw(raw: Float[Array, " 6"]) -> SegmentationParams:
    """Segmentation parameters of a raw vector: always 0 < P_d < 1 < P_a, temperatures > 0.

    Raw values are clipped to +-:data:`RAW_LIMIT` so that the strict inequalities survive float32
    rounding (sigmoid(17) is 1.0 in float32) and the rig file stays valid.
    """
    raw = jnp.clip(raw, -RAW_LIMIT, RAW_LIMIT)
    return SegmentationParams(
        p_d_hue=jax.nn.sigmoid(raw[0]),
        p_a_hue=1.0 + jax.nn.softplus(raw[1]),
        p_d_sat=jax.nn.sigmoid(raw[2]),
        p_a_sat=1.0 + jax.nn.softplus(raw[3]),
        temperature_hue_deg=_TEMPERATURE_UNIT_HUE_DEG * jax.nn.softplus(raw[4]),
        temperature_sat=_TEMPERATURE_UNIT_SAT * jax.nn.softplus(raw[5]),
    )


def _python_floats(seg: SegmentationParams) -> SegmentationParams:
    # Plain floats: the rig file then holds exactly what was measured with (round trip).
    values: dict[str, Any] = seg.as_dict()
    return SegmentationParams(**values)


# ----------------------------------------------------------------------------- gradient guard


@jax.custom_jvp
def _sqrt0(x: Array) -> Array:
    return jnp.sqrt(x)


@_sqrt0.defjvp
def _sqrt0_jvp(primals: tuple[Array], tangents: tuple[Array]) -> tuple[Array, Array]:
    # Double where: d sqrt(x) = dx / (2 sqrt(x)) is inf at x = 0, and inf * 0 is NaN.
    (x,), (t,) = primals, tangents
    y = jnp.sqrt(x)
    pos = x > 0
    return y, jnp.where(pos, 0.5 * t / jnp.where(pos, y, 1.0), 0.0)


class _NumpyWithSafeSqrt:
    """``jax.numpy`` whose square root has derivative 0 instead of inf at 0 (same values)."""

    sqrt = staticmethod(_sqrt0)

    def __getattr__(self, name: str) -> object:
        return getattr(jnp, name)


_RESIDUALS = _model.residuals


def _residuals_safe(p: Array, ev: _model.Evidence) -> Array:
    saved = _model.jnp
    _model.jnp = _NumpyWithSafeSqrt()  # type: ignore[assignment]
    try:
        return _RESIDUALS(p, ev)
    finally:
        _model.jnp = saved


@functools.cache
def _residuals_need_guard() -> bool:
    """Whether the model's residuals have non-finite derivatives at points of weight 0.

    They weight each point by sqrt(w) and most points have w = 0 in most groups, so the implicit
    gradient of the fit multiplies inf by 0. The guard changes no value, only that derivative
    (inf -> 0), and only while the loss is traced; it is off once the model guards it itself.
    """
    try:
        with jax.ensure_compile_time_eval():
            return _probe_residuals()
    except Exception:  # the model changed shape: it is no longer the code this guard knows
        return False


def _probe_residuals() -> bool:
    z = jnp.zeros(3)
    ev = _model.Evidence(
        x_px=jnp.arange(3.0),
        y_px=jnp.ones(3),
        w_rim=z,
        w_line=z,
        w_a=z,
        w_b=z,
        sign=jnp.asarray(1.0),
        start=jnp.ones(_model.N_PARAMS),
    )
    p = jnp.ones(_model.N_PARAMS)
    g = jax.grad(lambda w: jnp.sum(_RESIDUALS(p, eqx.tree_at(lambda e: e.w_line, ev, w))))(z)
    return not bool(jnp.all(jnp.isfinite(g)))


@contextlib.contextmanager
def _finite_gradients() -> Iterator[None]:
    """While the loss is traced, let the fit use residuals with finite gradients at w = 0."""
    if getattr(_fit, "residuals", None) is not _RESIDUALS or not _residuals_need_guard():
        yield
        return
    _fit.residuals = _residuals_safe
    try:
        yield
    finally:
        _fit.residuals = _RESIDUALS


# ----------------------------------------------------------------------------- loss


def pseudo_huber(x: Float[Array, "*n"], delta: float = HUBER_DELTA) -> Float[Array, "*n"]:
    """``delta^2 (sqrt(1 + (x / delta)^2) - 1)``: x^2 / 2 near 0, delta |x| far out."""
    return delta * delta * (jnp.sqrt(1.0 + (x / delta) ** 2) - 1.0)


class FrameLoss(eqx.Module):
    """One frame as the loss saw it: estimates (sinkage_mm, theta1_deg, theta2_deg), status."""

    values: Float[Array, "*n 3"]
    status: Int[Array, "*n"]
    loss: Float[Array, "*n"]


def labelled_soil_side(
    u_px: Float[Array, "H W"],
    v_px: Float[Array, "H W"],
    r_px: Float[Array, ""],
    target: Float[Array, " 3"],
    wheel_radius_mm: float,
) -> Float[Array, "H W"]:
    """Signed distance (px, > 0 on the soil side) to the soil line that the labels describe.

    Wheel frame (O-centred, entry side at +u, v down). With both angles labelled it is the chord
    A B (A = r (sin theta1, cos theta1), B = r (-sin theta2, cos theta2)); otherwise the flat line
    at depth r - z0 below O. NaN where the labels do not say (no sinkage and no angles).
    """
    t1, t2 = jnp.radians(target[1]), jnp.radians(target[2])
    angles = jnp.isfinite(t1) & jnp.isfinite(t2) & (t1 + t2 > 0)
    t1, t2 = jnp.where(angles, t1, 0.5), jnp.where(angles, t2, 0.5)
    ua, va = r_px * jnp.sin(t1), r_px * jnp.cos(t1)
    ub, vb = -r_px * jnp.sin(t2), r_px * jnp.cos(t2)
    k = (va - vb) / (ua - ub)
    chord = ((v_px - va) - k * (u_px - ua)) / jnp.sqrt(1.0 + k * k)
    z0_px = target[0] * r_px / wheel_radius_mm
    flat = v_px - (r_px - z0_px)
    return jnp.where(angles, chord, flat)


def boundary_contrast(
    mask: Float[Array, "H W"],
    circle: Float[Array, " 3"],
    target: Float[Array, " 3"],
    *,
    sign: float,
    wheel_radius_mm: float,
) -> Float[Array, ""]:
    """How far the soft mask is from an edge at the labelled soil line, in [0, 2].

    Mean of (1 - mask) over a strip of wheel face just above the line plus the mean of the mask
    over a strip of soil just below it, both inside the rim ``circle`` (cx, cy, r px). It is the
    surrogate that gives a frame that does not measure a gradient: the mask itself moves with
    every threshold, where the fit sees nothing until an edge appears.
    """
    height, width = mask.shape
    cx, cy, r = circle[0], circle[1], circle[2]
    yy, xx = jnp.mgrid[0:height, 0:width]
    u, v = sign * (xx - cx), yy - cy
    side = labelled_soil_side(u, v, r, target, wheel_radius_mm) / r
    inside = u * u + v * v < (0.93 * r) ** 2
    above = inside & (side > -STRIP_FAR) & (side < -STRIP_NEAR)
    below = inside & (side > STRIP_NEAR) & (side < STRIP_FAR)
    n_above, n_below = jnp.sum(above), jnp.sum(below)
    wheel_missing = jnp.sum(jnp.where(above, 1.0 - mask, 0.0)) / jnp.maximum(n_above, 1)
    soil_as_wheel = jnp.sum(jnp.where(below, mask, 0.0)) / jnp.maximum(n_below, 1)
    return jnp.where(n_above > 0, wheel_missing, 0.0) + jnp.where(n_below > 0, soil_as_wheel, 0.0)


def frame_loss(
    raw: Float[Array, " 6"],
    image: Float[Array, "H W 3"],
    target: Float[Array, " 3"],
    *,
    rect: tuple[int, int, int, int],
    travel: str,
    wheel_radius_mm: float,
) -> tuple[Float[Array, ""], FrameLoss]:
    """One frame's loss (sum over its measured cells plus the penalties) and what it saw."""
    seg = from_raw(raw)
    est = measure(image, seg, rect=rect, travel=travel, wheel_radius_mm=wheel_radius_mm)
    values = jnp.stack([est.sinkage_mm, jnp.degrees(est.theta1_rad), jnp.degrees(est.theta2_rad)])
    ok = est.status == _OK
    # Not ok: counts as measuring zeros, so a failed fit's values never reach the loss.
    used = jnp.where(ok & jnp.isfinite(values), values, 0.0)
    measured = jnp.isfinite(target)
    err = (used - jnp.where(measured, target, 0.0)) / jnp.asarray(LOSS_SCALES, used.dtype)
    loss = jnp.sum(jnp.where(measured, pseudo_huber(err), 0.0))
    contact = measured[0] & (jnp.where(measured[0], target[0], 0.0) > 0)
    deficit = jax.nn.relu(BOUNDARY_TARGET - jnp.sum(est.boundary_weight)) / BOUNDARY_TARGET
    loss = loss + jnp.where(contact, pseudo_huber(deficit), 0.0)
    # A labelled contact frame that does not measure: pull the mask towards an edge at the
    # labelled soil line (the rim circle is found even when the boundary is not).
    circle = jax.lax.stop_gradient(est.params[:3])
    usable = contact & ~ok & jnp.all(jnp.isfinite(circle)) & (circle[2] > 1.0)
    safe_circle = jnp.where(usable, circle, jnp.asarray([0.0, 0.0, 2.0], circle.dtype))
    contrast = boundary_contrast(
        wheel_mask(image, seg, rect),
        safe_circle,
        target,
        sign=travel_sign(travel),
        wheel_radius_mm=wheel_radius_mm,
    )
    loss = loss + jnp.where(usable, CONTRAST_WEIGHT * contrast, 0.0)
    return loss, FrameLoss(values=values, status=est.status, loss=loss)


class LossAndGrad(eqx.Module):
    """Mean loss over measured cells, its gradient w.r.t. the raw parameters, each frame."""

    loss: Float[Array, ""]
    grad: Float[Array, " 6"]
    frames: FrameLoss


@functools.partial(
    jax.jit, static_argnames=("rect", "travel", "wheel_radius_mm", "use_augment", "config")
)
def loss_and_grad(
    raw: Float[Array, " 6"],
    images_u8: UInt8[Array, "N H W 3"],
    targets: Float[Array, "N 3"],
    key: PRNGKeyArray,
    *,
    rect: tuple[int, int, int, int],
    travel: str,
    wheel_radius_mm: float,
    use_augment: bool = False,
    config: AugmentConfig = DEFAULT_CONFIG,
) -> LossAndGrad:
    """The calibration loss of a stack of labelled frames and its gradient (vmap of grad).

    Taking the gradient frame by frame lets a frame whose fit produced non-finite values (and
    so a NaN implicit gradient) drop out of the gradient; its constant penalty still counts in
    the loss. With ``use_augment`` each frame first gets a random lighting change from ``key``.
    """
    with _finite_gradients():
        dt = jnp.result_type(float)
        images = images_u8.astype(dt) / 255.0
        if use_augment:
            keys = jax.random.split(key, images.shape[0])
            images = jax.vmap(lambda im, k: augment(im, k, config))(images, keys)
        targets = targets.astype(dt)
        n_cells = jnp.maximum(jnp.sum(jnp.isfinite(targets)), 1).astype(dt)
        one = functools.partial(
            frame_loss, rect=rect, travel=travel, wheel_radius_mm=wheel_radius_mm
        )
        (losses, frames), grads = jax.vmap(
            jax.value_and_grad(one, has_aux=True), in_axes=(None, 0, 0)
        )(raw, images, targets)
        finite = jnp.all(jnp.isfinite(grads), axis=1, keepdims=True)
        grad = jnp.sum(jnp.where(finite, grads, 0.0), axis=0) / n_cells
        return LossAndGrad(loss=jnp.sum(losses) / n_cells, grad=grad, frames=frames)


# ----------------------------------------------------------------------------- optimisation


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
            state, scale = opt.init(raw), 0.5 * scale
        grad = out.grad
        if augment:
            noisy = call(
                raw, jax.random.fold_in(key, step), use_augment=True, config=augment_config
            )
            grad = 0.5 * (grad + noisy.grad)
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


# ----------------------------------------------------------------------------- command line

CLI_HELP = "tune the segmentation thresholds to a few labelled frames; writes a rig file"


def add_cli_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of ``sinkjax calibrate`` (conventions §3)."""
    p.add_argument(
        "labels",
        metavar="LABELS.csv",
        help="columns image,sinkage_mm,theta1_deg,theta2_deg; image paths relative to its "
        "folder; empty cell = not measured",
    )
    p.add_argument(
        "--rig", metavar="RIG.toml", help="rig to start from (default: rig.toml beside LABELS.csv)"
    )
    p.add_argument("--out", required=True, metavar="CALIBRATED.toml", help="rig file to write")
    p.add_argument(
        "--steps", type=_positive_int, default=50, metavar="N", help="Adam steps (default: 50)"
    )
    p.add_argument(
        "--augment",
        action="store_true",
        help="also calibrate under random lighting changes (slower; thresholds that survive "
        "the lamp moving)",
    )
    p.add_argument("--seed", type=int, default=0, metavar="S", help="augmentation seed (0)")


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def run_cli(args: argparse.Namespace) -> int:
    """``sinkjax calibrate``: validate everything, calibrate, write the rig, print a summary."""
    labels = Path(args.labels)
    rig_path = Path(args.rig) if args.rig else labels.parent / "rig.toml"
    if not rig_path.is_file():
        raise RigError(
            f"rig file {str(rig_path)!r} does not exist; pass --rig RIG.toml or put the rig.toml "
            "of these frames next to the labels file"
        )
    rig = load_rig(rig_path)
    frames = read_labels(labels, rig)
    out = Path(args.out)
    if not out.parent.is_dir():
        raise RigError(f"cannot write {str(out)!r}: folder {str(out.parent)!r} does not exist")
    n_cells = int(np.isfinite(frames.targets).sum())
    print(f"calibrating {rig_path} on {len(frames.names)} frames ({n_cells} measured values)")
    result = calibrate(
        frames, rig, steps=args.steps, augment=args.augment, seed=args.seed, progress=True
    )
    comment = (
        f"calibrated by `sinkjax calibrate {labels.name}` from {rig_path.name}: "
        f"{len(frames.names)} frames, loss {result.loss_before:.4g} -> "
        f"{result.loss_after:.4g}{', augmented' if args.augment else ''}"
    )
    try:
        save_rig(result.rig, out, comment=comment)
    except OSError as e:
        raise RigError(f"cannot write {str(out)!r}: {e.strerror or e}") from e
    print(result.summary())
    print(f"wrote {out}; measure with: sinkjax estimate IMAGES --rig {out}")
    return 0
