"""Eqs. 1-3 (sinkjax.geometry) against hand-computed cases and the paper's own formulas."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sinkjax as sj


def paper_eq1(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Eq. 1's k and b exactly as printed (sums), in plain Python floats."""
    n = len(x)
    sx, sy = float(np.sum(x)), float(np.sum(y))
    sxx, sxy = float(np.sum(x * x)), float(np.sum(x * y))
    den = n * sxx - sx * sx
    return (n * sxy - sy * sx) / den, (sy * sxx - sx * sxy) / den


def test_equivalent_line_is_eq1() -> None:
    rng = np.random.default_rng(0)
    x = rng.uniform(-50, 50, 200)
    y = 0.3 * x + 90 + rng.normal(0, 2, 200)
    k, b = sj.equivalent_line(jnp.asarray(x), jnp.asarray(y))
    k_ref, b_ref = paper_eq1(x, y)
    assert float(k) == pytest.approx(k_ref, rel=1e-10)
    assert float(b) == pytest.approx(b_ref, rel=1e-10)


def test_zero_weights_drop_points() -> None:
    rng = np.random.default_rng(1)
    x, y = rng.normal(size=50), rng.normal(size=50)
    w = (rng.uniform(size=50) > 0.5).astype(float)
    k, b = sj.equivalent_line(jnp.asarray(x), jnp.asarray(y), jnp.asarray(w))
    k_ref, b_ref = paper_eq1(x[w > 0], y[w > 0])
    assert float(k) == pytest.approx(k_ref, rel=1e-10)
    assert float(b) == pytest.approx(b_ref, rel=1e-10)


def test_sinkage_and_angles_by_hand() -> None:
    # Horizontal line 100 px below O, rim 150 px: z0 = 50.
    assert float(sj.sinkage_px(0.0, 100.0, 150.0)) == pytest.approx(50.0)
    # Line y = x + 100: distance from O is 100 / sqrt(2).
    assert float(sj.sinkage_px(1.0, 100.0, 150.0)) == pytest.approx(150 - 100 / math.sqrt(2))
    # A = (30, 40) (y down): theta1 = 90 deg - atan(40/30).
    t1 = float(sj.entry_angle_rad(30.0, 40.0))
    assert math.degrees(t1) == pytest.approx(90 - math.degrees(math.atan(4 / 3)))
    # B = (-30, 40): theta2 = 90 deg + atan(40 / -30), the same angle from the vertical.
    assert float(sj.exit_angle_rad(-30.0, 40.0)) == pytest.approx(t1)
    # x = 0 -> 0 by definition (Eqs. 2-3), with a finite gradient.
    assert float(sj.entry_angle_rad(0.0, 40.0)) == 0.0
    g = jax.grad(lambda x: sj.entry_angle_rad(x, 40.0) + sj.exit_angle_rad(x, 40.0))(0.0)
    assert np.isfinite(g)


def test_flat_ground_identity_and_mirror() -> None:
    r, depth = 150.0, 37.5
    cx, cy = 300.0, 200.0
    half = math.sqrt(r * r - (r - depth) ** 2)
    x = np.linspace(cx - half, cx + half, 2001)
    y = np.full_like(x, cy + r - depth)
    for travel in ("right", "left"):
        g = sj.geometry_from_boundary(jnp.asarray(x), jnp.asarray(y), cx, cy, r, travel=travel)
        expected = float(sj.flat_ground_angle_rad(depth, r))
        assert float(g.sinkage_px) == pytest.approx(depth, abs=1e-9)
        assert float(g.theta1_rad) == pytest.approx(expected, abs=1e-9)
        assert float(g.theta2_rad) == pytest.approx(expected, abs=1e-9)


def test_mirror_swaps_entry_and_exit() -> None:
    # A sloping boundary: entry (right) higher than exit.
    cx, cy, r = 0.0, 0.0, 100.0
    x = np.linspace(-60, 70, 500)
    y = 80 - 0.2 * x
    right = sj.geometry_from_boundary(jnp.asarray(x), jnp.asarray(y), cx, cy, r, travel="right")
    left = sj.geometry_from_boundary(jnp.asarray(x), jnp.asarray(y), cx, cy, r, travel="left")
    assert float(right.sinkage_px) == pytest.approx(float(left.sinkage_px))
    # Travelling left, the entry end is the left one: theta1(left) comes from x = -60.
    assert float(left.theta1_rad) == pytest.approx(float(sj.entry_angle_rad(60.0, 92.0)))
    assert float(right.theta1_rad) == pytest.approx(float(sj.entry_angle_rad(70.0, 66.0)))


def test_degenerate_inputs_have_finite_gradients() -> None:
    def f(y: jnp.ndarray, w: jnp.ndarray) -> jnp.ndarray:
        k, b = sj.equivalent_line(jnp.zeros(5), y, w)  # all x equal: slope undefined
        return sj.sinkage_px(k, b, 100.0)

    g = jax.grad(f)(jnp.arange(5.0), jnp.ones(5))
    assert np.all(np.isfinite(g))
    g0 = jax.grad(f, argnums=1)(jnp.arange(5.0), jnp.zeros(5))  # no points at all
    assert np.all(np.isfinite(g0))
    geo = sj.geometry_from_boundary(jnp.zeros(4), jnp.zeros(4), 0.0, 0.0, 50.0, weight=jnp.zeros(4))
    assert not bool(geo.contact) and float(geo.sinkage_px) == 0.0
