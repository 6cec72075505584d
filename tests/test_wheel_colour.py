"""The veto's wheel colour (sinkjax.soft.wheel_colour): a round cloud of chromaticities reads as
its median (NumPy), a highlight's stretched one as its saturated end, so that a confidence
rectangle in a glow still lets the veto remove soil (rendered by hand: exact colours)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sinkjax.soft.colour import chromaticity
from sinkjax.soft.segmentation import reference_mask
from sinkjax.soft.wheel_colour import wheel_colour

BODY = np.array([0.55, 0.12, 0.12])  # red paint
WHITE = np.array([1.0, 1.0, 1.0])
SOIL = np.array([0.45, 0.33, 0.22])  # brown: a red-orange hue, paler


def _chroma(rgb: np.ndarray) -> np.ndarray:
    r, g, b = np.moveaxis(rgb, -1, 0)
    return np.stack([2 * r - g - b, np.sqrt(3) * (g - b)], -1) / (r + g + b)[..., None]


def test_a_round_cloud_is_its_median() -> None:
    rng = np.random.default_rng(0)
    q = _chroma(BODY) + rng.normal(0, 0.01, (1024, 2))
    got = wheel_colour(jnp.asarray(q), jnp.ones(1024))
    np.testing.assert_allclose(np.asarray(got.centre), np.median(q, axis=0), atol=1e-15)
    mad = np.median(np.abs(q - np.median(q, axis=0)), axis=0)
    assert float(got.spread) == pytest.approx(1.4826 * np.hypot(*mad), rel=1e-8)


def test_a_highlight_reads_as_its_saturated_end() -> None:
    # Body plus a surface part (white light) growing across the rectangle: the dichromatic
    # model's segment from the body colour towards grey.
    rng = np.random.default_rng(1)
    share = rng.uniform(0.0, 0.45, 1024)
    rgb = (1 - share)[:, None] * BODY + share[:, None] * WHITE * 0.6
    q = _chroma(rgb) + rng.normal(0, 0.002, (1024, 2))
    got = wheel_colour(jnp.asarray(q), jnp.ones(1024))
    med = np.median(q, axis=0)
    u = med / np.linalg.norm(med)
    along = q @ u
    # Along the hue direction: the upper quartile (NumPy's lower-interpolated quantile).
    assert float(jnp.dot(got.centre, jnp.asarray(u))) == np.quantile(along, 0.75, method="lower")
    assert np.linalg.norm(np.asarray(got.centre) - _chroma(BODY)) < 0.6 * np.linalg.norm(
        med - _chroma(BODY)
    )
    assert float(got.spread) < 0.01  # across the hue: the noise, not the highlight's reach


def _glow_rect_scene() -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """A red wheel on a grey wall over brown soil, its confidence rectangle across a highlight
    (white light added from 0 to 45 % left to right, nothing clipped)."""
    img = np.empty((90, 120, 3))
    img[:] = 0.5
    img[70:] = SOIL
    yy, xx = np.mgrid[:90, :120]
    img[(yy - 40) ** 2 + (xx - 60) ** 2 < 30**2] = BODY
    rect = (45, 22, 30, 10)
    share = np.linspace(0.0, 0.45, 30)[None, :, None]
    img[22:32, 45:75] = (1 - share) * BODY + share * WHITE * 0.6
    return img, rect


def test_the_veto_removes_soil_beside_a_rectangle_in_a_highlight() -> None:
    img, rect = _glow_rect_scene()
    veto = np.asarray(jax.jit(reference_mask, static_argnums=1)(jnp.asarray(img), rect))
    yy, xx = np.mgrid[:90, :120]
    d = np.hypot(yy - 40, xx - 60)
    assert veto[(yy > 73) & (d > 33)].max() < 0.05  # soil
    assert veto[(yy < 18) & (d > 33)].max() < 0.05  # wall
    assert veto[(d < 27) & (yy > 35)].min() > 0.95  # the body below the rectangle
    # Read as one point with its spread (the median), the highlight's spread swallows the soil's
    # colour and the veto would let it through: the soil lies within that spread.
    q = _chroma(img[22:32, 45:75].reshape(-1, 3))
    med = np.median(q, axis=0)
    spread = 1.4826 * np.hypot(*np.median(np.abs(q - med), axis=0))
    assert np.linalg.norm(_chroma(SOIL) - med) < 2 * spread
    assert np.all(np.isfinite(np.asarray(chromaticity(jnp.asarray(img)))))
