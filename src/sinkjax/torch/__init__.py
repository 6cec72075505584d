"""PyTorch and kornia front end: the soft HSI segmentation in torch, and a gradient bridge to JAX.

Optional: needs the ``torch`` extra (``pip install 'sinkjax[torch]'``). Images are kornia's
``(B, 3, H, W)`` RGB in [0, 1]; masks are ``(B, 1, H, W)`` in [0, 1] (1 = wheel).

- :func:`rgb_to_hsi`, :func:`soft_hsi_mask` / :class:`SoftHSISegmenter`, :func:`smooth_mask`,
  :func:`soft_open`: the paper's HSI segmentation, equal to :mod:`sinkjax.soft.segmentation` to
  float64 round-off, differentiable with respect to the image and the six thresholds.
- :func:`measure_torch` / :class:`SinkageFromMask` / :class:`SinkageFromImage`: z0, theta1,
  theta2 and their one-sigma from the JAX estimator, as torch tensors whose backward is JAX's VJP
  (through the implicit-differentiated fit). Tensors cross by DLPack.
- :func:`lighting_augmentation`: kornia photometric augmentations for robustness studies.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

try:
    import kornia
    import torch
    from torch import Tensor, nn
except ImportError as e:  # pragma: no cover - exercised only without the extra
    raise ImportError(
        "sinkjax.torch needs PyTorch and kornia; install them with: pip install 'sinkjax[torch]'"
    ) from e

import jax
import jax.numpy as jnp
import numpy as np

from ..rig import HUE_SCALE_DEG, SegmentationParams
from ..soft.uncertainty import UncertaintyModel
from ..status import Status
from . import jax_bridge as _bridge

__all__ = [
    "MeasureFromMask",
    "RgbToHsi",
    "SinkageFromImage",
    "SinkageFromMask",
    "SoftHSISegmenter",
    "Status",
    "TorchEstimate",
    "lighting_augmentation",
    "measure_torch",
    "rgb_to_hsi",
    "smooth_mask",
    "soft_hsi_mask",
    "soft_open",
]

_EPS = 1e-12
SEG_FIELDS = _bridge.SEG_FIELDS


def _check_images(images: Any, name: str = "images") -> None:
    if not isinstance(images, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor. Got {type(images)}")
    if images.dim() != 4 or images.shape[1] != 3:
        raise ValueError(f"{name} must have a shape of (B, 3, H, W). Got {tuple(images.shape)}")
    if not images.is_floating_point():
        raise TypeError(f"{name} must be floating point in [0, 1]. Got {images.dtype}")


def _check_masks(masks: Any, images: Tensor) -> None:
    if not isinstance(masks, Tensor):
        raise TypeError(f"masks must be a torch.Tensor. Got {type(masks)}")
    b, _, h, w = images.shape
    if tuple(masks.shape) != (b, 1, h, w):
        raise ValueError(
            f"masks must have a shape of (B, 1, H, W) = {(b, 1, h, w)} to match the images. "
            f"Got {tuple(masks.shape)}"
        )


def _check_rect(rect: Any, height: int, width: int) -> tuple[int, int, int, int]:
    if (
        not isinstance(rect, tuple | list)
        or len(rect) != 4
        or not all(isinstance(v, int) and not isinstance(v, bool) for v in rect)
    ):
        raise ValueError(f"rect must be four integers (x, y, w, h) in pixels. Got {rect!r}")
    x, y, w, h = rect
    if x < 0 or y < 0 or w < 1 or h < 1 or x + w > width or y + h > height:
        raise ValueError(f"confidence rectangle {list(rect)} is off the {width}x{height} image")
    return (x, y, w, h)


# ----------------------------------------------------------------------------- colour


def rgb_to_hsi(image: Tensor) -> Tensor:
    """The paper's HSI of an RGB image: hue in degrees [0, 360), saturation and intensity in [0, 1].

    Same formula as :func:`sinkjax.soft.colour.rgb_to_hsi` (hue as ``atan2(sqrt(3) (G - B),
    2R - G - B)``), not kornia's HSV. Grey pixels get H = 0 and black pixels S = 0, with zero
    (not NaN) gradients there.

    Args:
        image: RGB in [0, 1] with shape :math:`(*, 3, H, W)`.

    Returns:
        HSI with shape :math:`(*, 3, H, W)`.

    Example:
        >>> hsi = rgb_to_hsi(torch.rand(2, 3, 4, 5))
        >>> hsi.shape
        torch.Size([2, 3, 4, 5])
    """
    if not isinstance(image, Tensor):
        raise TypeError(f"Input type is not a torch.Tensor. Got {type(image)}")
    if image.dim() < 3 or image.shape[-3] != 3:
        raise ValueError(f"Input size must have a shape of (*, 3, H, W). Got {tuple(image.shape)}")
    r, g, b = image[..., 0, :, :], image[..., 1, :, :], image[..., 2, :, :]
    cx = 2.0 * r - g - b
    cy = (3.0**0.5) * (g - b)
    grey = cx * cx + cy * cy <= _EPS
    # Double where: atan2(0, 0) has a NaN gradient even in the branch torch.where does not take.
    h = torch.rad2deg(
        torch.atan2(torch.where(grey, torch.zeros_like(cy), cy), torch.where(grey, 1.0, cx))
    )
    h = torch.where(grey, torch.zeros_like(h), torch.remainder(h, 360.0))
    total = r + g + b
    dark = total <= _EPS
    ratio = torch.amin(image, dim=-3) / torch.where(dark, torch.ones_like(total), total)
    s = torch.where(dark, torch.zeros_like(total), 1.0 - 3.0 * ratio)
    return torch.stack([h, s, total / 3.0], dim=-3)


class RgbToHsi(nn.Module):
    """Module form of :func:`rgb_to_hsi`: :math:`(*, 3, H, W)` -> :math:`(*, 3, H, W)`."""

    def forward(self, image: Tensor) -> Tensor:
        return rgb_to_hsi(image)


def _circular_mean_deg(angles_deg: Tensor) -> Tensor:
    # Over the last two dims; (*, h, w) -> (*,). Zero for a perfectly balanced set, as in JAX.
    rad = torch.deg2rad(angles_deg)
    c = torch.cos(rad).mean(dim=(-2, -1))
    s = torch.sin(rad).mean(dim=(-2, -1))
    flat = c * c + s * s <= _EPS
    m = torch.rad2deg(
        torch.atan2(torch.where(flat, torch.zeros_like(s), s), torch.where(flat, 1.0, c))
    )
    return torch.where(flat, torch.zeros_like(m), torch.remainder(m, 360.0))


def _wrap_deg(angle_deg: Tensor) -> Tensor:
    return torch.remainder(angle_deg + 180.0, 360.0) - 180.0


# ----------------------------------------------------------------------------- segmentation


def _param_tensors(
    params: SegmentationParams | Mapping[str, Tensor | float], like: Tensor
) -> dict[str, Tensor]:
    if isinstance(params, SegmentationParams):
        items: Mapping[str, Any] = params.as_dict()
    elif isinstance(params, Mapping):
        items = params
    else:
        raise TypeError(
            f"params must be a SegmentationParams or a mapping of {SEG_FIELDS}. Got {type(params)}"
        )
    missing = [n for n in SEG_FIELDS if n not in items]
    if missing:
        raise ValueError(f"params lacks {missing}; it needs all of {SEG_FIELDS}")
    out = {}
    for n in SEG_FIELDS:
        v = items[n]
        # A Python float goes straight to the images' dtype (via float32 it would lose ~1e-8).
        v = v if isinstance(v, Tensor) else torch.as_tensor(v, dtype=like.dtype)
        if v.numel() != 1:
            raise ValueError(f"params[{n!r}] must be a scalar. Got shape {tuple(v.shape)}")
        out[n] = v.reshape(()).to(dtype=like.dtype, device=like.device)
    return out


def soft_hsi_mask(
    images: Tensor,
    params: SegmentationParams | Mapping[str, Tensor | float],
    rect: tuple[int, int, int, int],
) -> Tensor:
    """Soft wheel mask of RGB images: the paper's H/S band test as a product of four sigmoids.

    Equal to :func:`sinkjax.soft.segmentation.wheel_mask` per image: the band is centred on the
    circular mean hue H_w and the mean saturation S_w of the confidence rectangle ``rect`` =
    (x, y, w, h) px; hue limits are H_w + (P - 1) 180 deg, saturation limits P S_w; the
    temperatures set the sigmoid widths.

    Args:
        images: RGB in [0, 1] with shape :math:`(B, 3, H, W)`.
        params: a :class:`~sinkjax.SegmentationParams`, or a mapping from its six field names to
            scalar tensors (gradients reach them).
        rect: confidence rectangle (x, y, w, h) in pixels, inside the image.

    Returns:
        Mask in [0, 1] with shape :math:`(B, 1, H, W)`.

    Example:
        >>> m = soft_hsi_mask(torch.rand(2, 3, 32, 32), SegmentationParams(), (8, 8, 4, 4))
        >>> m.shape
        torch.Size([2, 1, 32, 32])
    """
    _check_images(images)
    rect = _check_rect(rect, images.shape[-2], images.shape[-1])
    p = _param_tensors(params, images)
    hsi = rgb_to_hsi(images)
    h, s = hsi[:, 0], hsi[:, 1]
    x, y, w, hh = rect
    h_w = _circular_mean_deg(h[:, y : y + hh, x : x + w])[:, None, None]
    s_w = s[:, y : y + hh, x : x + w].mean(dim=(-2, -1))[:, None, None]
    h_lo = (p["p_d_hue"] - 1.0) * HUE_SCALE_DEG
    h_hi = (p["p_a_hue"] - 1.0) * HUE_SCALE_DEG
    s_lo = p["p_d_sat"] * s_w
    s_hi = p["p_a_sat"] * s_w
    dh = _wrap_deg(h - h_w)
    th, ts = p["temperature_hue_deg"], p["temperature_sat"]
    m_h = torch.sigmoid((dh - h_lo) / th) * torch.sigmoid((h_hi - dh) / th)
    m_s = torch.sigmoid((s - s_lo) / ts) * torch.sigmoid((s_hi - s) / ts)
    return (m_h * m_s)[:, None]


class SoftHSISegmenter(nn.Module):
    """:func:`soft_hsi_mask` with the six thresholds as ``nn.Parameter`` scalars.

    Args:
        rect: confidence rectangle (x, y, w, h) in pixels.
        params: initial thresholds (default: ``SegmentationParams()``).
        dtype: of the parameters (default: torch's default dtype). Pass ``torch.float64`` rather
            than calling ``.double()`` later, which would start from float32-rounded values.

    Shape:
        images :math:`(B, 3, H, W)` -> mask :math:`(B, 1, H, W)`.

    Example:
        >>> seg = SoftHSISegmenter((8, 8, 4, 4))
        >>> seg(torch.rand(1, 3, 32, 32)).shape
        torch.Size([1, 1, 32, 32])
    """

    def __init__(
        self,
        rect: tuple[int, int, int, int],
        params: SegmentationParams | None = None,
        *,
        dtype: torch.dtype | None = None,
    ) -> None:
        super().__init__()
        if not isinstance(rect, tuple | list) or len(rect) != 4:
            raise ValueError(f"rect must be (x, y, w, h) in pixels. Got {rect!r}")
        self.rect = tuple(int(v) for v in rect)
        init = (params or SegmentationParams()).as_dict()
        for name in SEG_FIELDS:
            self.register_parameter(
                name,
                nn.Parameter(torch.tensor(init[name], dtype=dtype or torch.get_default_dtype())),
            )

    def params(self) -> dict[str, Tensor]:
        return {name: getattr(self, name) for name in SEG_FIELDS}

    def to_segmentation_params(self) -> SegmentationParams:
        """The current thresholds as a JAX :class:`~sinkjax.SegmentationParams` (for a rig)."""
        values = {n: jnp.asarray(float(v.detach())) for n, v in self.params().items()}
        return SegmentationParams(**values)

    def forward(self, images: Tensor) -> Tensor:
        return soft_hsi_mask(images, self.params(), self.rect)  # type: ignore[arg-type]


def smooth_mask(mask: Tensor) -> Tensor:
    """Binomial [1, 4, 6, 4, 1]/16 blur (sigma ~ 1 px) with edge replication, via kornia.

    Equal to :func:`sinkjax.soft.segmentation.smooth`, the soft stand-in for the paper's
    dilation-then-erosion. Shape :math:`(B, C, H, W)` -> :math:`(B, C, H, W)`.
    """
    if not isinstance(mask, Tensor) or mask.dim() != 4:
        raise ValueError(
            f"mask must have a shape of (B, C, H, W). Got {getattr(mask, 'shape', mask)}"
        )
    taps = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0], dtype=mask.dtype, device=mask.device) / 16.0
    return kornia.filters.filter2d_separable(
        mask, taps[None], taps[None], border_type="replicate", normalized=False
    )


def soft_open(mask: Tensor, radius_px: int = 1) -> Tensor:
    """Grey-level opening (min then max over a (2 r + 1)^2 square), via kornia.morphology.

    Equal to :func:`sinkjax.soft.segmentation.soft_open` (pixels outside the image are ignored).
    Shape :math:`(B, C, H, W)` -> :math:`(B, C, H, W)`. Raises ValueError for ``radius_px < 1``.
    """
    if not isinstance(mask, Tensor) or mask.dim() != 4:
        raise ValueError(
            f"mask must have a shape of (B, C, H, W). Got {getattr(mask, 'shape', mask)}"
        )
    if not isinstance(radius_px, int) or radius_px < 1:
        raise ValueError(f"radius_px must be a positive integer. Got {radius_px!r}")
    size = 2 * radius_px + 1
    kernel = torch.ones(size, size, dtype=mask.dtype, device=mask.device)
    return kornia.morphology.opening(mask, kernel, border_type="geodesic")


# ----------------------------------------------------------------------------- bridge to JAX


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
        ctx: Any, batch: _bridge.JittedBatch, n_batched: int, *inputs: Tensor
    ) -> tuple[Tensor, Tensor]:
        dtype = _jax_float()
        xs = [_to_jax(t, dtype) for t in inputs]
        needs_grad = any(ctx.needs_input_grad[: len(inputs)])
        if needs_grad:
            values, status, vjp = batch.forward_vjp(*xs)
            # A frame whose fit failed (non-finite parameters) makes the implicit-function linear
            # solve of the backward pass raise for the whole batch. Its gradient is 0 anyway
            # (nothing it reports is usable), so residuals are recomputed with such frames
            # replaced by a healthy one, whose cotangent backward then zeroes.
            dead = ~np.all(np.isfinite(np.asarray(values)), axis=-1) | (
                np.asarray(status) == _bridge.FIT_FAILED
            )
            if dead.any():
                healthy = np.flatnonzero(~dead)
                if healthy.size == 0:
                    vjp = None
                else:
                    take = jnp.asarray(np.where(dead, healthy[0], np.arange(dead.size)))
                    swapped = [x[take] if k < n_batched else x for k, x in enumerate(xs)]
                    vjp = batch.forward_vjp(*swapped)[2]
            ctx.vjp = vjp
            ctx.dead = torch.from_numpy(dead).to(inputs[0].device)
            ctx.batch = batch
            # JAX may keep aliases of the DLPack-shared inputs among its residuals: saving the
            # tensors lets torch's version counter catch an in-place edit before backward.
            ctx.save_for_backward(*inputs)
        else:
            values, status = batch.forward(*xs)
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
        batch = _bridge.from_mask_batch(travel, float(wheel_radius_mm), uncertainty)
        return _JaxFunction._run(ctx, batch, 2, images, masks)

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
        batch = _bridge.from_image_batch(
            tuple(rect), travel, float(wheel_radius_mm), uncertainty, open_radius_px
        )
        return _JaxFunction._run(ctx, batch, 1, images, seg_vector)

    @staticmethod
    def backward(ctx: Any, g_values: Tensor, g_status: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        return (*_JaxFunction._grad(ctx, g_values), None, None, None, None, None)


class TorchEstimate(NamedTuple):
    """Per-frame results, each shape (B,). ``status`` indexes :class:`sinkjax.Status` codes (0 = ok)."""

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
        open_radius_px: without masks, as in :func:`sinkjax.soft.estimator.measure`; with masks, apply
            :func:`soft_open` to them yourself.

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
        rect = _check_rect(rect, images.shape[-2], images.shape[-1])
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


# ----------------------------------------------------------------------------- augmentation


def lighting_augmentation(
    *,
    p: float = 0.5,
    shadow: bool = True,
    colour_jitter: bool = True,
    planckian: bool = True,
    noise_std: float = 0.02,
) -> kornia.augmentation.AugmentationSequential:
    """Photometric kornia augmentations mimicking the lighting a rig sees (no geometry changes).

    Plasma-fractal shadows (:class:`~kornia.augmentation.RandomPlasmaShadow`), brightness /
    contrast / saturation / small hue jitter (``ColorJitter``), black-body illuminant changes
    (``RandomPlanckianJitter``) and sensor noise (``RandomGaussianNoise``), each applied with
    probability ``p``. Geometry is untouched, so sinkage and angle labels stay valid.

    Shape: :math:`(B, 3, H, W)` in [0, 1] -> same (clipped to [0, 1]).

    Example:
        >>> aug = lighting_augmentation()
        >>> aug(torch.rand(2, 3, 32, 32)).shape
        torch.Size([2, 3, 32, 32])
    """
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"p must be in [0, 1]. Got {p}")
    aug = kornia.augmentation
    ops: list[nn.Module] = []
    if shadow:
        ops.append(aug.RandomPlasmaShadow(roughness=(0.1, 0.7), shade_intensity=(-0.5, 0.0), p=p))
    if colour_jitter:
        ops.append(aug.ColorJitter(brightness=0.2, contrast=0.2, saturation=0.2, hue=0.02, p=p))
    if planckian:
        ops.append(aug.RandomPlanckianJitter(mode="blackbody", p=p))
    if noise_std > 0:
        ops.append(aug.RandomGaussianNoise(mean=0.0, std=noise_std, p=p))
    ops.append(_Clip())
    # AugmentationSequential runs plain nn.Modules too (the final clip); its annotation is narrower.
    return aug.AugmentationSequential(*ops)  # type: ignore[arg-type]


class _Clip(nn.Module):
    def forward(self, x: Tensor) -> Tensor:
        return x.clamp(0.0, 1.0)
