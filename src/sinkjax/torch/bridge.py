"""Gradient bridge from torch to the JAX estimator: tensors cross by DLPack, backward is JAX's VJP.

:func:`measure_torch` (or :class:`MeasureFromMask`) gives z0, theta1, theta2 and their one-sigma
as torch tensors; :class:`SinkageFromMask` and :class:`SinkageFromImage` are the
``torch.autograd.Function`` s underneath, running the jitted batches of
:mod:`sinkjax.torch.jax_bridge` (the implicit-differentiated fit) forward and backward.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import torch
from torch import Tensor, nn

from ..rig import SEG_FIELDS, SegmentationParams
from ..soft.uncertainty import UncertaintyModel
from ..status import Status
from . import jax_bridge as _bridge
from .segmentation import _check_images, _check_masks, _param_tensors, _valid_rect

__all__ = [
    "MeasureFromMask",
    "SinkageFromImage",
    "SinkageFromMask",
    "TorchEstimate",
    "measure_torch",
]


def _jax_float() -> torch.dtype:
    return torch.float64 if jax.config.read("jax_enable_x64") else torch.float32


def _to_jax(t: Tensor, dtype: torch.dtype) -> jax.Array:
    """A torch tensor as a JAX array, sharing memory when dtype, device and layout allow."""
    t = t.detach()
    # JAX computes in float32 unless x64 is on: a float64 (or half) tensor is cast in torch first,
    # which is a copy; the results are cast back to the caller's dtype.
    if t.dtype != dtype:
        t = t.to(dtype)
    t = t.contiguous()
    try:
        return jax.dlpack.from_dlpack(t)
    except (RuntimeError, TypeError, ValueError, BufferError):
        # DLPack fails where JAX has no backend for the tensor's device (a CUDA tensor with a
        # CPU-only jaxlib) or rejects the layout: copy through host memory instead.
        return jnp.asarray(t.cpu().numpy())


def _to_torch(a: jax.Array, like: Tensor) -> Tensor:
    """A JAX array as a torch tensor with ``like``'s dtype and device (zero-copy if they match)."""
    try:
        t = torch.from_dlpack(a)
    except (RuntimeError, TypeError, ValueError, BufferError):
        t = torch.from_numpy(np.array(a))
    return t.to(dtype=like.dtype if like.is_floating_point() else t.dtype, device=like.device)


