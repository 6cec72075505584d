"""soft.probes: the image samples of the plausibility tests, on painted pictures."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

from sinkjax.soft.model import N_PARAMS
from sinkjax.soft.probes import PROBE_DEEP, PROBE_DROP, patch_rgb, soil_lost

H, W = 360, 480
CX, CY, R, D = 240.0, 130.0, 150.0, 110.0  # the soil line v = D below the centre, in the rim
SKY = (0.60, 0.60, 0.62)
SOIL = (0.55, 0.50, 0.40)


def _params() -> jax.Array:
    # Horizontal equivalent line v = D (k = 0, b = D); both end lines the same (alpha 0, c D).
    p = np.zeros(N_PARAMS, np.float32)
    p[:9] = [CX, CY, R, 0.0, D, 0.0, D, 0.0, D]
    return jnp.asarray(p)


def _picture(shadow: tuple[float, float, float], ground_drop_px: float) -> np.ndarray:
    """Background above the ground, lit soil below it; inside the rim, a black wheel above the
    soil line and ``shadow`` below it. Outside the rim the ground is ``ground_drop_px`` below the
    soil line's level (0: the surface goes on; large: the line is an edge on the wheel)."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    img = np.empty((H, W, 3), np.float32)
    img[:] = SKY
    img[y >= CY + D + ground_drop_px] = SOIL
    disc = (x - CX) ** 2 + (y - CY) ** 2 <= R * R
    img[disc & (y < CY + D)] = (0.05, 0.05, 0.05)
    img[disc & (y >= CY + D)] = shadow
    return img


def _lost(img: np.ndarray) -> bool:
    return bool(jax.jit(soil_lost)(jnp.asarray(img), _params(), jnp.asarray(1.0, jnp.float32)))


def test_the_wheels_shadow_on_the_soil_inside_the_rim_is_still_soil() -> None:
    # The shadow is the soil's colour at 25 % of its light: in RGB the lit soil beyond the rim is
    # nearer the grey background than this dark soil; it is the soil found well below the line.
    shadow = tuple(0.25 * c for c in SOIL)
    lit, dark, sky = (np.asarray(c) for c in (SOIL, shadow, SKY))
    assert np.sum((lit - dark) ** 2) > 4 * np.sum((lit - sky) ** 2)  # RGB alone would say "lost"
    assert not _lost(_picture(shadow, 0.0))


@pytest.mark.parametrize("drop", [0.0, 0.05])
def test_lit_soil_beyond_a_shadow_of_another_colour_is_still_soil(drop) -> None:
    # A neutral grey shadow (lit by the sky alone) inside the rim, the ground beyond it level or
    # a little lower: in RGB the lit soil there is nearer the background than this shadow, but
    # it is the soil found well below the extension.
    shadow, lit, sky = (np.asarray(c) for c in ((0.18, 0.18, 0.19), SOIL, SKY))
    assert np.sum((lit - shadow) ** 2) > 4 * np.sum((lit - sky) ** 2)
    assert not _lost(_picture(tuple(shadow), drop * R))


@pytest.mark.parametrize("shadow", [tuple(0.25 * c for c in SOIL), (0.10, 0.12, 0.22)])
@pytest.mark.parametrize("drop", [0.2, 0.5])
def test_a_line_on_the_wheel_with_background_beyond_the_rim_is_lost(shadow, drop) -> None:
    # The ground outside is a fifth or a half of the radius lower: just below the line's
    # extension (and PROBE_DROP of the radius lower) there is only background, whether the
    # sample PROBE_DEEP of the radius down finds the soil (0.2) or the background too (0.5).
    assert drop * R > 4.0 + PROBE_DROP * R + 2.0
    assert (drop * R < 4.0 + PROBE_DEEP * R) == (drop == 0.2)
    assert _lost(_picture(shadow, drop * R))


def test_patch_rgb_is_the_mean_of_nine_bilinear_samples() -> None:
    rng = np.random.default_rng(3)
    img = rng.random((40, 50, 3)).astype(np.float32)
    x, y = 21.3, 17.6
    o = np.array([-2.0, 0.0, 2.0])
    xs, ys = np.meshgrid(x + o, y + o, indexing="ij")
    want = [
        ndimage.map_coordinates(img[..., c], [ys.ravel(), xs.ravel()], order=1).mean()
        for c in range(3)
    ]
    got = patch_rgb(jnp.asarray(img), jnp.asarray(x, jnp.float32), jnp.asarray(y, jnp.float32))
    np.testing.assert_allclose(np.asarray(got), want, atol=1e-6)
