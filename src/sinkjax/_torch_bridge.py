"""The JAX half of the PyTorch bridge: the soft estimator driven by a mask someone else computed.

:func:`sinkjax._soft.measure` segments the image itself (HSI thresholds). A learned segmenter (a
torch network, say) supplies its own soft mask instead; :func:`measure_from_mask` runs everything
after the segmentation step exactly as ``measure`` does (outline, image-based edge refinement,
Hough start, joint fit, covariance), so that ``measure_from_mask(image, wheel_mask(image, seg,
rect))`` is ``measure(image, seg, rect=rect)`` (tested), value for value. Its gradients differ in
one way: weights that are exactly zero pass no derivative (``_zero_tangent_where_zero``), where
``measure`` gets NaN from the fit's ``sqrt(w)``. No torch here: :mod:`sinkjax.torch` turns
these batched, jitted functions into a ``torch.autograd.Function``.

Batched functions take torch's layout, images ``(B, 3, H, W)`` and masks ``(B, 1, H, W)``, so the
tensors can cross by DLPack without a copy; the transpose to channel-last happens inside XLA.
They return ``values (B, 6)``: z0 (mm), theta1 (deg), theta2 (deg) and their one-sigma, in that
order, and ``status (B,)`` (indices into :data:`sinkjax._soft.STATUS_CODES`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ._fit import build_evidence, fit
from ._geometry import travel_sign
from ._hough import hough_rim
from ._model import Evidence, measurements
from ._outline import extract_outline, refine_outline
from ._rig import SegmentationParams
from ._segmentation import soft_open, wheel_mask
from ._soft import (
    _FIT_FAILED,
    _NO_CONTACT,
    _NO_WHEEL,
    _OK,
    MIN_BOUNDARY_POINTS,
    MIN_RIM_SUPPORT,
    SoftEstimate,
)
from ._uncertainty import UncertaintyModel, covariance, measurement_std

VALUE_NAMES = (
    "sinkage_mm",
    "theta1_deg",
    "theta2_deg",
    "sinkage_std_mm",
    "theta1_std_deg",
    "theta2_std_deg",
)
FIT_FAILED = _FIT_FAILED
SEG_FIELDS = (
    "p_d_hue",
    "p_a_hue",
    "p_d_sat",
    "p_a_sat",
    "temperature_hue_deg",
    "temperature_sat",
)


@jax.custom_jvp
def _zero_tangent_where_zero(w: Float[Array, " K"]) -> Float[Array, " K"]:
    """Identity whose derivative is a select: tangent (and so cotangent) 0 where ``w == 0``.

    The fit's residuals carry ``sqrt(w)``, whose derivative is infinite at w = 0; every outline
    point that a hard gate (out of the rim band, not below the rim, padding) gives weight
    exactly 0 then sends inf or NaN back, and NaN * 0 poisons the whole gradient. Those weights
    are 0 on a neighbourhood of the input (their gates are piecewise constant), so their true
    contribution is 0: in reverse mode the transposed select drops the inf cotangent without
    changing any value. (Forward mode still meets sqrt's inf * 0 after the guard; the fix for
    that belongs in the residuals.)
    """
    return w


@_zero_tangent_where_zero.defjvp
def _zero_tangent_where_zero_jvp(
    primals: tuple[Array], tangents: tuple[Array]
) -> tuple[Array, Array]:
    (w,), (t,) = primals, tangents
    return w, jnp.where(w > 0, t, jnp.zeros_like(t))


def _guard_weights(ev: Evidence) -> Evidence:
    return eqx.tree_at(
        lambda e: (e.w_rim, e.w_line, e.w_a, e.w_b),
        ev,
        tuple(_zero_tangent_where_zero(w) for w in (ev.w_rim, ev.w_line, ev.w_a, ev.w_b)),
    )


def measure_from_mask(
    image: Float[Array, "H W 3"],
    mask: Float[Array, "H W"],
    *,
    travel: str = "right",
    wheel_radius_mm: float = 1.0,
    uncertainty: UncertaintyModel | None = None,
) -> SoftEstimate:
    """The soft method from a given soft wheel mask in [0, 1] (1 = wheel) and its image in [0, 1].

    Mirrors :func:`sinkjax._soft.measure` step for step after ``wheel_mask``; the image is still
    needed because the outline is refined on it. Keyword arguments are static. (``measure``'s
    ``open_radius_px`` belongs to the segmentation: open the mask before passing it.)
    Raises ValueError if the shapes disagree.
    """
    if image.ndim != 3 or image.shape[-1] != 3 or mask.shape != image.shape[:2]:
        raise ValueError(
            f"need image (H, W, 3) and mask (H, W) of the same H, W; got image {image.shape} "
            f"and mask {mask.shape}"
        )
    height, width = mask.shape
    outline = refine_outline(image, extract_outline(mask))
    # The starting circle is a discrete choice: no gradient flows through it.
    circle = jax.lax.stop_gradient(hough_rim(outline, height, width))
    ev = _guard_weights(build_evidence(outline, circle, travel_sign(travel)))
    res = fit(ev)
    p = res.params
    cov = covariance(p, ev)
    est = measurements(p, wheel_radius_mm)
    std = measurement_std(p, cov, wheel_radius_mm, uncertainty)
    contact = jnp.sum(ev.w_line) >= MIN_BOUNDARY_POINTS
    status = jnp.where(
        circle.support < MIN_RIM_SUPPORT,
        _NO_WHEEL,
        jnp.where(~res.ok, _FIT_FAILED, jnp.where(contact, _OK, _NO_CONTACT)),
    )
    zero_if_no_contact = jnp.where(contact, 1.0, 0.0)
    return SoftEstimate(
        sinkage_mm=est[0] * zero_if_no_contact,
        sinkage_std_mm=std[0],
        theta1_rad=est[1] * zero_if_no_contact,
        theta1_std_rad=std[1],
        theta2_rad=est[2] * zero_if_no_contact,
        theta2_std_rad=std[2],
        params=p,
        params_std=jnp.sqrt(jnp.maximum(jnp.diag(cov), 0.0)),
        status=status.astype(jnp.int32),
        boundary_weight=ev.w_line,
        boundary_x_px=ev.x_px,
        boundary_y_px=ev.y_px,
    )


def estimate_values(est: SoftEstimate) -> Float[Array, " 6"]:
    """(z0 mm, theta1 deg, theta2 deg, sigma z0 mm, sigma theta1 deg, sigma theta2 deg)."""
    return jnp.stack(
        [
            est.sinkage_mm,
            jnp.degrees(est.theta1_rad),
            jnp.degrees(est.theta2_rad),
            est.sinkage_std_mm,
            jnp.degrees(est.theta1_std_rad),
            jnp.degrees(est.theta2_std_rad),
        ]
    )


def seg_from_vector(v: Float[Array, " 6"]) -> SegmentationParams:
    """SegmentationParams from its six leaves in :data:`SEG_FIELDS` order."""
    return SegmentationParams(**{name: v[i] for i, name in enumerate(SEG_FIELDS)})


BatchFn = Callable[..., tuple[Float[Array, "B 6"], Int[Array, " B"]]]


def _from_mask_batch(
    travel: str, wheel_radius_mm: float, uncertainty: UncertaintyModel | None
) -> BatchFn:
    def one(image_chw: Array, mask_1hw: Array) -> tuple[Array, Array]:
        est = measure_from_mask(
            jnp.moveaxis(image_chw, 0, -1),
            mask_1hw[0],
            travel=travel,
            wheel_radius_mm=wheel_radius_mm,
            uncertainty=uncertainty,
        )
        return estimate_values(est), est.status

    return jax.vmap(one)


def _from_image_batch(
    rect: tuple[int, int, int, int],
    travel: str,
    wheel_radius_mm: float,
    uncertainty: UncertaintyModel | None,
    open_radius_px: int,
) -> BatchFn:
    def one(image_chw: Array, seg_vector: Array) -> tuple[Array, Array]:
        # measure(image, seg) is measure_from_mask(image, wheel_mask(image, seg)) (tested); this
        # path has the NaN-free gradients of the weight guard.
        image = jnp.moveaxis(image_chw, 0, -1)
        mask = wheel_mask(image, seg_from_vector(seg_vector), rect)
        if open_radius_px > 0:
            mask = soft_open(mask, open_radius_px)
        est = measure_from_mask(
            image, mask, travel=travel, wheel_radius_mm=wheel_radius_mm, uncertainty=uncertainty
        )
        return estimate_values(est), est.status

    return jax.vmap(one, in_axes=(0, None))


class JittedBatch:
    """A batched estimator as three jitted functions, compiled once per input shape and dtype.

    ``forward(*xs)`` -> (values, status); ``forward_vjp(*xs)`` -> (values, status, vjp) where
    ``vjp`` is a pytree (``jax.tree_util.Partial``) holding the residuals, and
    ``backward(vjp, g_values)`` -> cotangents of ``xs``. Running forward and backward through
    jitted functions, and keeping the residuals between them, costs one solve per step instead of
    the two that re-running the forward pass inside backward would.
    """

    def __init__(self, fn: BatchFn) -> None:
        def with_vjp(*xs: Array) -> tuple[Array, Array, Callable]:
            values, vjp, status = jax.vjp(fn, *xs, has_aux=True)
            return values, status, vjp

        self.forward = jax.jit(fn)
        self.forward_vjp = jax.jit(with_vjp)
        self.backward = jax.jit(lambda vjp, g: vjp(g))


@functools.cache
def from_mask_batch(
    travel: str, wheel_radius_mm: float, uncertainty: UncertaintyModel | None = None
) -> JittedBatch:
    """Jitted ``(images (B,3,H,W), masks (B,1,H,W)) -> (values (B,6), status (B,))``."""
    travel_sign(travel)  # eager ValueError for a bad travel
    return JittedBatch(_from_mask_batch(travel, float(wheel_radius_mm), uncertainty))


@functools.cache
def from_image_batch(
    rect: tuple[int, int, int, int],
    travel: str,
    wheel_radius_mm: float,
    uncertainty: UncertaintyModel | None = None,
    open_radius_px: int = 0,
) -> JittedBatch:
    """Jitted ``(images (B,3,H,W), seg_vector (6,)) -> (values (B,6), status (B,))``."""
    travel_sign(travel)
    fn = _from_image_batch(
        tuple(rect),  # type: ignore[arg-type]
        travel,
        float(wheel_radius_mm),
        uncertainty,
        int(open_radius_px),
    )
    return JittedBatch(fn)
