"""Low light: a coloured wheel's hue drowned in sensor noise, and the blur that brings it back.

The H/S test reads each pixel's hue and saturation, which are the direction and length of its
opponent chroma ``(R - (G + B)/2, sqrt(3)/2 (G - B))``. Sensor noise of ``sigma`` per channel
(independent, RGB units) puts noise of ``sqrt(3/2) sigma`` on each chroma component, whatever
the light; the wheel's chroma ``|c_w|`` shrinks with the light. In a dim frame (a wheel at 15 %
of full scale, noise of 1.3 %) the ratio ``sqrt(3/2) sigma / |c_w|`` is 0.5-1: the hue of single
pixels is a coin toss, the mask is salt and pepper, the outline has edges everywhere and no rim
circle is found (``no_wheel``), or the fit reads a boundary in the noise.

Averaging ``n`` pixels divides the noise by ``sqrt(n)``: a Gaussian blur of ``s`` px divides
white noise by ``2 sqrt(pi) s``. :func:`denoise` measures ``sigma`` in the confidence rectangle
(the median absolute difference of horizontally adjacent pixels: the face is smooth, and the
median ignores the few edges of holes or lugs in it) and blurs the frame with the ``s`` that
takes the ratio down to ``TARGET_RATIO``, ramped in between ``RATIO_OFF`` and ``RATIO_ON`` (below
it the frame is returned unchanged, so normal footage gives the same numbers as without this
step). A symmetric blur keeps a straight edge where it is; the rim's and the soil line's
curvature over a blur of a few px moves them by a small fraction of a px. The blur makes
neighbouring outline points' errors move together: the measurement's sigma widens to match
(:func:`sigma_factor`), or the frame's smaller scatter would read as precision.

The blur's width is a choice from the frame's statistics (no gradient flows through it); the
image itself is blurred linearly, so gradients with respect to the image still flow.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .segmentation import Rect, rect_values

RATIO_OFF = 0.15  # noise / wheel chroma at which the blur starts
RATIO_ON = 0.25  # ... and is fully on
TARGET_RATIO = 0.05  # the ratio after the blur
MAX_SIGMA_PX = 6.0
_TAPS = 18  # kernel half-width, px (3 sigma at the largest)
_MAD_TO_SIGMA = 1.4826 / math.sqrt(2.0)  # MAD of a difference of two -> one pixel's sigma
_SQRT3_2 = math.sqrt(3.0) / 2.0


def noise_ratio(image: Float[Array, "H W 3"], rect: Rect | Int[Array, " 4"]) -> Float[Array, ""]:
    """Per-pixel chroma noise over the wheel's chroma, both in the confidence rectangle: the
    noise from adjacent-pixel differences (robust), the chroma from the rectangle's mean."""
    here = rect_values(image, rect)
    right = rect_values(image, rect, dx=1)
    diff = (right - here).reshape(-1)
    mad = jnp.median(jnp.abs(diff - jnp.median(diff)))
    sigma = _MAD_TO_SIGMA * mad
    mean = jnp.mean(here, axis=0)
    q1 = mean[0] - 0.5 * (mean[1] + mean[2])
    q2 = _SQRT3_2 * (mean[1] - mean[2])
    chroma = jnp.sqrt(q1 * q1 + q2 * q2 + 1e-12)
    return jax.lax.stop_gradient(math.sqrt(1.5) * sigma / jnp.maximum(chroma, 1e-3))


def _gauss_axis(a: Float[Array, "H W C"], sigma: Float[Array, ""], axis: int) -> Array:
    # A normalised Gaussian of width ``sigma`` (traced) over 2 * _TAPS + 1 px, edge-replicated.
    offsets = jnp.arange(-_TAPS, _TAPS + 1, dtype=a.dtype)
    w = jnp.exp(-0.5 * (offsets / jnp.maximum(sigma, 0.3)) ** 2)
    w = w / jnp.sum(w)
    pad = [(0, 0)] * a.ndim
    pad[axis] = (_TAPS, _TAPS)
    p = jnp.pad(a, pad, mode="edge")
    n = a.shape[axis]
    out = jnp.zeros_like(a)
    for i in range(2 * _TAPS + 1):
        out = out + w[i] * jax.lax.slice_in_dim(p, i, i + n, axis=axis)
    return out


def _share(ratio: Float[Array, ""]) -> Float[Array, ""]:
    # The blur's ramp: 0 up to RATIO_OFF, 1 from RATIO_ON.
    return jnp.clip((ratio - RATIO_OFF) / (RATIO_ON - RATIO_OFF), 0.0, 1.0)


def blur_sigma_px(ratio: Float[Array, ""]) -> Float[Array, ""]:
    """The blur that takes a noise ratio to TARGET_RATIO (white noise / (2 sqrt(pi) s))."""
    return jnp.clip(ratio / (TARGET_RATIO * 2.0 * math.sqrt(math.pi)), 1.0, MAX_SIGMA_PX)


def applied_blur_px(
    image: Float[Array, "H W 3"],
    rect: Rect | Int[Array, " 4"],
    ratio: Float[Array, ""] | None = None,
) -> Float[Array, ""]:
    """The blur :func:`denoise` applies, as a Gaussian's sigma in px (the ramp's share times its
    width; 0 where the frame is returned unchanged)."""
    ratio = noise_ratio(image, rect) if ratio is None else ratio
    return _share(ratio) * blur_sigma_px(ratio)


def sigma_factor(blur_px: Float[Array, ""]) -> Float[Array, ""]:
    """How much wider a measurement's sigma is for an image blurred by ``blur_px`` before it was
    segmented: the blur divides the outline's residual scatter, from which the delta method takes
    its sigma, but makes neighbouring residuals move together over ~2 sqrt(pi) times the total
    smoothing (the mask's own, about 1 px, and the blur, in quadrature), so the independent
    points are fewer by the same factor: variance times sqrt(1 + blur^2), sigma times its square
    root. 1 without a blur."""
    return (1.0 + blur_px * blur_px) ** 0.25


def denoise(
    image: Float[Array, "H W 3"],
    rect: Rect | Int[Array, " 4"],
    ratio: Float[Array, ""] | None = None,
) -> Float[Array, "H W 3"]:
    """``image`` blurred as its noise asks (module docstring); unchanged (and nothing computed
    beyond the rectangle's statistics) where the noise ratio is below RATIO_OFF. ``ratio``: its
    :func:`noise_ratio`, where the caller has it."""
    ratio = noise_ratio(image, rect) if ratio is None else ratio
    share = _share(ratio)

    def blurred() -> Array:
        sigma = blur_sigma_px(ratio)
        b = _gauss_axis(_gauss_axis(image, sigma, 0), sigma, 1)
        return image + share * (b - image)

    return jax.lax.cond(share > 0.0, blurred, lambda: image)