class _JaxFunction(torch.autograd.Function):
    """Shared forward/backward: ``batch`` maps the float inputs to (values (B, 6), status (B,))."""

    @staticmethod
    def _run(
        ctx: Any,
        batch: _bridge.JittedBatch,
        rig: _bridge.BridgeRig,
        n_batched: int,
        *inputs: Tensor,
    ) -> tuple[Tensor, Tensor]:
        dtype = _jax_float()
        xs = [_to_jax(t, dtype) for t in inputs]
        needs_grad = any(ctx.needs_input_grad[: len(inputs)])
        if needs_grad:
            values, status, vjp = batch.forward_vjp(rig, *xs)
            # A frame whose fit failed (non-finite parameters) makes the implicit-function linear
            # solve of the backward pass raise for the whole batch. Its gradient is 0 anyway
            # (nothing it reports is usable), so residuals are recomputed with such frames
            # replaced by a healthy one, whose cotangent backward then zeroes.
            dead = ~np.all(np.isfinite(np.asarray(values)), axis=-1) | (
                np.asarray(status) == Status.FIT_FAILED.code
            )
            if dead.any():
                healthy = np.flatnonzero(~dead)
                if healthy.size == 0:
                    vjp = None
                else:
                    take = jnp.asarray(np.where(dead, healthy[0], np.arange(dead.size)))
                    swapped = [x[take] if k < n_batched else x for k, x in enumerate(xs)]
                    vjp = batch.forward_vjp(rig, *swapped)[2]
            ctx.vjp = vjp
            ctx.dead = torch.from_numpy(dead).to(inputs[0].device)
            ctx.batch = batch
            # JAX may keep aliases of the DLPack-shared inputs among its residuals: saving the
            # tensors lets torch's version counter catch an in-place edit before backward.
            ctx.save_for_backward(*inputs)
        else:
            values, status = batch.forward(rig, *xs)
        ctx.n_batched = n_batched
        out = _to_torch(values, inputs[0])
        st = torch.from_numpy(np.array(status)).to(dtype=torch.int64, device=inputs[0].device)
        ctx.mark_non_differentiable(st)
        return out, st

    @staticmethod
    def _grad(ctx: Any, g_values: Tensor) -> tuple[Tensor | None, ...]:
        inputs = ctx.saved_tensors
        g_values = torch.where(ctx.dead[:, None], torch.zeros_like(g_values), g_values)
        if ctx.vjp is None:  # every frame failed
            return tuple(
                torch.zeros_like(x) if need else None
                for x, need in zip(inputs, ctx.needs_input_grad, strict=False)
            )
        g = _to_jax(g_values.contiguous(), _jax_float())
        # ctx.vjp stays: backward may run again on a retained graph; it goes with the graph.
        grads = ctx.batch.backward(ctx.vjp, g)
        # A VJP is linear in the cotangent, so a frame with none has zero gradient; enforce it
        # with a select, so that non-finite residuals (NaN * 0) cannot leak into a batch whose
        # loss ignores that frame. Only the per-frame inputs are batched.
        silent = (g_values == 0).all(dim=-1)
        out: list[Tensor | None] = []
        for k, (gr, x, need) in enumerate(zip(grads, inputs, ctx.needs_input_grad, strict=False)):
            if not need:
                out.append(None)
                continue
            t = _to_torch(gr, x)
            if k < ctx.n_batched:
                t = torch.where(silent.view(-1, *([1] * (t.dim() - 1))), torch.zeros_like(t), t)
            out.append(t)
        return tuple(out)


