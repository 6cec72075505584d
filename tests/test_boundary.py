"""Which lower outline points are the soil boundary (soft.fit.boundary_side), on constructed
edges whose soil curve is known exactly."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from sinkjax.soft.fit import boundary_side
from sinkjax.soft.settings import SoftSettings

R = 150.0


def _edge(line_v_px, u_lo: float, u_hi: float, seed: int) -> tuple[np.ndarray, ...]:
    """The lower half of a rim of radius R (one point per px of u), with the soil cutting it
    where ``line_v_px(u)`` lies above the rim, between ``u_lo`` and ``u_hi``. The rim edge's
    error is that of a dark, noisy frame: most points within a pixel of the circle, one in
    five 2-4 px inside it (more than the 1.5 px that counts as "clearly inside").
    Returns u, d - r, and whether each point is on the soil curve (the reference)."""
    rng = np.random.default_rng(seed)
    u = np.arange(-0.9 * R, 0.9 * R, 1.0)
    rim_v = np.sqrt(R * R - u * u)
    soil_v = line_v_px(u)
    soil = (soil_v < rim_v) & (u >= u_lo) & (u <= u_hi)
    v = np.where(soil, soil_v, rim_v)
    dr = np.hypot(u, v) - R
    noise = np.where(rng.uniform(size=u.shape) < 0.2, -rng.uniform(2, 4, u.shape), 0.0)
    dr = np.where(soil, dr, dr + noise - rng.uniform(0, 1, u.shape))
    return u, dr, soil


def _inside(u: np.ndarray, dr: np.ndarray) -> np.ndarray:
    return np.asarray(
        boundary_side(
            jnp.asarray(u), jnp.asarray(dr), jnp.ones(u.shape), jnp.asarray(1.5), SoftSettings()
        )
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rim_edge_noise_beyond_a_and_b_is_not_soil(seed: int) -> None:
    """A level soil 10 px inside the rim: the boundary is the chord, not the rim edge's
    dips beyond its ends (which the offset test alone took for soil)."""
    u, dr, soil = _edge(lambda u: np.full_like(u, R - 10.0), -R, R, seed)
    inside = _inside(u, dr)
    # The noise does put rim points clearly inside the rim beyond the chord.
    assert np.sum((dr < -1.5) & ~soil) >= 20
    # The chord's points (10 px down to 0 at its ends) count where they are clearly inside.
    assert np.all(inside[soil & (dr < -1.5)])
    assert not np.any(inside[~soil])


def test_a_hollow_ahead_keeps_a_boundary_away_from_the_rims_lowest_point() -> None:
    """B ahead of O (hollow terrain, theta2 < 0): the soil cuts the rim only at u > 0, a sloped
    line that does not reach u = 0 (it meets the rim at u = 20 and 110 px, up to 8.8 px inside it
    between them); all of it still counts, nothing beyond it."""
    v_b, v_a = np.sqrt(R * R - 20.0**2), np.sqrt(R * R - 110.0**2)
    u, dr, soil = _edge(lambda u: v_b + (v_a - v_b) * (u - 20.0) / 90.0, 20.0, 110.0, 3)
    assert not np.any(soil & (u <= 0)) and np.min(dr[soil]) < -8.5
    inside = _inside(u, dr)
    assert np.all(inside[soil & (dr < -1.5)])
    assert not np.any(inside[~soil])
