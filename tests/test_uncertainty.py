"""The soft method's uncertainty model: per-quantity scales and floors, and the interval multiplier
of a Gaussian or Student-t model against scipy.stats."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import sinkjax as sj
from sinkjax.soft.uncertainty import (
    ADJUST_LEVELS,
    NO_ADJUST,
    QUANTITIES,
    UncertaintyModel,
    central_multiplier,
    measurement_std,
)

LEVELS = (0.5, 0.68, 0.8, 0.9, 0.95, 0.99)


def test_gaussian_multiplier_at_95_is_1_96() -> None:
    gaussian = UncertaintyModel.raw()
    ref = stats.norm.ppf(0.975)
    assert ref == pytest.approx(1.959964, abs=1e-6)
    for q in QUANTITIES:
        assert float(gaussian.multiplier(0.95, q)) == pytest.approx(ref, rel=1e-5)
    for p in LEVELS:
        assert float(central_multiplier(p)) == pytest.approx(stats.norm.ppf(0.5 + p / 2), rel=1e-5)


def test_multiplier_outside_jit_compiles_once_per_shape() -> None:
    # An eager bisection loop would compile anew for every level (a 50-level curve: 40 s).
    from sinkjax.soft.uncertainty import _beta_root

    model = UncertaintyModel()
    float(model.multiplier(0.5, "sinkage"))
    before = _beta_root._cache_size()
    for p in (0.37, 0.61, 0.83, 0.97):
        k = float(model.multiplier(p, "theta1"))
        assert math.isfinite(k) and k > 0
    assert _beta_root._cache_size() == before


@pytest.mark.parametrize("dof", [1.0, 2.5, 4.0, 7.3, 30.0, 250.0])
def test_student_t_multiplier_matches_scipy(dof: float) -> None:
    got = np.asarray(central_multiplier(np.asarray(LEVELS), dof))
    np.testing.assert_allclose(got, stats.t.ppf(0.5 + np.asarray(LEVELS) / 2, dof), rtol=1e-4)


def test_model_multiplier_and_interval_per_quantity() -> None:
    m = UncertaintyModel(
        dof_sinkage=3.0, dof_theta1=math.inf, dof_theta2=12.0, level_adjust=NO_ADJUST
    )
    # In units of the reported sigma, the t's standard deviation (scipy's t.std).
    ref = [
        stats.t.ppf(0.975, 3.0) / stats.t.std(3.0),
        stats.norm.ppf(0.975),
        stats.t.ppf(0.975, 12.0) / stats.t.std(12.0),
    ]
    np.testing.assert_allclose(np.asarray(m.multiplier(0.95)), ref, rtol=1e-4)
    low, high = m.interval(0.95, "theta2", np.asarray([20.0, 30.0]), np.asarray([0.5, 1.0]))
    np.testing.assert_allclose(np.asarray(low), [20.0 - 0.5 * ref[2], 30.0 - ref[2]], rtol=1e-5)
    np.testing.assert_allclose(np.asarray(high), [20.0 + 0.5 * ref[2], 30.0 + ref[2]], rtol=1e-5)
    with pytest.raises(ValueError, match="quantity"):
        m.multiplier(0.95, "theta3")
    # Jit-able, and the same under jit.
    jitted = jax.jit(central_multiplier)(jnp.asarray(0.9), jnp.asarray(5.0))
    assert float(jitted) == pytest.approx(stats.t.ppf(0.95, 5.0), rel=1e-4)


def test_each_quantity_has_its_own_scale_and_floor() -> None:
    # Any parameter vector and covariance: sigma^2 = (scale sigma_raw)^2 + floor^2 per quantity,
    # floors in px times mm/px for z0 and in degrees (as radians) for the angles.
    p = jnp.asarray([160.0, 120.0, 80.0, 0.05, 60.0, 0.0, 62.0, 0.0, 63.0])
    a = np.random.default_rng(1).normal(size=(9, 9))
    cov = jnp.asarray(0.01 * a @ a.T + 1e-3 * np.eye(9))
    radius_mm = 140.0
    raw = np.asarray(measurement_std(p, cov, radius_mm, UncertaintyModel.raw()))
    m = UncertaintyModel(1.5, 2.5, 3.5, 0.2, 0.1, 0.3, math.inf, 4.0, 9.0)
    got = np.asarray(measurement_std(p, cov, radius_mm, m))
    floor = np.asarray([0.2 * radius_mm / 80.0, math.radians(0.1), math.radians(0.3)])
    t_scale = np.sqrt((np.asarray([1.5, 2.5, 3.5]) * raw) ** 2 + floor**2)
    # The reported sigma is the standard deviation of the t with that scale (scipy).
    std = [1.0, stats.t.std(4.0), stats.t.std(9.0)]
    np.testing.assert_allclose(got, t_scale * np.asarray(std), rtol=1e-5)
    # The public name is the same class; the fitted defaults are finite and positive.
    assert sj.UncertaintyModel is UncertaintyModel
    d = UncertaintyModel()
    assert np.all(np.asarray(d.scales()) > 0) and np.all(np.asarray(d.floors()) >= 0)
    assert np.all(np.asarray(d.dofs()) > 2)  # a finite variance


def test_level_adjustment_scales_the_t_multiplier_by_the_interpolated_factor() -> None:
    # Factors at ADJUST_LEVELS (numpy's interp between them, held beyond) times scipy's t
    # quantile over the t's standard deviation.
    table = ((0.8, 0.9, 1.0, 1.1, 1.2, 1.3), (1.0,) * 6, (1.3, 1.2, 1.1, 1.0, 0.9, 0.8))
    m = UncertaintyModel(dof_sinkage=4.0, dof_theta1=6.0, dof_theta2=3.0, level_adjust=table)
    levels = np.asarray([0.3, 0.5, 0.6, 0.85, 0.95, 0.97, 0.995])
    for i, (q, dof) in enumerate(zip(QUANTITIES, (4.0, 6.0, 3.0), strict=True)):
        t = stats.t.ppf(0.5 + levels / 2, dof) / stats.t.std(dof)
        ref = t * np.interp(levels, ADJUST_LEVELS, table[i])
        np.testing.assert_allclose(np.asarray(m.multiplier(levels, q)), ref, rtol=1e-4)
        both = np.asarray(m.multiplier(0.6))
        assert both[i] == pytest.approx(float(m.multiplier(0.6, q)), rel=1e-12)
    # The shipped model is adjusted by less than half either way, and raw() not at all.
    assert np.all(np.abs(np.log(np.asarray(UncertaintyModel().level_adjust))) < np.log(1.5))
    assert UncertaintyModel.raw().level_adjust == NO_ADJUST


@pytest.mark.parametrize("dof", [3.2, 4.0, 6.0, 20.0])
def test_reported_sigma_keeps_1_96_close_to_95_percent(dof: float) -> None:
    # The CSV's sigma is the t's standard deviation, so ±1.96 sigma holds about 95 % of a
    # heavy-tailed error (scipy's t cdf), and the model's own 95 % multiplier is exact.
    m = UncertaintyModel(dof_sinkage=dof, dof_theta1=dof, dof_theta2=dof, level_adjust=NO_ADJUST)
    sd = stats.t.std(dof)
    assert 100 * (2 * stats.t.cdf(1.96 * sd, dof) - 1) == pytest.approx(95.0, abs=1.0)
    k = float(m.multiplier(0.95, "theta1"))
    assert 2 * stats.t.cdf(k * sd, dof) - 1 == pytest.approx(0.95, abs=1e-4)
    # At 50 % the heavy-tailed interval is narrower than the Gaussian's 0.674 sigma.
    assert float(m.multiplier(0.5, "sinkage")) < stats.norm.ppf(0.75)