class SinkageFromMask(_JaxFunction):
    """``apply(images (B,3,H,W), masks (B,1,H,W), travel, wheel_radius_mm)`` -> (values, status).

    ``values`` (B, 6) is z0 (mm), theta1, theta2 (deg), then their one-sigma; ``status`` (B,) int64
    indexes :class:`sinkjax.Status` codes and has no gradient. An optional last argument is the
    :class:`~sinkjax.soft.uncertainty.UncertaintyModel` (default: the estimator's). Backward is
    JAX's VJP of :func:`sinkjax.torch.jax_bridge.measure_from_mask`, reaching images and masks.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        images: Tensor,
        masks: Tensor,
        travel: str,
        wheel_radius_mm: float,
        uncertainty: UncertaintyModel | None = None,
    ) -> tuple[Tensor, Tensor]:
        rig = _bridge.bridge_rig(None, travel, wheel_radius_mm)
        return _JaxFunction._run(ctx, _bridge.from_mask_batch(uncertainty), rig, 2, images, masks)

    @staticmethod
    def backward(ctx: Any, g_values: Tensor, g_status: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        return (*_JaxFunction._grad(ctx, g_values), None, None, None)


class SinkageFromImage(_JaxFunction):
    """``apply(images (B,3,H,W), seg_vector (6,), rect, travel, wheel_radius_mm)``.

    The whole JAX estimator, HSI segmentation included (:func:`sinkjax.soft.estimator.measure`);
    ``seg_vector`` holds the thresholds in ``SEG_FIELDS`` order, shared by the batch. Outputs as
    :class:`SinkageFromMask`.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        images: Tensor,
        seg_vector: Tensor,
        rect: tuple[int, int, int, int],
        travel: str,
        wheel_radius_mm: float,
        uncertainty: UncertaintyModel | None = None,
        open_radius_px: int = 0,
    ) -> tuple[Tensor, Tensor]:
        batch = _bridge.from_image_batch(uncertainty, open_radius_px)
        rig = _bridge.bridge_rig(rect, travel, wheel_radius_mm)
        return _JaxFunction._run(ctx, batch, rig, 1, images, seg_vector)

    @staticmethod
    def backward(ctx: Any, g_values: Tensor, g_status: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        return (*_JaxFunction._grad(ctx, g_values), None, None, None, None, None)


class TorchEstimate(NamedTuple):
    """Per-frame results, each shape (B,). ``status`` is a :attr:`sinkjax.Status.code` (0 = ok)."""

    sinkage_mm: Tensor
    theta1_deg: Tensor
    theta2_deg: Tensor
    sinkage_std_mm: Tensor
    theta1_std_deg: Tensor
    theta2_std_deg: Tensor
    status: Tensor

    @property
    def values(self) -> Tensor:
        """(B, 3): z0 mm, theta1 deg, theta2 deg."""
        return torch.stack([self.sinkage_mm, self.theta1_deg, self.theta2_deg], -1)


def measure_torch(
    images: Tensor,
    masks: Tensor | None = None,
    *,
    seg: SegmentationParams | Mapping[str, Tensor | float] | None = None,
    rect: tuple[int, int, int, int] | None = None,
    travel: str = "right",
    wheel_radius_mm: float = 1.0,
    uncertainty: UncertaintyModel | None = None,
    open_radius_px: int = 0,
) -> TorchEstimate:
    """Sinkage and entry/exit angles with one-sigma, differentiable through the JAX estimator.

    With ``masks`` the JAX fit uses them as the wheel masks (a torch segmenter's output);
    without, JAX segments the images with the HSI thresholds ``seg`` and the confidence
    rectangle ``rect`` (both required then; tensors in ``seg`` receive gradients).

    Args:
        images: RGB in [0, 1] with shape :math:`(B, 3, H, W)`.
        masks: soft wheel masks in [0, 1] with shape :math:`(B, 1, H, W)`, or None.
        seg: thresholds when ``masks`` is None.
        rect: confidence rectangle (x, y, w, h) px when ``masks`` is None.
        travel: "right" or "left".
        wheel_radius_mm: physical rim radius R (z0 is reported in mm).
        uncertainty: how the one-sigma is scaled and floored (default: the estimator's).
        open_radius_px: without masks, as in :func:`sinkjax.soft.estimator.measure`; with masks,
            apply :func:`soft_open` to them yourself.

    Returns:
        :class:`TorchEstimate` of (B,) tensors in the images' dtype and device.

    Example:
        >>> est = measure_torch(images, seg_module(images), wheel_radius_mm=140.0)  # doctest: +SKIP
        >>> est.sinkage_mm.sum().backward()  # doctest: +SKIP
    """
    _check_images(images)
    if travel not in ("right", "left"):
        raise ValueError(f"travel must be 'right' or 'left'. Got {travel!r}")
    if masks is not None:
        _check_masks(masks, images)
        values, status = SinkageFromMask.apply(
            images, masks, travel, float(wheel_radius_mm), uncertainty
        )
    else:
        if seg is None or rect is None:
            raise ValueError("without masks, measure_torch needs seg= and rect= to segment with")
        rect = _valid_rect(rect, images.shape[-2], images.shape[-1])
        p = _param_tensors(seg, images)
        seg_vector = torch.stack([p[n] for n in SEG_FIELDS])
        values, status = SinkageFromImage.apply(
            images, seg_vector, rect, travel, float(wheel_radius_mm), uncertainty, open_radius_px
        )
    return TorchEstimate(*values.unbind(-1), status)  # type: ignore[call-arg]


class MeasureFromMask(nn.Module):
    """Module form of :func:`measure_torch` with masks: ``(images, masks)`` -> TorchEstimate."""

    def __init__(self, *, travel: str = "right", wheel_radius_mm: float = 1.0) -> None:
        super().__init__()
        self.travel = travel
        self.wheel_radius_mm = float(wheel_radius_mm)

    def forward(self, images: Tensor, masks: Tensor) -> TorchEstimate:
        return measure_torch(
            images, masks, travel=self.travel, wheel_radius_mm=self.wheel_radius_mm
        )
