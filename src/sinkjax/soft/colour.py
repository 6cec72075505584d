"""Colour stage: RGB -> the paper's HSI, in JAX, with finite gradients everywhere."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

_EPS = 1e-12


def rgb_to_hsi(
    rgb: Float[Array, "*hw 3"],
) -> tuple[Float[Array, "*hw"], Float[Array, "*hw"], Float[Array, "*hw"]]:
    """The paper's HSI: hue in degrees [0, 360), saturation and intensity in [0, 1].

    ``rgb`` is channel-last in [0, 1]. Hue is the textbook arccos formula written as
    ``atan2(sqrt(3) (G - B), 2R - G - B)``, which is the same angle (both are the polar angle of
    the chromaticity vector) but has bounded derivatives where arccos has infinite ones.
    Grey pixels get H = 0 and black pixels S = 0, with zero (not NaN) gradients there.
    """
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    cx = 2.0 * r - g - b
    cy = jnp.sqrt(3.0) * (g - b)
    grey = cx * cx + cy * cy <= _EPS
    # Double where: atan2(0, 0) has a NaN gradient even in the untaken branch.
    h = jnp.degrees(jnp.arctan2(jnp.where(grey, 0.0, cy), jnp.where(grey, 1.0, cx)))
    h = jnp.where(grey, 0.0, jnp.mod(h, 360.0))
    total = r + g + b
    dark = total <= _EPS
    s = jnp.where(dark, 0.0, 1.0 - 3.0 * jnp.min(rgb, axis=-1) / jnp.where(dark, 1.0, total))
    return h, s, total / 3.0


def circular_mean_deg(
    angles_deg: Float[Array, "*n"], weight: Float[Array, "*n"] | None = None
) -> Float[Array, ""]:
    """Mean direction of angles in degrees, in [0, 360). Zero for a perfectly balanced set.

    ``weight`` (same shape, >= 0): a weighted mean direction, e.g. a 0/1 mask of the pixels.
    """
    rad = jnp.radians(angles_deg)
    if weight is None:
        c, s = jnp.mean(jnp.cos(rad)), jnp.mean(jnp.sin(rad))
    else:
        # Normalising is unnecessary for a direction, but keeps `flat` on the same scale.
        total = jnp.maximum(jnp.sum(weight), 1.0)
        c, s = jnp.sum(weight * jnp.cos(rad)) / total, jnp.sum(weight * jnp.sin(rad)) / total
    flat = c * c + s * s <= _EPS
    m = jnp.degrees(jnp.arctan2(jnp.where(flat, 0.0, s), jnp.where(flat, 1.0, c)))
    return jnp.where(flat, 0.0, jnp.mod(m, 360.0))


def wrap_deg(angle_deg: Float[Array, "*n"]) -> Float[Array, "*n"]:
    """Angle difference wrapped to [-180, 180)."""
    return jnp.mod(angle_deg + 180.0, 360.0) - 180.0


def chromaticity(rgb: Float[Array, "*hw 3"]) -> Float[Array, "*hw 2"]:
    """The chromaticity vector (2R - G - B, sqrt(3) (G - B)) / (R + G + B): HSI's hue as its
    direction, a saturation as its length (zero on the grey axis).

    A brightness factor (shading, exposure, a shadow) cancels; unlike (H, S) it is linear near
    grey, so a noisy dark pixel lands near the origin instead of at a random hue. Black pixels
    get (0, 0) with zero (not NaN) gradients.
    """
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    total = r + g + b
    dark = total <= _EPS
    inv = jnp.where(dark, 0.0, 1.0 / jnp.where(dark, 1.0, total))
    return jnp.stack([(2.0 * r - g - b) * inv, jnp.sqrt(3.0) * (g - b) * inv], axis=-1)


# The sRGB transfer function (IEC 61966-2-1): encoded values up to this knee are linear in light.
_SRGB_KNEE = 0.04045


def srgb_to_linear(rgb: Float[Array, "*shape"]) -> Float[Array, "*shape"]:
    """sRGB-encoded values in [0, 1] (any shape) as linear light (IEC 61966-2-1): ``v / 12.92``
    up to the knee at 0.04045, ``((v + 0.055) / 1.055) ** 2.4`` above it. Finite gradients
    everywhere (the power is taken above the knee only)."""
    x = jnp.clip(rgb, 0.0, 1.0)
    high = x > _SRGB_KNEE
    return jnp.where(high, ((jnp.where(high, x, 1.0) + 0.055) / 1.055) ** 2.4, x / 12.92)


def linear_light(
    image: Float[Array, "H W 3"], srgb: bool | Bool[Array, ""] | Float[Array, ""]
) -> Array:
    """``image`` in linear light: :func:`srgb_to_linear` of it where ``srgb`` is true (a bool or
    a traced 0/1 flag: one compiled function serves both), else ``image`` itself."""
    flag = jnp.asarray(srgb)
    on = flag if flag.dtype == jnp.bool_ else flag > 0.5
    return jax.lax.cond(on, srgb_to_linear, lambda x: x, image)
