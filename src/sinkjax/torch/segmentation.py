"""The paper's HSI segmentation as torch ops (kornia style): colour, soft mask, clean-up.

Each function equals its JAX twin in :mod:`sinkjax.soft.colour` / :mod:`sinkjax.soft.segmentation`
to float64 round-off and is differentiable with respect to the image and the six thresholds.
Images are ``(B, 3, H, W)`` RGB in [0, 1]; masks ``(B, 1, H, W)`` in [0, 1] (1 = wheel). The input
checks here are shared with :mod:`sinkjax.torch.bridge`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import jax.numpy as jnp
import kornia
import torch
from torch import Tensor, nn

from ..rig import HUE_SCALE_DEG, SEG_FIELDS, SegmentationParams, rect_problem

__all__ = [
    "RgbToHsi",
    "SoftHSISegmenter",
    "rgb_to_hsi",
    "smooth_mask",
    "soft_hsi_mask",
    "soft_open",
]

_EPS = 1e-12


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


def _valid_rect(rect: Any, height: int, width: int) -> tuple[int, int, int, int]:
    # The rule is sinkjax.rig.rect_problem's, shared with the JAX estimators and the CLI.
    problem = rect_problem(rect, height, width)
    if problem is not None:
        raise ValueError(problem)
    x, y, w, h = rect
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

    Equal to :func:`sinkjax.soft.segmentation.paper_mask` per image: the band is centred on the
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
    rect = _valid_rect(rect, images.shape[-2], images.shape[-1])
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
