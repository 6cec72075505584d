"""The soft Hough stage (sinkjax.soft.hough) on outlines of drawn wheels with known rims.

References: the drawn circle itself, SciPy's geometric least-squares circle through the outline
points that lie on the true rim, and NumPy's least squares for the algebraic (Kasa) fit.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import least_squares

from sinkjax.soft.hough import _kasa, hough_rim, radius_range_px
from sinkjax.soft.outline import extract_outline
from sinkjax.soft.settings import SoftSettings

SETTINGS = SoftSettings()

H, W = 120, 160
CX, CY, R = 78.4, 52.7, 41.3


def wheel_mask(
    *, n_lugs: int = 0, lug_h: float = 0.0, soil_y: float = 1e9, cut: float = 0.0, ss: int = 6
) -> np.ndarray:
    """(H, W) exact-coverage mask of a wheel (rim R, ``n_lugs`` lugs ``lug_h`` high) behind soil
    y > ``soil_y``, with a ``cut`` radians wide wedge of the upper rim hidden (an occluder)."""
    xs = (np.arange(W * ss) + 0.5) / ss - 0.5
    ys = (np.arange(H * ss) + 0.5) / ss - 0.5
    x, y = np.meshgrid(xs, ys)
    rho, ang = np.hypot(x - CX, y - CY), np.arctan2(y - CY, x - CX)
    wheel = rho <= R
    if n_lugs:
        pitch = 2 * np.pi / n_lugs
        a = (ang + pitch / 2) % pitch - pitch / 2
        wheel |= (rho <= R + lug_h) & (np.abs(rho * np.sin(a)) <= 0.3 * pitch * R / 2)
    if cut:
        wheel &= ~((np.abs(ang + np.pi / 2) < cut / 2) & (rho > 0.8 * R))
    wheel &= y <= soil_y
    return wheel.astype(np.float64).reshape(H, ss, W, ss).mean(axis=(1, 3))


@jax.jit
def rim(mask: jax.Array):
    """Outline then Hough circle, compiled once for this file's (H, W)."""
    return hough_rim(extract_outline(mask, SETTINGS), H, W, SETTINGS)


def ls_circle(x: np.ndarray, y: np.ndarray, start: tuple[float, float, float]) -> np.ndarray:
    """Geometric least-squares circle (SciPy), the reference for the polished Hough circle."""
    fun = lambda p: np.hypot(x - p[0], y - p[1]) - p[2]
    return least_squares(fun, np.asarray(start), xtol=1e-12, ftol=1e-12).x


CASES = {
    "plain": {},
    "lugs": {"n_lugs": 18, "lug_h": 4.0},
    "lugs_soil": {"n_lugs": 18, "lug_h": 4.0, "soil_y": CY + 25.0},
    "occluded_soil": {"soil_y": CY + 30.0, "cut": 0.8},
}


@pytest.mark.parametrize("case", list(CASES))
def test_rim_found_not_lug_tips(case: str) -> None:
    mask = jnp.asarray(wheel_mask(**CASES[case]))
    o, c = jax.jit(extract_outline)(mask, SETTINGS), rim(mask)
    cx, cy, r = float(c.cx_px), float(c.cy_px), float(c.r_px)
    # Lug tips stand 4 px (10 %) outside the rim; the result must be the rim, to a fraction of
    # a pixel.
    assert cx == pytest.approx(CX, abs=0.3) and cy == pytest.approx(CY, abs=0.3)
    assert r == pytest.approx(R, abs=0.3)
    # Reference: the least-squares circle through the outline points that truly lie on the rim.
    x, y, wt = (np.asarray(a) for a in (o.x_px, o.y_px, o.weight))
    on_rim = np.asarray(o.valid) & (wt > 0.5) & (np.abs(np.hypot(x - CX, y - CY) - R) < 1.0)
    ref = ls_circle(x[on_rim], y[on_rim], (CX, CY, R))
    np.testing.assert_allclose([cx, cy, r], ref, atol=0.15)
    # Support: the fraction of the circumference with rim evidence.
    visible = on_rim.sum() / (2 * np.pi * R)
    assert float(c.support) == pytest.approx(visible, abs=0.15)


def test_no_circle_has_little_support() -> None:
    # A half-plane (bare soil surface) is no rim: whatever circle comes out has little support.
    yy = np.arange(H, dtype=np.float64)[:, None] * np.ones((1, W))
    mask = np.clip(70.5 - yy, 0.0, 1.0)
    c = rim(jnp.asarray(mask))
    assert float(c.support) < 0.2


def test_kasa_is_weighted_algebraic_least_squares() -> None:
    rng = np.random.default_rng(1)
    t = rng.uniform(0, 2 * np.pi, 300)
    x = 40.0 + 25.0 * np.cos(t) + rng.normal(0, 0.3, t.size)
    y = -12.0 + 25.0 * np.sin(t) + rng.normal(0, 0.3, t.size)
    w = rng.uniform(0.0, 1.0, t.size)
    cx, cy, r = (float(v) for v in jax.jit(_kasa)(jnp.asarray(x), jnp.asarray(y), jnp.asarray(w)))
    # min sum w (x^2 + y^2 + D x + E y + F)^2, directly in NumPy.
    sw = np.sqrt(w)
    a = np.stack([x, y, np.ones_like(x)], 1) * sw[:, None]
    d, e, f = np.linalg.lstsq(a, -(x * x + y * y) * sw, rcond=None)[0]
    assert cx == pytest.approx(-d / 2, abs=1e-6) and cy == pytest.approx(-e / 2, abs=1e-6)
    assert r == pytest.approx(np.sqrt(d * d / 4 + e * e / 4 - f), abs=1e-6)


def test_radius_range() -> None:
    assert radius_range_px(120, 160) == pytest.approx((0.12 * 120, 0.75 * 120))


@pytest.mark.slow
def test_jit_equals_eager_and_vmap_equals_loop() -> None:
    masks = jnp.asarray(np.stack([wheel_mask(**CASES["lugs"]), wheel_mask(**CASES["plain"])]))

    def stage(mask):
        return hough_rim(extract_outline(mask, SETTINGS, capacity=900), H, W, SETTINGS)

    eager = stage(masks[0])
    jitted = jax.jit(stage)(masks[0])
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9), eager, jitted)
    batched = jax.jit(jax.vmap(stage))(masks)
    for i in range(2):
        one = jax.jit(stage)(masks[i])
        jax.tree.map(
            lambda a, b, i=i: np.testing.assert_allclose(a[i], b, rtol=1e-9, atol=1e-9),
            batched,
            one,
        )
