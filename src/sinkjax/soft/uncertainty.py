"""Uncertainty stage: Gauss-Newton covariance at the optimum, propagated by the delta method.

Each residual group (rim, boundary + ends) gets its own noise level from its weighted residuals.
Neighbouring outline points are not independent (the mask is smoothed and the image blurred over a
few pixels), so the covariance is inflated by a correlation length in points. What the fit cannot
see (segmentation bias shared by a whole edge, JPEG, blur) is an error floor added in quadrature.
The errors are heavier-tailed than a Gaussian (a frame's sigma is itself uncertain): error /
sigma follows a Student-t with ``dof_*`` degrees of freedom. The reported one-sigma is that
t's standard deviation, so value ± 1.96 sigma stays close to a 95 % interval (within a point for
dof > 3); the interval at any level p is value ± :meth:`UncertaintyModel.multiplier` (p) · sigma
(at 50 % about 0.5 sigma rather than 0.67: most errors are smaller than a Gaussian's, a few far
larger). All constants, per quantity, are maximum-likelihood fits on synthetic
recordings disjoint from the benchmark's (``experiments/uncertainty_calibration.py``).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .model import N_PARAMS, Evidence, measurements, residuals

QUANTITIES = ("sinkage", "theta1", "theta2")  # the order of every per-quantity stack
# Above this many degrees of freedom the quantile's expansion in 1/dof (Cornish-Fisher, three
# terms) is exact to 1e-7; below it the bisection is, in float32 too.
_EXPANSION_DOF = 100.0
_BISECTIONS = 100
MIN_DOF = 2.5  # the fewest degrees of freedom a model may have: its t keeps a standard deviation
# The levels at which a model's interval multipliers are corrected to the errors' own quantiles
# (UncertaintyModel.level_adjust); between them the correction is interpolated, beyond them held.
ADJUST_LEVELS = (0.5, 0.68, 0.8, 0.9, 0.95, 0.99)
NO_ADJUST = 3 * ((1.0,) * len(ADJUST_LEVELS),)  # the t's own multipliers


def central_multiplier(level: ArrayLike, dof: ArrayLike = math.inf) -> Float[Array, "*shape"]:
    """Half-width, in scale units, of the central interval holding ``level`` of a Student-t with
    ``dof`` degrees of freedom (``math.inf``: the Gaussian, 1.96 at 0.95). Broadcasts; jit-able.

    Solves P(|T| <= k) = 1 - I_x(dof/2, 1/2) = level, x = dof / (dof + k^2), for x by bisection
    (I the regularised incomplete beta function); for dof >= 100 the expansion of the quantile
    about the Gaussian's z in powers of 1/dof.
    """
    dtype = jax.dtypes.canonicalize_dtype(jnp.float64)
    shape = jnp.broadcast_shapes(jnp.shape(level), jnp.shape(dof))
    p = jnp.broadcast_to(jnp.asarray(level, dtype), shape)
    nu = jnp.broadcast_to(jnp.asarray(dof, dtype), shape)
    z = jnp.sqrt(2.0) * jax.scipy.special.erfinv(p)
    g = 1.0 / jnp.maximum(nu, _EXPANSION_DOF)  # 0 for the Gaussian
    z2 = z * z
    expansion = z * (
        1.0
        + g * (z2 + 1.0) / 4.0
        + g**2 * ((5.0 * z2 + 16.0) * z2 + 3.0) / 96.0
        + g**3 * (((3.0 * z2 + 19.0) * z2 + 17.0) * z2 - 15.0) / 384.0
    )
    t_like = nu < _EXPANSION_DOF
    a = 0.5 * jnp.where(t_like, nu, 1.0)
    x = _beta_root(a, 1.0 - p)
    student = jnp.sqrt(2.0 * a * (1.0 - x) / x)
    return jnp.where(t_like, student, expansion)


@jax.jit
def _beta_root(a: Array, target: Array) -> Array:
    # x in (0, 1] with I_x(a, 1/2) = target, by bisection. Jitted on its own so that a call
    # outside jit compiles once per shape (an eager fori_loop would compile anew for every
    # level: a reliability curve of 50 levels took 40 s).
    def halve(_: Array, bounds: tuple[Array, Array]) -> tuple[Array, Array]:
        lo, hi = bounds
        mid = 0.5 * (lo + hi)
        above = jax.scipy.special.betainc(a, 0.5, mid) > target
        return jnp.where(above, lo, mid), jnp.where(above, mid, hi)

    lo, hi = jax.lax.fori_loop(0, _BISECTIONS, halve, (jnp.zeros_like(a), jnp.ones_like(a)))
    return jnp.clip(0.5 * (lo + hi), jnp.finfo(a.dtype).tiny, 1.0)


class UncertaintyModel(eqx.Module):
    """How the fit's statistical covariance becomes an honest one-sigma, per quantity.

    For each of sinkage z0, entry angle θ1 and exit angle θ2: ``scale_*`` multiplies the
    delta-method sigma (the correlation between neighbouring outline points, as a square-root
    correlation length); ``floor_*`` is added in quadrature (error that the residuals cannot see:
    a shared shift of a whole edge by blur, JPEG or segmentation); ``dof_*`` are the degrees of
    freedom of the Student-t that error / sigma follows (``math.inf``: Gaussian; at least 2.5, so
    that it has a standard deviation). ``scale_*`` and ``floor_*`` give the t's scale; the
    reported sigma (the ``*_std_*`` columns, docs/conventions.md §4) is its standard deviation,
    the scale times sqrt(dof / (dof - 2)). The interval at level p is value ± ``multiplier(p)`` ·
    sigma, e.g. a 50 % interval for the sinkage::

        k = float(UncertaintyModel().multiplier(0.5, "sinkage"))
        low, high = sinkage_mm - k * sinkage_std_mm, sinkage_mm + k * sinkage_std_mm

    The errors are more peaked than any t that also holds their tails (most frames err by far
    less than their sigma, a few by several sigmas), so ``level_adjust`` corrects the t's
    multipliers, per quantity, at the :data:`ADJUST_LEVELS`: each factor is the empirical
    quantile of |error| / sigma on the calibration recordings over the t's multiplier at that
    level (recalibrating the quantiles of a predictive distribution, as in Kuleshov et al. 2018,
    "Accurate uncertainties for deep learning using calibrated regression"). It changes no sigma,
    only which multiple of it an interval at a given level spans.

    The defaults are maximum-likelihood fits on synthetic recordings disjoint from the benchmark
    (``python experiments/uncertainty_calibration.py --update-source`` refits and rewrites them);
    ``UncertaintyModel.raw()`` turns all of it off (scale 1, no floor, Gaussian, no adjustment).
    """

    scale_sinkage: float = 0.836
    scale_theta1: float = 1.022
    scale_theta2: float = 1.124
    floor_sinkage_px: float = 0.05
    floor_theta1_deg: float = 0.0
    floor_theta2_deg: float = 0.0
    dof_sinkage: float = 3.82
    dof_theta1: float = 2.69
    dof_theta2: float = 3.37
    # Per quantity (z0, θ1, θ2), the factor on the t's multiplier at each of ADJUST_LEVELS.
    level_adjust: tuple[tuple[float, ...], ...] = eqx.field(
        default=(
            (0.874, 1.029, 1.083, 1.034, 1.019, 0.956),
            (0.915, 0.982, 1.025, 1.101, 1.059, 0.911),
            (0.898, 0.975, 1.029, 1.095, 1.109, 0.943),
        ),
        static=True,
    )

    @staticmethod
    def raw() -> UncertaintyModel:
        """The delta-method sigma as it is: scale 1, no floor, Gaussian, no level correction."""
        return UncertaintyModel(
            1.0, 1.0, 1.0, 0.0, 0.0, 0.0, math.inf, math.inf, math.inf, level_adjust=NO_ADJUST
        )

    def scales(self) -> Float[Array, " 3"]:
        """The sigma scales of z0, θ1, θ2."""
        return jnp.stack([jnp.asarray(self.scale_sinkage), self.scale_theta1, self.scale_theta2])

    def floors(self) -> Float[Array, " 3"]:
        """The floors of z0 (px), θ1 and θ2 (deg)."""
        return jnp.stack(
            [jnp.asarray(self.floor_sinkage_px), self.floor_theta1_deg, self.floor_theta2_deg]
        )

    def dofs(self) -> Float[Array, " 3"]:
        """The Student-t degrees of freedom of z0, θ1, θ2 (inf: Gaussian)."""
        return jnp.stack([jnp.asarray(self.dof_sinkage), self.dof_theta1, self.dof_theta2])

    def std_factors(self) -> Float[Array, " 3"]:
        """Standard deviation over scale of each quantity's t: sqrt(dof / (dof - 2)); 1 for the
        Gaussian. The degrees of freedom are held above 2.5 (a finite standard deviation)."""
        nu = jnp.maximum(self.dofs(), MIN_DOF)
        return jnp.where(jnp.isinf(nu), 1.0, jnp.sqrt(nu / jnp.where(jnp.isinf(nu), 1.0, nu - 2.0)))

    def multiplier(self, level: ArrayLike, quantity: str | None = None) -> Float[Array, "*q"]:
        """How many (reported) sigmas each side of the value the central interval at ``level``
        (e.g. 0.95) spans: for ``quantity`` ("sinkage", "theta1" or "theta2") a scalar (or the
        shape of ``level``), else z0, θ1, θ2 for a scalar ``level``. The t's multiplier times the
        ``level_adjust`` factor interpolated at ``level``."""
        dofs, factors = jnp.maximum(self.dofs(), MIN_DOF), self.std_factors()
        grid = jnp.asarray(ADJUST_LEVELS)
        table = jnp.asarray(self.level_adjust, dtype=grid.dtype)
        if quantity is not None:
            if quantity not in QUANTITIES:
                raise ValueError(f"quantity must be one of {QUANTITIES}, got {quantity!r}")
            i = QUANTITIES.index(quantity)
            adjust = jnp.interp(jnp.asarray(level, grid.dtype), grid, table[i])
            return central_multiplier(level, dofs[i]) / factors[i] * adjust
        adjust = jnp.stack([jnp.interp(jnp.asarray(level, grid.dtype), grid, t) for t in table])
        return central_multiplier(level, dofs) / factors * adjust

    def interval(
        self, level: float, quantity: str, value: ArrayLike, std: ArrayLike
    ) -> tuple[Float[Array, "*n"], Float[Array, "*n"]]:
        """The central interval (low, high) at ``level`` around ``value`` with one-sigma ``std``
        (the result's or the CSV's value and ``*_std_*`` column, any unit)."""
        k = self.multiplier(level, quantity)
        v, s = jnp.asarray(value), jnp.asarray(std)
        return v - k * s, v + k * s


def _group_scale(res: Array, w: Array) -> Array:
    # Weighted RMS of the unweighted residuals (res already carries sqrt(w)); at least 0.05 px.
    sw = jnp.sum(w)
    var = jnp.sum(res * res) / jnp.maximum(sw - 3.0, 1.0)
    return jnp.sqrt(jnp.maximum(var, 0.05**2))


def covariance(p: Float[Array, " P"], ev: Evidence) -> Float[Array, "P P"]:
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
            jnp.full((6,), s_end),  # the ends' priors: angles, offsets, bends
            jnp.ones((3,)),  # the recording rim's prior is in px already
        ]
    )
    jw = jac / scale[:, None]
    info = jw.T @ jw
    return jnp.linalg.inv(info + 1e-9 * jnp.eye(N_PARAMS))


def measurement_std(
    p: Float[Array, " P"],
    cov: Float[Array, "P P"],
    wheel_radius_mm: float | Float[Array, ""] | None = None,
    model: UncertaintyModel | None = None,
) -> Float[Array, " 3"]:
    """One-sigma (z0 px or mm, theta1 rad, theta2 rad): scaled delta method plus floors."""
    m = UncertaintyModel() if model is None else model
    g = jax.jacfwd(measurements)(p, wheel_radius_mm)
    var = jnp.maximum(jnp.einsum("ij,jk,ik->i", g, cov, g), 0.0)
    mm_per_px = 1.0 if wheel_radius_mm is None else wheel_radius_mm / jnp.maximum(p[2], 1.0)
    scale = (m.scales() * m.std_factors()).astype(p.dtype)
    one = jnp.ones((), p.dtype)
    floor = m.floors().astype(p.dtype) * jnp.stack(
        [mm_per_px * one, jnp.radians(one), jnp.radians(one)]
    )
    return jnp.sqrt(scale**2 * var + (floor * m.std_factors().astype(p.dtype)) ** 2)
