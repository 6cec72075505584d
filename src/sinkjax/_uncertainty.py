"""Uncertainty stage: Gauss-Newton covariance at the optimum, propagated by the delta method.

Each residual group (rim, boundary + ends) gets its own noise level from its weighted residuals.
Neighbouring outline points are not independent (the mask is smoothed and the image blurred over a
few pixels), so the covariance is inflated by a correlation length in points. What the fit cannot
see (segmentation bias shared by a whole edge, JPEG, blur) is an error floor added in quadrature.
Both constants were measured on synthetic recordings disjoint from the benchmark's
(``experiments/uncertainty_calibration.py``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._model import N_PARAMS, Evidence, measurements, residuals

CORRELATION_LENGTH = 3.0
# Floors in the reported quantities: sinkage (px) and angles (degrees).
FLOOR_SINKAGE_PX = 0.25
FLOOR_ANGLE_DEG = 0.4


def _group_scale(res: Array, w: Array) -> Array:
    # Weighted RMS of the unweighted residuals (res already carries sqrt(w)); at least 0.05 px.
    sw = jnp.sum(w)
    var = jnp.sum(res * res) / jnp.maximum(sw - 3.0, 1.0)
    return jnp.sqrt(jnp.maximum(var, 0.05**2))


def covariance(p: Float[Array, " 9"], ev: Evidence) -> Float[Array, "9 9"]:
    """Parameter covariance (px^2, rad^2), scaled by each group's residual variance."""
    n = ev.x_px.shape[0]
    res = residuals(p, ev)
    jac = jax.jacfwd(residuals)(p, ev)
    rim_line = res[:n]
    ends = res[n : 2 * n]
    s_rim = _group_scale(jnp.where(ev.w_rim > 0, rim_line, 0.0), ev.w_rim)
    s_line = _group_scale(jnp.where(ev.w_line > 0, rim_line, 0.0), ev.w_line)
    s_end = _group_scale(ends, ev.w_a + ev.w_b)
    scale = jnp.concatenate(
        [
            jnp.where(ev.w_rim > 0, s_rim, s_line),
            jnp.full((n,), s_end),
            jnp.ones((N_PARAMS,)),
        ]
    )
    jw = jac / scale[:, None]
    info = jw.T @ jw
    return CORRELATION_LENGTH * jnp.linalg.inv(info + 1e-9 * jnp.eye(N_PARAMS))


def measurement_std(
    p: Float[Array, " 9"], cov: Float[Array, "9 9"], wheel_radius_mm: float | None = None
) -> Float[Array, " 3"]:
    """One-sigma (z0 px or mm, theta1 rad, theta2 rad): delta method plus the floors."""
    g = jax.jacfwd(measurements)(p, wheel_radius_mm)
    var = jnp.einsum("ij,jk,ik->i", g, cov, g)
    z_floor = FLOOR_SINKAGE_PX if wheel_radius_mm is None else FLOOR_SINKAGE_PX * wheel_radius_mm / p[2]
    floor = jnp.stack(
        [jnp.asarray(z_floor, p.dtype), jnp.radians(jnp.asarray(FLOOR_ANGLE_DEG, p.dtype)), jnp.radians(jnp.asarray(FLOOR_ANGLE_DEG, p.dtype))]
    )
    return jnp.sqrt(jnp.maximum(var, 0.0) + floor**2)
