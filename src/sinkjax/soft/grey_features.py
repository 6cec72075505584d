"""The features a wheel without colour is told from soil by (:mod:`~sinkjax.soft.adaptive`):
local texture, and chroma in two forms.

Texture is the local intensity spread around a least-squares plane (shading is a gradient, not
texture), taken from the one of a pixel's four corner windows that is smoothest (a pixel next to
an edge keeps its own side's spread); :func:`pooled_texture` averages it over larger windows
(taking the roughest of the four), so a few smooth grains of sand do not pass for a smooth face.

Chroma is the opponent colour ``(R - (G + B)/2, sqrt(3)/2 (G - B))`` (RGB units). Its distance
from the confidence rectangle's mean (:func:`chroma_distance`) shrinks with the light: a brown
soil in the wheel's shadow is nearly as grey as the wheel. Divided by the intensity
(:func:`chromaticity_distance`) it does not: a surface's chromaticity is its albedo's under one
light, so shadowed brown soil stays as far from a bare-metal wheel's as lit soil.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .histogram import binned_histogram, log_quantile

TEX_WINDOW_PX = 5  # one-sided texture windows, px on a side
_INTENSITY_FLOOR = 0.02  # chromaticity: the intensity divided by, at least (noise in black)


def _box_mean(a: Float[Array, "H W"], size: int) -> Float[Array, "h w"]:
    # Mean over every size x size window lying inside ``a`` (index = the window's top-left).
    s = jax.lax.reduce_window(a, 0.0, jax.lax.add, (size, size), (1, 1), "VALID")
    return s / float(size * size)


def _window_moments(a: Float[Array, "H W"], size: int) -> tuple[Array, Array]:
    # Sums of a * (x offset) and a * (y offset) from each size x size window's centre, over
    # every window lying inside ``a`` (index = the window's top-left): column (row) sums of
    # the window, weighted by their offsets (slices: a convolution is slower on a CPU).
    height, width = a.shape
    h, w = height - size + 1, width - size + 1
    cols = jax.lax.reduce_window(a, 0.0, jax.lax.add, (size, 1), (1, 1), "VALID")
    rows = jax.lax.reduce_window(a, 0.0, jax.lax.add, (1, size), (1, 1), "VALID")
    offsets = [j - 0.5 * (size - 1) for j in range(size)]
    sx = sum(o * cols[:, j : j + w] for j, o in enumerate(offsets))
    sy = sum(o * rows[i : i + h, :] for i, o in enumerate(offsets))
    return sx, sy


def texture(intensity: Float[Array, "H W"], size: int = TEX_WINDOW_PX) -> Float[Array, "H W"]:
    """Local intensity spread: the std of the residual of a least-squares plane over a
    size x size window (shading is a gradient, not texture), the smallest over the four windows
    that have the pixel at a corner (the image edge-replicated): a pixel next to an edge keeps
    the spread of its own side."""
    k = size - 1
    p = jnp.pad(intensity, k, mode="edge")
    mean = _box_mean(p, size)
    var = jnp.maximum(_box_mean(p * p, size) - mean * mean, 0.0)
    # The plane's share: x and y offsets from the window's centre are orthogonal, so each
    # slope's explained variance is (sum I dx)^2 / (n sum dx^2).
    sxx = float(size * np.sum((np.arange(size) - 0.5 * k) ** 2))
    sx, sy = _window_moments(p, size)
    var = jnp.maximum(var - (sx * sx + sy * sy) / (sxx * size * size), 0.0)
    h, w = intensity.shape
    # var[a, b] is the window whose top-left pixel is (a - k, b - k): the pixel's own windows
    # start at offsets 0 (pixel bottom/right) and k (pixel top/left).
    corners = [var[dy : dy + h, dx : dx + w] for dy in (0, k) for dx in (0, k)]
    v = jnp.min(jnp.stack(corners), axis=0)
    # Double where: sqrt has an infinite derivative at 0 (a flat window).
    pos = v > 1e-12
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, v, 1.0)), 0.0)


def pooled_texture(tex: Float[Array, "H W"], size: int) -> Float[Array, "H W"]:
    """``tex`` averaged over size x size: the most of the 4 windows with the pixel at a corner."""
    k = size - 1
    mean = _box_mean(jnp.pad(tex, k, mode="edge"), size)
    h, w = tex.shape
    return jnp.max(jnp.stack([mean[dy : dy + h, dx : dx + w] for dy in (0, k) for dx in (0, k)]), 0)


_TEX_SPAN = (float(np.log(1e-4)), float(np.log(0.1)), 64)  # log texture histogram


def face_texture(tex: Float[Array, "H W"], weight: Float[Array, "H W"]) -> Float[Array, ""]:
    """The 95th percentile of ``tex`` over 0/1 ``weight`` (the face: the upper half of the
    rim's inside, where the mask sees wheel), from a histogram of its log (11 % bins). Not
    differentiable (a choice of bin)."""
    log_t = jnp.log(jnp.maximum(jax.lax.stop_gradient(tex), 1e-4))
    hist, centres = binned_histogram(log_t, weight, _TEX_SPAN, (1,), clip=True)
    return jnp.exp(log_quantile(hist, centres, 0.95))


def safe_norm(a1: Array, a2: Array) -> Array:
    """|(a1, a2)| with a finite gradient at 0 (double where)."""
    d2 = a1 * a1 + a2 * a2
    pos = d2 > 1e-24
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, d2, 1.0)), 0.0)


def chroma_distance(
    q1: Float[Array, "H W"], q2: Float[Array, "H W"], weight: Float[Array, "H W"]
) -> tuple[Float[Array, "H W"], Float[Array, ""]]:
    """Each pixel's opponent-chroma distance from the ``weight``-ed mean (the confidence
    rectangle), and the rectangle's spread of it (its RMS), RGB units."""
    total = jnp.maximum(jnp.sum(weight), 1.0)
    d1 = q1 - jnp.sum(weight * q1) / total
    d2 = q2 - jnp.sum(weight * q2) / total
    spread = jnp.sqrt(jnp.sum(weight * (d1 * d1 + d2 * d2)) / total + 1e-12)
    return safe_norm(d1, d2), spread


def chromaticity_distance(
    q1: Float[Array, "H W"],
    q2: Float[Array, "H W"],
    intensity: Float[Array, "H W"],
    weight: Float[Array, "H W"],
) -> tuple[Float[Array, "H W"], Float[Array, ""]]:
    """:func:`chroma_distance` of the chroma divided by the intensity (at least 0.02): the
    distance does not shrink in shadow."""
    den = jnp.maximum(intensity, _INTENSITY_FLOOR)
    return chroma_distance(q1 / den, q2 / den, weight)
