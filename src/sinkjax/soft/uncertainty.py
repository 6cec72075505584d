"""Uncertainty stage: Gauss-Newton covariance at the optimum, propagated by the delta method.

Each residual group (rim, boundary + ends) gets its own noise level from its weighted residuals.
Neighbouring outline points are not independent (the mask is smoothed and the image blurred over a
few pixels), so the covariance is inflated by a correlation length in points. What the fit cannot
see (segmentation bias shared by a whole edge, JPEG, blur) is an error floor added in quadrature.
Both constants were measured on synthetic recordings disjoint from the benchmark's
(``experiments/uncertainty_calibration.py``).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .model import N_PARAMS, Evidence, measurements, residuals


class UncertaintyModel(eqx.Module):
    """How the fit's statistical covariance becomes an honest one-sigma.

    ``scale_*`` multiply the delta-method sigma (the correlation between neighbouring outline
    points, as a square-root correlation length); ``floor_*`` are added in quadrature (error that
    the residuals cannot see: a shared shift of a whole edge by blur, JPEG or segmentation).
    The defaults are maximum-likelihood fits on synthetic recordings disjoint from the benchmark
    (``experiments/uncertainty_calibration.py``); ``UncertaintyModel.raw()`` turns all of it off.
    """

    scale_sinkage: float = 1.6
    scale_angle: float = 2.57
    floor_sinkage_px: float = 0.11
    floor_angle_deg: float = 0.07

    @staticmethod
    def raw() -> UncertaintyModel:
        return UncertaintyModel(1.0, 1.0, 0.0, 0.0)


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
            jnp.full((4,), s_end),
            jnp.ones((3,)),  # the recording rim's prior is in px already
        ]
    )
    jw = jac / scale[:, None]
    info = jw.T @ jw
    return jnp.linalg.inv(info + 1e-9 * jnp.eye(N_PARAMS))


def measurement_std(
    p: Float[Array, " 9"],
    cov: Float[Array, "9 9"],
    wheel_radius_mm: float | Float[Array, ""] | None = None,
    model: UncertaintyModel | None = None,
) -> Float[Array, " 3"]:
    """One-sigma (z0 px or mm, theta1 rad, theta2 rad): scaled delta method plus floors."""
    m = UncertaintyModel() if model is None else model
    g = jax.jacfwd(measurements)(p, wheel_radius_mm)
    var = jnp.maximum(jnp.einsum("ij,jk,ik->i", g, cov, g), 0.0)
    mm_per_px = 1.0 if wheel_radius_mm is None else wheel_radius_mm / jnp.maximum(p[2], 1.0)
    scale = jnp.stack([m.scale_sinkage, m.scale_angle, m.scale_angle]).astype(p.dtype)
    floor = jnp.stack(
        [
            m.floor_sinkage_px * mm_per_px,
            jnp.radians(m.floor_angle_deg) * jnp.ones((), p.dtype),
            jnp.radians(m.floor_angle_deg) * jnp.ones((), p.dtype),
        ]
    ).astype(p.dtype)
    return jnp.sqrt(scale**2 * var + floor**2)
