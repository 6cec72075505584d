"""Illumination augmentations: the lamp moves, the exposure changes, a shadow falls on the wheel.

Calibration under ``--augment`` measures every labelled frame under a fresh random lighting change
at every step, so the tuned thresholds must work for lighting the labelled frames never showed.
Each operation is a pure JAX function of one image ``Float[Array, "H W 3"]`` in [0, 1] (channel
last) and a PRNG key: seeded, jit- and vmap-able. :func:`augment` chains them with the strengths
of an :class:`AugmentConfig`. (The torch/kornia side of the project exposes kornia equivalents.)

>>> import jax, jax.numpy as jnp
>>> img = jnp.full((48, 64, 3), 0.5)
>>> out = augment(img, jax.random.key(0))
>>> out.shape, bool((out >= 0).all() & (out <= 1).all())
((48, 64, 3), True)
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

# Log gains (R, G, B) of the lamp per 100 mireds (1e6 / T) warmer, relative to green: from the
# sRGB colours of black bodies at 6500 K (#fff9fd) and 4000 K (#ffd1a3), 96 mireds apart, red
# over green rises by a factor 1.19 and blue over green falls by 0.77. Log-linear in mireds is
# close to the Planckian locus over 3000-7000 K.
MIRED_LOG_GAINS_PER_100 = (0.18, 0.0, -0.27)


class AugmentConfig(eqx.Module):
    """Strengths of the random lighting changes (all static Python floats).

    brightness_log_std: std of the log exposure gain. contrast_log_std: std of the log contrast
    factor around the image mean. channel_log_std: std of independent per-channel log gains
    (colour jitter). mired_range: colour temperature shift, uniform in +-range mireds.
    shadow_max: darkest shadow factor is 1 - shadow_max. shadow_grid: coarsest cells of the
    smooth random shadow field. noise_std_max: Gaussian sensor noise std, uniform in [0, max].
    """

    brightness_log_std: float = eqx.field(static=True, default=0.25)
    contrast_log_std: float = eqx.field(static=True, default=0.15)
    channel_log_std: float = eqx.field(static=True, default=0.04)
    mired_range: float = eqx.field(static=True, default=80.0)
    shadow_max: float = eqx.field(static=True, default=0.55)
    shadow_grid: int = eqx.field(static=True, default=3)
    noise_std_max: float = eqx.field(static=True, default=0.02)


DEFAULT_CONFIG = AugmentConfig()


def brightness_contrast(
    image: Float[Array, "H W 3"], gain: Float[Array, ""], contrast: Float[Array, ""]
) -> Float[Array, "H W 3"]:
    """``(image - mean) * contrast + mean`` then times ``gain`` (exposure), clipped to [0, 1]."""
    mean = jnp.mean(image)
    return jnp.clip(((image - mean) * contrast + mean) * gain, 0.0, 1.0)


def channel_gains(image: Float[Array, "H W 3"], gains: Float[Array, " 3"]) -> Float[Array, "H W 3"]:
    """Per-channel gains (a white-balance error or coloured lamp), clipped to [0, 1]."""
    return jnp.clip(image * gains[None, None, :], 0.0, 1.0)


def colour_temperature_gains(mired_shift: Float[Array, ""]) -> Float[Array, " 3"]:
    """RGB gains for a lamp ``mired_shift`` mireds warmer (> 0) or cooler (< 0) than the original.

    A Planckian-like shift: along the black-body locus red and blue move in opposite directions;
    the log gains are linear in mireds, which is close to the locus over 3000-6500 K.
    """
    per = jnp.asarray(MIRED_LOG_GAINS_PER_100, dtype=jnp.result_type(mired_shift, float))
    return jnp.exp(per * mired_shift / 100.0)


def _upsample_matrix(n_out: int, n_in: int) -> np.ndarray:
    # Normalised Gaussian weights from n_in evenly spaced nodes to n_out pixels: a smooth
    # interpolant built in NumPy (a constant under jit, unlike a resize it costs no compile time).
    nodes = np.linspace(0.0, n_out - 1.0, n_in)
    sigma = 0.6 * (nodes[1] - nodes[0])
    w = np.exp(-0.5 * ((np.arange(n_out)[:, None] - nodes[None]) / sigma) ** 2)
    return w / w.sum(axis=1, keepdims=True)


def smooth_field(
    key: PRNGKeyArray, height: int, width: int, *, grid: int = 3, octaves: int = 3
) -> Float[Array, "H W"]:
    """A plasma-like smooth random field in [0, 1]: octaves of smoothly upsampled noise.

    The coarsest octave has ``grid`` cells along the shorter side; each finer octave doubles the
    cells and halves the amplitude. ``height``, ``width``, ``grid`` and ``octaves`` are static.
    """
    keys = jax.random.split(key, octaves)
    field = jnp.zeros((height, width))
    short = min(height, width)
    for i, k in enumerate(keys):
        cells = grid * 2**i
        gh = max(2, round(cells * height / short)) + 1
        gw = max(2, round(cells * width / short)) + 1
        coarse = jax.random.normal(k, (gh, gw))
        wy = jnp.asarray(_upsample_matrix(height, gh), coarse.dtype)
        wx = jnp.asarray(_upsample_matrix(width, gw), coarse.dtype)
        field = field + 0.5**i * (wy @ coarse @ wx.T)
    lo, hi = jnp.min(field), jnp.max(field)
    return (field - lo) / jnp.maximum(hi - lo, 1e-6)


def soft_shadow(
    image: Float[Array, "H W 3"], field: Float[Array, "H W"], depth: Float[Array, ""]
) -> Float[Array, "H W 3"]:
    """Darken where a [0, 1] ``field`` is high: factor ``1 - depth * field`` (a soft shadow)."""
    return image * (1.0 - depth * field)[..., None]


def gaussian_noise(
    image: Float[Array, "H W 3"], key: PRNGKeyArray, std: Float[Array, ""]
) -> Float[Array, "H W 3"]:
    """Additive Gaussian sensor noise of standard deviation ``std`` (image units), clipped."""
    return jnp.clip(image + std * jax.random.normal(key, image.shape, image.dtype), 0.0, 1.0)


@functools.partial(jax.jit, static_argnames="config")
def augment(
    image: Float[Array, "H W 3"], key: PRNGKeyArray, config: AugmentConfig = DEFAULT_CONFIG
) -> Float[Array, "H W 3"]:
    """One random lighting change of ``image`` (in [0, 1], channel last), seeded by ``key``.

    Order: soft shadow, colour temperature and colour jitter, brightness/contrast, noise.
    Raises ValueError if ``image`` is not (H, W, 3).
    """
    if image.ndim != 3 or image.shape[-1] != 3:
        raise ValueError(f"augment needs an image of shape (H, W, 3), got {image.shape}")
    height, width = image.shape[:2]
    dt = image.dtype
    k = jax.random.split(key, 8)
    field = smooth_field(k[0], height, width, grid=config.shadow_grid)
    depth = jax.random.uniform(k[1], (), dt, 0.0, config.shadow_max)
    out = soft_shadow(image, field.astype(dt), depth)
    mired = jax.random.uniform(k[2], (), dt, -config.mired_range, config.mired_range)
    jitter = jnp.exp(config.channel_log_std * jax.random.normal(k[3], (3,), dt))
    out = channel_gains(out, colour_temperature_gains(mired).astype(dt) * jitter)
    gain = jnp.exp(config.brightness_log_std * jax.random.normal(k[4], (), dt))
    contrast = jnp.exp(config.contrast_log_std * jax.random.normal(k[5], (), dt))
    out = brightness_contrast(out, gain, contrast)
    std = jax.random.uniform(k[6], (), dt, 0.0, config.noise_std_max)
    return gaussian_noise(out, k[7], std)
