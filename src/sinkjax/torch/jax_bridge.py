"""The JAX half of the PyTorch bridge: the soft estimator driven by a mask someone else computed.

:func:`sinkjax.soft.estimator.measure` segments the image itself (HSI thresholds). A learned
segmenter (a torch network, say) supplies its own soft mask instead, through
:func:`sinkjax.soft.estimator.measure_from_mask` (everything after the segmentation step;
``measure`` is ``measure_from_mask(image, wheel_mask(image, seg, rect))``). No torch here:
:mod:`sinkjax.torch.bridge` turns these batched, jitted functions into
``torch.autograd.Function`` s.

Batched functions take torch's layout, images ``(B, 3, H, W)`` and masks ``(B, 1, H, W)``, so the
tensors can cross by DLPack without a copy; the transpose to channel-last happens inside XLA.
They return ``values (B, 6)``: z0 (mm), theta1 (deg), theta2 (deg) and their one-sigma, in that
order, and ``status (B,)`` (:attr:`sinkjax.Status.code` of each frame's outcome).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..geometry import travel_sign
from ..rig import SEG_FIELDS, SegmentationParams
from ..soft.estimator import SoftEstimate, measure_from_mask
from ..soft.segmentation import soft_open, wheel_mask
from ..soft.uncertainty import UncertaintyModel
from ..xla import jit, map_frames

VALUE_NAMES = (
    "sinkage_mm",
    "theta1_deg",
    "theta2_deg",
    "sinkage_std_mm",
    "theta1_std_deg",
    "theta2_std_deg",
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


class BridgeRig(eqx.Module):
    """A rig's numbers as arrays, the first argument of every :class:`JittedBatch` function:
    traced, so one compiled function serves every rig of an image size (:func:`bridge_rig`)."""

    rect_px: Int[Array, " 4"]  # the confidence rectangle x, y, w, h (unused with masks)
    travel_sign: Float[Array, ""]  # +1.0 travel right, -1.0 left
    wheel_radius_mm: Float[Array, ""]


def bridge_rig(
    rect: tuple[int, int, int, int] | None, travel: str, wheel_radius_mm: float
) -> BridgeRig:
    """``rect`` (None with masks), ``travel`` and ``wheel_radius_mm`` as arrays of fixed dtypes
    (every rig the same abstract signature). Raises ValueError for a bad ``travel``."""
    dtype = jax.dtypes.canonicalize_dtype(jnp.float64)
    return BridgeRig(
        rect_px=jnp.asarray((0, 0, 1, 1) if rect is None else tuple(rect), jnp.int32),
        travel_sign=jnp.asarray(travel_sign(travel), dtype),
        wheel_radius_mm=jnp.asarray(float(wheel_radius_mm), dtype),
    )


def _from_mask_batch(uncertainty: UncertaintyModel | None) -> BatchFn:
    def one(rig: BridgeRig, image_chw: Array, mask_1hw: Array) -> tuple[Array, Array]:
        est = measure_from_mask(
            jnp.moveaxis(image_chw, 0, -1),
            mask_1hw[0],
            travel=rig.travel_sign,
            wheel_radius_mm=rig.wheel_radius_mm,
            uncertainty=uncertainty,
        )
        return estimate_values(est), est.status

    def batch(rig: BridgeRig, images: Array, masks: Array) -> tuple[Array, Array]:
        return map_frames(lambda frame: one(rig, *frame), (images, masks))

    return batch


def _from_image_batch(uncertainty: UncertaintyModel | None, open_radius_px: int) -> BatchFn:
    def one(rig: BridgeRig, image_chw: Array, seg_vector: Array) -> tuple[Array, Array]:
        # measure(image, seg) is measure_from_mask(image, wheel_mask(image, seg)) (tested); this
        # path has the NaN-free gradients of the weight guard.
        image = jnp.moveaxis(image_chw, 0, -1)
        mask = wheel_mask(image, seg_from_vector(seg_vector), rig.rect_px)
        if open_radius_px > 0:
            mask = soft_open(mask, open_radius_px)
        est = measure_from_mask(
            image,
            mask,
            travel=rig.travel_sign,
            wheel_radius_mm=rig.wheel_radius_mm,
            uncertainty=uncertainty,
        )
        return estimate_values(est), est.status

    def batch(rig: BridgeRig, images: Array, seg_vector: Array) -> tuple[Array, Array]:
        return map_frames(lambda image: one(rig, image, seg_vector), images)

    return batch


class JittedBatch:
    """A batched estimator as three jitted functions, compiled once per input shape and dtype,
    whatever the rig (its :class:`BridgeRig` is a traced argument).

    ``forward(rig, *xs)`` -> (values, status); ``forward_vjp(rig, *xs)`` -> (values, status,
    vjp) where ``vjp`` is a pytree (``jax.tree_util.Partial``) holding the residuals, and
    ``backward(vjp, g_values)`` -> cotangents of ``xs`` (none for the rig). Running forward and
    backward through jitted functions, and keeping the residuals between them, costs one solve
    per step instead of the two that re-running the forward pass inside backward would.
    """

    def __init__(self, fn: BatchFn) -> None:
        def with_vjp(rig: BridgeRig, *xs: Array) -> tuple[Array, Array, Callable]:
            values, vjp, status = jax.vjp(lambda *x: fn(rig, *x), *xs, has_aux=True)
            return values, status, vjp

        self.forward = jit(fn)
        self.forward_vjp = jit(with_vjp)
        self.backward = jit(lambda vjp, g: vjp(g))


@functools.cache
def from_mask_batch(uncertainty: UncertaintyModel | None = None) -> JittedBatch:
    """Jitted ``(rig, images (B,3,H,W), masks (B,1,H,W)) -> (values (B,6), status (B,))``."""
    return JittedBatch(_from_mask_batch(uncertainty))


@functools.cache
def from_image_batch(
    uncertainty: UncertaintyModel | None = None, open_radius_px: int = 0
) -> JittedBatch:
    """Jitted ``(rig, images (B,3,H,W), seg_vector (6,)) -> (values (B,6), status (B,))``."""
    return JittedBatch(_from_image_batch(uncertainty, int(open_radius_px)))
