"""Segmentation stage: the paper's H/S range test as soft masks, and soft clean-up.

The hard test H_d <= H <= H_a and S_d <= S <= S_a becomes a product of sigmoids whose widths are
the temperatures in :class:`~sinkjax.SegmentationParams`; as they go to zero the mask becomes the
classic binary mask. Hue is compared circularly around the wheel's mean hue H_w.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..rig import HUE_SCALE_DEG, SegmentationParams, rect_problem
from .colour import circular_mean_deg, rgb_to_hsi, wrap_deg

# The confidence rectangle (x, y, w, h) in px: static ints, or a traced array (see below).
Rect = tuple[int, int, int, int] | Int[Array, " 4"]


def confidence_means(
    h_deg: Float[Array, "H W"], s: Float[Array, "H W"], rect: Rect
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Eqs. 4-5: H_w (circular mean, degrees) and S_w over the confidence rectangle (x, y, w, h).

    ``rect`` is a tuple of ints (static: the rectangle is sliced out; raises ValueError if it
    does not lie inside the image) or an int array of 4 (traced: a masked mean over the image,
    so one compiled function serves every rectangle; the caller checks it with
    :func:`sinkjax.rig.rect_problem`).
    """
    height, width = h_deg.shape[-2:]
    if isinstance(rect, tuple | list):
        problem = rect_problem(tuple(rect), height, width)
        if problem is not None:
            raise ValueError(problem)
        x, y, w, h = rect
        return circular_mean_deg(h_deg[y : y + h, x : x + w]), jnp.mean(s[y : y + h, x : x + w])
    x0, y0, w0, h0 = (rect[i] for i in range(4))
    cols = jnp.arange(width, dtype=rect.dtype)
    rows = jnp.arange(height, dtype=rect.dtype)
    inside = ((rows >= y0) & (rows < y0 + h0))[:, None] & ((cols >= x0) & (cols < x0 + w0))[None, :]
    weight = inside.astype(s.dtype)
    count = jnp.maximum(jnp.sum(weight), 1.0)
    return circular_mean_deg(h_deg, weight), jnp.sum(weight * s) / count


def band_limits(
    h_w_deg: Float[Array, ""], s_w: Float[Array, ""], seg: SegmentationParams
) -> tuple[Float[Array, ""], Float[Array, ""], Float[Array, ""], Float[Array, ""]]:
    """(hue low, hue high) as offsets from H_w in degrees, and (S_d, S_a)."""
    return (
        (seg.p_d_hue - 1.0) * HUE_SCALE_DEG,
        (seg.p_a_hue - 1.0) * HUE_SCALE_DEG,
        seg.p_d_sat * s_w,
        seg.p_a_sat * s_w,
    )


def soft_mask(
    h_deg: Float[Array, "H W"],
    s: Float[Array, "H W"],
    h_w_deg: Float[Array, ""],
    s_w: Float[Array, ""],
    seg: SegmentationParams,
) -> Float[Array, "H W"]:
    """Soft wheel mask in [0, 1]: sigmoids of the distances to the four band limits."""
    h_lo, h_hi, s_lo, s_hi = band_limits(h_w_deg, s_w, seg)
    dh = wrap_deg(h_deg - h_w_deg)
    th = seg.temperature_hue_deg
    ts = seg.temperature_sat
    m_h = jax.nn.sigmoid((dh - h_lo) / th) * jax.nn.sigmoid((h_hi - dh) / th)
    m_s = jax.nn.sigmoid((s - s_lo) / ts) * jax.nn.sigmoid((s_hi - s) / ts)
    return m_h * m_s


def wheel_mask(
    image: Float[Array, "H W 3"], seg: SegmentationParams, rect: Rect
) -> Float[Array, "H W"]:
    """Image in [0, 1] -> soft wheel mask, the paper's steps (2)-(3) made differentiable."""
    h, s, _ = rgb_to_hsi(image)
    h_w, s_w = confidence_means(h, s, rect)
    return soft_mask(h, s, h_w, s_w, seg)


def _blur_axis(a: Float[Array, "H W"], axis: int) -> Float[Array, "H W"]:
    # Binomial [1, 4, 6, 4, 1]/16 (sigma = 1 px) with edge replication: cheap and separable.
    pad = [(0, 0), (0, 0)]
    pad[axis] = (2, 2)
    p = jnp.pad(a, pad, mode="edge")
    n = a.shape[axis]
    taps = (1.0, 4.0, 6.0, 4.0, 1.0)
    out = jnp.zeros_like(a)
    for i, t in enumerate(taps):
        out = out + t * jax.lax.slice_in_dim(p, i, i + n, axis=axis)
    return out / 16.0


def smooth(mask: Float[Array, "H W"]) -> Float[Array, "H W"]:
    """Gaussian-like smoothing (sigma ~ 1 px): the soft stand-in for dilation-then-erosion.

    Isolated mis-classified pixels (sensor noise, soil grains of wheel colour) drop below 0.5 and
    stop producing edges, while real edges keep their sub-pixel position (the blur is symmetric).
    """
    return _blur_axis(_blur_axis(mask, 0), 1)


def soft_open(mask: Float[Array, "H W"], radius_px: int = 1) -> Float[Array, "H W"]:
    """Grey-level opening (min filter then max filter) of a soft mask: removes thin spurs.

    The grey-level generalisation of the paper's erosion/dilation; piecewise differentiable.
    """
    size = 2 * radius_px + 1
    window = (size, size)
    er = -jax.lax.reduce_window(-mask, -jnp.inf, jax.lax.max, window, (1, 1), "SAME")
    return jax.lax.reduce_window(er, -jnp.inf, jax.lax.max, window, (1, 1), "SAME")
