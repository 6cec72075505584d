"""The ends' windows (soft.ends): the crossing's standard error, and the window chosen by
intersecting confidence intervals, against exact crossings and Monte Carlo spreads."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from sinkjax.soft.ends import _crossing_and_error, chosen_window, end_kernel
from sinkjax.soft.settings import SoftSettings

CX, CY, R, DEPTH = 200.0, 190.0, 140.0, 130.4  # rim circle and flat soil level (px, image)


def _surface(x: np.ndarray, drop: float, step_from_b: float) -> np.ndarray:
    """Flat soil at DEPTH below O, stepping up by ``drop`` px (a tanh of 8.4 px) ``step_from_b``
    px inside B: a rut's edge, the paper rig's proportions."""
    xb = CX - np.sqrt(R * R - DEPTH * DEPTH)
    return CY + DEPTH - drop * 0.5 * (1.0 + np.tanh((x - xb - step_from_b) / 8.4))


def _exact_exit_angle(drop: float, step_from_b: float) -> float:
    """Where the surface meets the rim behind O (bisection), as the angle from the bottom (rad,
    negative behind)."""
    lo, hi = CX - R, CX
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        y = float(_surface(np.asarray(mid), drop, step_from_b))
        inside = (mid - CX) ** 2 + (y - CY) ** 2 < R * R
        lo, hi = (lo, mid) if inside else (mid, hi)
    x = 0.5 * (lo + hi)
    return float(np.arctan2(x - CX, float(_surface(np.asarray(x), drop, step_from_b)) - CY))


def _boundary(drop: float, step_from_b: float, noise: float, seed: int) -> tuple:
    """Boundary points one a pixel from 4 px inside B towards O (wheel frame), with Gaussian
    noise across the edge, and their squared distances from the end-most one."""
    xb = CX - np.sqrt(R * R - DEPTH * DEPTH)
    x = np.arange(xb + 4.0, CX, 1.0)
    y = _surface(x, drop, step_from_b) + noise * np.random.default_rng(seed).normal(size=x.size)
    u, v = jnp.asarray(x - CX), jnp.asarray(y - CY)
    return u, v, jnp.ones_like(u), (u - u[0]) ** 2 + (v - v[0]) ** 2


def _choose(drop: float, noise: float, seed: int, z: float = 2.0) -> float:
    u, v, w, d2 = _boundary(drop, 20.0, noise, seed)
    s = SoftSettings(end_window_z=z)
    return float(chosen_window(u, v, w, d2, jnp.asarray(28.0), jnp.asarray(R), -1.0, s))


def test_crossing_error_matches_the_spread_of_noisy_draws() -> None:
    # The straight line's crossing over a 15 px tapered window, 0.3 px edge noise: the reported
    # standard error against the standard deviation of the crossing over 400 draws.
    angles, errors = [], []
    for seed in range(400):
        u, v, w, d2 = _boundary(0.0, 20.0, 0.3, seed)
        k = w * end_kernel(d2, jnp.asarray(15.0), jnp.asarray(1.0))
        a, e = _crossing_and_error(u, v, k, jnp.asarray(R), -1.0)
        angles.append(float(a))
        errors.append(float(e))
    spread = float(np.std(angles))
    assert 0.8 < float(np.median(errors)) / spread < 1.25
    assert abs(float(np.mean(angles)) - _exact_exit_angle(0.0, 20.0)) < 0.3 * spread


def test_window_is_the_longest_on_a_flat_surface_and_stops_before_a_rut_edge() -> None:
    # Flat soil: every window agrees, the longest is kept (noise or none).
    assert _choose(0.0, 0.0, 0) == 28.0
    assert [_choose(0.0, 0.2, seed) for seed in range(5)] == [28.0] * 5
    # A 1.9 px rut edge 20 px inside B, a clean edge: the long windows' crossings drift by more
    # than their errors, the ladder stops short; the straight line over the chosen window
    # crosses the rim nearer the exact point. (Under 0.2 px of noise the drift is within the
    # errors and the longest window stays: the rule trades bias for noise, it does not remove it.)
    chosen = _choose(1.9, 0.0, 0)
    assert chosen < 28.0
    assert _choose(1.9, 0.0, 0, z=float("inf")) == 28.0
    exact = _exact_exit_angle(1.9, 20.0)
    u, v, w, d2 = _boundary(1.9, 20.0, 0.0, 0)
    off = {}
    for window in (chosen, 28.0):
        k = w * end_kernel(d2, jnp.asarray(window), jnp.asarray(1.0))
        off[window] = abs(float(_crossing_and_error(u, v, k, jnp.asarray(R), -1.0)[0]) - exact)
    assert off[chosen] < 0.7 * off[28.0]  # 0.27 against 0.42 deg (20 px chosen)
