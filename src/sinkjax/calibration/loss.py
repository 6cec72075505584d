"""Calibration loss: the estimator's error on labelled frames as a function of the thresholds.

The soft estimator is differentiable in the segmentation parameters (through the optimistix fit,
by implicit differentiation), so instead of trying P_a/P_d by hand, calibration minimises a robust
loss between the estimated and the measured z0, theta1, theta2 of labelled frames.

Parameters live in an unconstrained *raw* space that keeps them valid by construction:
``P_d = sigmoid(raw)`` in (0, 1), ``P_a = 1 + softplus(raw)`` > 1, temperatures
``scale * softplus(raw)`` > 0 (scale 1 degree of hue, 0.01 of saturation, so that one Adam step
moves every parameter by a comparable amount), the soil/background veto's fraction
``0.25 softplus(raw)`` > 0.

Loss of one labelled cell: pseudo-Huber of the error in units of 1 mm (sinkage) or 1 degree
(angles); empty cells are masked out; the total is the mean over measured cells. A frame whose
status is not ``ok`` counts as measuring zeros (what ``no_contact`` reports), which is flat in the
thresholds; so a frame labelled with contact that does not measure also gets a surrogate term with
a gradient: how far the soft mask is from having an edge at the labelled soil line inside the rim
(:func:`boundary_contrast`), plus a term rewarding boundary weight when the fit sees too little.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int, PRNGKeyArray, UInt8

from ..geometry import travel_sign
from ..rig import SEGMENTATION_KEYS, SegmentationParams
from ..soft.estimator import (
    MIN_BOUNDARY_POINTS,
    SoftEstimate,
    measure_and_mask,
    measure_from_mask,
)
from ..soft.rim import RecordingRim
from ..soft.segmentation import Rect
from ..status import Status
from ..xla import map_frames
from .augment import AugmentConfig, augment

LOSS_SCALES = (1.0, 1.0, 1.0)  # 1 mm of sinkage weighs as much as 1 degree of angle
HUBER_DELTA = 1.0  # pseudo-Huber corner in those units: quadratic below, linear above
# A frame labelled with contact needs this much boundary weight before the deficit term is 0.
BOUNDARY_TARGET = 4.0 * MIN_BOUNDARY_POINTS
# Surrogate for frames that do not measure: strips between STRIP_NEAR and STRIP_FAR rim radii
# above / below the labelled soil line, weighted like CONTRAST_WEIGHT mm (or deg) of error.
STRIP_NEAR, STRIP_FAR = 0.03, 0.12
CONTRAST_WEIGHT = 5.0
RAW_NAMES = SEGMENTATION_KEYS  # the raw vector's order: the H/S band, then the veto
RAW_LIMIT = 12.0
_TEMPERATURE_UNIT_HUE_DEG = 1.0
_TEMPERATURE_UNIT_SAT = 0.01
_VETO_UNIT = 0.25  # the default veto fraction: raw 0.54 (softplus 1)
_OK = Status.OK.code


# ----------------------------------------------------------------------------- parameters


def _logit(p: float) -> float:
    p = min(max(p, 1e-6), 1.0 - 1e-6)  # a rig may say P_d = 0 (no lower saturation bound)
    return math.log(p / (1.0 - p))


def _inv_softplus(y: float) -> float:
    return y + math.log(-math.expm1(-y))


def to_raw(seg: SegmentationParams) -> Float[Array, " 7"]:
    """Unconstrained raw vector (order :data:`RAW_NAMES`) of valid segmentation parameters."""
    return jnp.asarray(raw_values(seg.as_dict()))


def raw_values(d: dict[str, float]) -> list[float]:
    """:func:`to_raw` of the parameters ``d`` (``SegmentationParams.as_dict()``) as Python
    floats: a grid of many points is made without a JAX call per point."""
    return [
        _logit(d["p_d_hue"]),
        _inv_softplus(d["p_a_hue"] - 1.0),
        _logit(d["p_d_sat"]),
        _inv_softplus(d["p_a_sat"] - 1.0),
        _inv_softplus(d["temperature_hue_deg"] / _TEMPERATURE_UNIT_HUE_DEG),
        _inv_softplus(d["temperature_sat"] / _TEMPERATURE_UNIT_SAT),
        # A veto of 0 (none wanted: a rig may say so) sits just above it.
        _inv_softplus(max(d["veto_fraction"], 1e-6) / _VETO_UNIT),
    ]


def from_raw(raw: Float[Array, " 7"]) -> SegmentationParams:
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
        veto_fraction=_VETO_UNIT * jax.nn.softplus(raw[6]),
    )


# ----------------------------------------------------------------------------- loss


def pseudo_huber(x: Float[Array, "*n"], delta: float = HUBER_DELTA) -> Float[Array, "*n"]:
    """``delta^2 (sqrt(1 + (x / delta)^2) - 1)``: x^2 / 2 near 0, delta |x| far out."""
    return delta * delta * (jnp.sqrt(1.0 + (x / delta) ** 2) - 1.0)


class FrameLoss(eqx.Module):
    """One frame as the loss saw it: estimates (sinkage_mm, theta1_deg, theta2_deg), status,
    the fitted rim circle (cx, cy, r px) and equivalent line (k, b px), without gradient."""

    values: Float[Array, "*n 3"]
    status: Int[Array, "*n"]
    loss: Float[Array, "*n"]
    circle: Float[Array, "*n 3"]
    line: Float[Array, "*n 2"]


def labelled_soil_side(
    u_px: Float[Array, "H W"],
    v_px: Float[Array, "H W"],
    r_px: Float[Array, ""],
    target: Float[Array, " 3"],
    wheel_radius_mm: float | Float[Array, ""],
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
    sign: float | Float[Array, ""],
    wheel_radius_mm: float | Float[Array, ""],
) -> Float[Array, ""]:
    """How far the soft mask is from an edge at the labelled soil line, in [0, 2].

    Mean of (1 - mask) over a strip of wheel face just above the line plus the mean of the mask
    over a strip of soil just below it, both inside the rim ``circle`` (cx, cy, r px). It is the
    surrogate that gives a frame that does not measure a gradient: the mask itself moves with
    every threshold, where the fit sees nothing until an edge appears.
    """
    height, width = mask.shape
    cx, cy, r = circle[0], circle[1], circle[2]
    dt = mask.dtype
    yy, xx = (g.astype(dt) for g in jnp.mgrid[0:height, 0:width])
    u, v = sign * (xx - cx), yy - cy
    side = labelled_soil_side(u, v, r, target, wheel_radius_mm) / r
    inside = u * u + v * v < (0.93 * r) ** 2
    above = inside & (side > -STRIP_FAR) & (side < -STRIP_NEAR)
    below = inside & (side > STRIP_NEAR) & (side < STRIP_FAR)
    n_above, n_below = jnp.sum(above).astype(dt), jnp.sum(below).astype(dt)
    wheel_missing = jnp.sum(jnp.where(above, 1.0 - mask, 0.0)) / jnp.maximum(n_above, 1.0)
    soil_as_wheel = jnp.sum(jnp.where(below, mask, 0.0)) / jnp.maximum(n_below, 1.0)
    return jnp.where(n_above > 0, wheel_missing, 0.0) + jnp.where(n_below > 0, soil_as_wheel, 0.0)


def frame_loss(
    raw: Float[Array, " 7"],
    image: Float[Array, "H W 3"],
    target: Float[Array, " 3"],
    *,
    rect: Rect,
    travel: str | Float[Array, ""],
    wheel_radius_mm: float | Float[Array, ""],
    rim: RecordingRim | None = None,
    srgb: bool | Float[Array, ""] = False,
) -> tuple[Float[Array, ""], FrameLoss]:
    """One frame's loss (sum over its measured cells plus the penalties) and what it saw.
    ``rim``: the recording's rim to measure with (as ``sinkjax estimate`` does); None: the
    frame's own. The rig's numbers may be Python values or arrays (``rect`` an int array of 4,
    ``travel`` the sign +1.0 / -1.0, ``srgb`` a 0/1 flag), traced as in
    :func:`sinkjax.soft.estimator.measure`."""
    # The contrast term looks at the mask the frame was measured with (made once).
    est, mask = measure_and_mask(
        image, from_raw(raw), rect=rect, travel=travel, wheel_radius_mm=wheel_radius_mm, rim=rim,
        srgb=srgb,
    )  # fmt: skip
    sign = travel_sign(travel) if isinstance(travel, str) else travel
    return _estimate_loss(est, mask, target, sign, wheel_radius_mm)


def mask_frame_loss(
    image: Float[Array, "H W 3"],
    mask: Float[Array, "H W"],
    target: Float[Array, " 3"],
    *,
    travel: str | Float[Array, ""],
    wheel_radius_mm: float | Float[Array, ""],
    rim_range_px: tuple[Float[Array, ""], Float[Array, ""]] | None = None,
    srgb: bool | Float[Array, ""] = False,
) -> tuple[Float[Array, ""], FrameLoss]:
    """:func:`frame_loss` of any soft wheel mask (a learned segmenter's, say): the fit's error
    against ``target`` plus the penalties, differentiable w.r.t. ``mask``. ``travel`` may be a
    traced sign (+1.0 / -1.0) and the rig's numbers arrays (``srgb`` a 0/1 flag), as in
    :func:`sinkjax.soft.estimator.measure_from_mask`."""
    est = measure_from_mask(
        image,
        mask,
        travel=travel,
        wheel_radius_mm=wheel_radius_mm,
        rim_range_px=rim_range_px,
        srgb=srgb,
    )
    sign = travel_sign(travel) if isinstance(travel, str) else travel
    return _estimate_loss(est, mask, target, sign, wheel_radius_mm)


def _estimate_loss(
    est: SoftEstimate,
    mask: Float[Array, "H W"],
    target: Float[Array, " 3"],
    sign: float | Float[Array, ""],
    wheel_radius_mm: float | Float[Array, ""],
) -> tuple[Float[Array, ""], FrameLoss]:
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
    # lax.cond: a frame that measures (most, most of the time) skips the full-image strips.
    contrast = jax.lax.cond(
        usable,
        lambda: jnp.asarray(
            CONTRAST_WEIGHT
            * boundary_contrast(
                mask, safe_circle, target, sign=sign, wheel_radius_mm=wheel_radius_mm
            ),
            mask.dtype,
        ),
        lambda: jnp.zeros((), mask.dtype),
    )
    loss = loss + contrast
    line = jax.lax.stop_gradient(est.params[3:5])
    return loss, FrameLoss(values=values, status=est.status, loss=loss, circle=circle, line=line)


class LossAndGrad(eqx.Module):
    """Mean loss over measured cells, its gradient w.r.t. the raw parameters, each frame."""

    loss: Float[Array, ""]
    grad: Float[Array, " 7"]
    frames: FrameLoss


class LossRig(eqx.Module):
    """The rig's numbers the loss needs, as arrays: traced, so that one compiled loss serves
    every rig of an image size (a new rig's calibration compiles nothing that the persistent
    compilation cache holds). Built by :func:`sinkjax.calibration.compiled.loss_rig`."""

    rect_px: Int[Array, " 4"]  # the confidence rectangle x, y, w, h
    travel_sign: Float[Array, ""]  # +1.0 travel right, -1.0 left
    wheel_radius_mm: Float[Array, ""]
    srgb: Float[Array, ""]  # 1.0: the frames are sRGB-encoded (Rig.encoding), else 0.0


def frame_losses(
    raw: Float[Array, " 7"],
    images_u8: UInt8[Array, "N H W 3"],
    targets: Float[Array, "N 3"],
    key: PRNGKeyArray,
    rim: RecordingRim | None,
    rig: LossRig,
    *,
    use_augment: bool,
    config: AugmentConfig,
    with_grad: bool,
) -> LossAndGrad:
    """The mean loss over the measured cells of a stack of labelled frames, each frame's loss and
    values, and (``with_grad``) the gradient w.r.t. ``raw``: the body of the compiled losses of
    :mod:`sinkjax.calibration.compiled`. Taking the gradient frame by frame lets a frame whose
    fit produced non-finite values (and so a NaN implicit gradient) drop out of the gradient;
    its constant penalty still counts in the loss."""
    dt = jnp.result_type(float)
    images = images_u8.astype(dt) / 255.0
    if use_augment:
        keys = jax.random.split(key, images.shape[0])
        images = jax.vmap(lambda im, k: augment(im, k, config))(images, keys)
    targets = targets.astype(dt)
    n_cells = jnp.maximum(jnp.sum(jnp.isfinite(targets)), 1).astype(dt)
    one = functools.partial(
        frame_loss, rect=rig.rect_px, travel=rig.travel_sign, wheel_radius_mm=rig.wheel_radius_mm,
        rim=rim, srgb=rig.srgb,
    )  # fmt: skip
    if with_grad:
        both = jax.value_and_grad(one, has_aux=True)
        (losses, frames), grads = map_frames(lambda it: both(raw, *it), (images, targets))
        finite = jnp.all(jnp.isfinite(grads), axis=1, keepdims=True)
        grad = jnp.sum(jnp.where(finite, grads, 0.0), axis=0) / n_cells
    else:
        losses, frames = map_frames(lambda it: one(raw, *it), (images, targets))
        grad = jnp.zeros_like(raw)
    return LossAndGrad(loss=jnp.sum(losses) / n_cells, grad=grad, frames=frames)
