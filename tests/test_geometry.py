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
    # x = 0: the point is straight below O, angle 0, with the gradient of atan2: 1 / y.
    assert float(sj.entry_angle_rad(0.0, 40.0)) == 0.0
    g = jax.grad(lambda x: sj.entry_angle_rad(x, 40.0) - sj.exit_angle_rad(x, 40.0))(0.0)
    assert float(g) == pytest.approx(2 / 40.0)


def test_atan2_angles_equal_the_papers_where_it_applies() -> None:
    # A ahead of O (x_A > 0) and B behind it (x_B < 0): conventions §1 = Eqs. 2-3 as printed.
    rng = np.random.default_rng(3)
    for _ in range(50):
        x, y = rng.uniform(0.5, 150), rng.uniform(-100, 150)
        assert float(sj.entry_angle_rad(x, y)) == pytest.approx(
            math.pi / 2 - math.atan(y / x), abs=1e-12
        )
        assert float(sj.exit_angle_rad(-x, y)) == pytest.approx(
            math.pi / 2 + math.atan(y / -x), abs=1e-12
        )


def test_atan2_angles_are_continuous_and_go_negative() -> None:
    # A point on the rim below O sweeping through x = 0: the angle is its polar angle from the
    # downward vertical, with no jump (the paper's form jumps from 0 to 180 deg there).
    r = 100.0
    phi = np.linspace(-0.4, 0.4, 81)
    xs, ys = r * np.sin(phi), r * np.cos(phi)
    t1 = np.asarray(sj.entry_angle_rad(jnp.asarray(xs), jnp.asarray(ys)))
    t2 = np.asarray(sj.exit_angle_rad(jnp.asarray(xs), jnp.asarray(ys)))
    np.testing.assert_allclose(t1, phi, atol=1e-12)
    np.testing.assert_allclose(t2, -phi, atol=1e-12)
    # Hollow terrain: the soil touches only the entry half, B at x_B > 0 ahead of O -> theta2 < 0.
    cx, cy = 0.0, 0.0
    x = np.linspace(10.0, 80.0, 400)
    y = np.sqrt(r * r - 10.0**2) - 0.6 * (x - 10.0)
    g = sj.geometry_from_boundary(jnp.asarray(x), jnp.asarray(y), cx, cy, r)
    assert math.degrees(float(g.theta2_rad)) == pytest.approx(
        -math.degrees(math.asin(10.0 / r)), abs=1e-9
    )
    assert float(g.theta1_rad) > 0


def test_angles_have_finite_gradients_at_the_origin() -> None:
    for f in (sj.entry_angle_rad, sj.exit_angle_rad):
        assert float(f(0.0, 0.0)) == 0.0
        gx, gy = jax.grad(lambda x, y, f=f: f(x, y), argnums=(0, 1))(0.0, 0.0)
        assert np.isfinite(float(gx)) and np.isfinite(float(gy))
    gv = jax.vmap(jax.grad(sj.exit_angle_rad))(jnp.array([0.0, 1.0]), jnp.array([0.0, 0.0]))
    assert np.all(np.isfinite(np.asarray(gv)))


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
