"""Per-pixel colour features, normalised by the confidence rectangle's own statistics.

A learned segmenter should carry across wheels, soils and lamps. The one thing every rig says
about its wheel is the confidence rectangle (docs/conventions.md §2): a patch that is always wheel
face. So every pixel's colour features are given to the networks *relative to that patch*:
``(f - mean) / spread`` and ``f - mean``, where mean and spread are the rectangle's. A red wheel
under a warm lamp and a grey wheel in low light then look alike to the network: "like the face"
or "not like the face", in the face's own units.

Features (:data:`FEATURE_NAMES`): R, G, B, the paper's intensity I and saturation S, and the
chroma vector (S cos H, S sin H), which is continuous where hue wraps and vanishes for grey
pixels (no hue singularity, finite gradients).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..soft.colour import rgb_to_hsi
from ..soft.segmentation import Rect

FEATURE_NAMES = ("r", "g", "b", "intensity", "saturation", "chroma_x", "chroma_y")
N_FEATURES = len(FEATURE_NAMES)
# Inputs to a network per pixel: the normalised features and the plain differences.
N_INPUTS = 2 * N_FEATURES
# The spread never drops below this (units of [0, 1] colour): a perfectly flat patch (a
# synthetic face, a saturated sensor) must not make every other pixel infinitely far away.
SPREAD_FLOOR = 0.01
# Normalised features are squashed to +-Z_LIMIT: beyond a few spreads "not the face" is all
# that matters, and bounded inputs keep a tiny network's activations in range.
Z_LIMIT = 6.0


def pixel_features(image: Float[Array, "H W 3"]) -> Float[Array, "H W F"]:
    """The :data:`FEATURE_NAMES` of every pixel of an RGB image in [0, 1]."""
    h_deg, s, i = rgb_to_hsi(image)
    h = jnp.radians(h_deg)
    return jnp.concatenate(
        [image, jnp.stack([i, s, s * jnp.cos(h), s * jnp.sin(h)], axis=-1)], axis=-1
    )


def rect_weight(rect: Rect, height: int, width: int, dtype: jnp.dtype) -> Float[Array, "H W"]:
    """1 inside the confidence rectangle (x, y, w, h) px, 0 outside; ``rect`` static or traced."""
    x0, y0, w0, h0 = (jnp.asarray(rect[i]) for i in range(4))
    rows = jnp.arange(height)
    cols = jnp.arange(width)
    inside_r = (rows >= y0) & (rows < y0 + h0)
    inside_c = (cols >= x0) & (cols < x0 + w0)
    return (inside_r[:, None] & inside_c[None, :]).astype(dtype)


def rect_statistics(
    features: Float[Array, "H W F"], rect: Rect
) -> tuple[Float[Array, " F"], Float[Array, " F"]]:
    """Mean and spread (standard deviation, floored at :data:`SPREAD_FLOOR`) of each feature
    over the confidence rectangle."""
    height, width, _ = features.shape
    w = rect_weight(rect, height, width, features.dtype)[..., None]
    n = jnp.maximum(jnp.sum(w), 1.0)
    mean = jnp.sum(w * features, axis=(0, 1)) / n
    var = jnp.sum(w * (features - mean[None, None, :]) ** 2, axis=(0, 1)) / n
    # sqrt(var + floor^2), not max(sqrt(var), floor): smooth, and finite gradient at var = 0.
    return mean, jnp.sqrt(var + SPREAD_FLOOR**2)


def normalised_inputs(image: Float[Array, "H W 3"], rect: Rect) -> Float[Array, "H W C"]:
    """The networks' per-pixel inputs: ``Z_LIMIT tanh(z / Z_LIMIT)`` of ``z = (f - mean) /
    spread`` and ``f - mean`` (both over the rectangle), channel-last."""
    f = pixel_features(image)
    mean, spread = rect_statistics(f, rect)
    d = f - mean[None, None, :]
    z = d / spread[None, None, :]
    return jnp.concatenate([Z_LIMIT * jnp.tanh(z / Z_LIMIT), d], axis=-1)


def colour_distance_mask(
    image: Float[Array, "H W 3"], rect: Rect, *, radius: float = 3.0, temperature: float = 0.5
) -> Float[Array, "H W"]:
    """A hand-made mask from the same inputs: how close (in rectangle spreads) a pixel's chroma
    and intensity are to the face's. The starting point learned segmenters imitate when no
    threshold mask is at hand; ``radius`` in spreads, ``temperature`` the sigmoid's width."""
    f = pixel_features(image)
    mean, spread = rect_statistics(f, rect)
    z = (f - mean[None, None, :]) / spread[None, None, :]
    # Chroma and intensity only: R, G, B repeat them. Guarded norm: no NaN gradient at 0.
    d2 = jnp.sum(z[..., 3:] ** 2, axis=-1)
    d = jnp.sqrt(d2 + 1e-12)
    return jax.nn.sigmoid((radius - d) / temperature)
