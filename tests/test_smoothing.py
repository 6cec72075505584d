"""The random-walk Kalman/RTS smoother against hand-computed cases, and its CSV columns."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from sinkjax.app.results import COLUMNS
from sinkjax.app.smoothing import (
    SMOOTH_COLUMNS,
    SmoothingOptions,
    rts_random_walk,
    series_time,
    smooth_csv,
    smooth_rows,
)


def test_steady_state_variance_matches_the_riccati_solution():
    # Random walk (q) seen through white noise (r). The filter's steady state solves
    # P = (P + q) r / (P + q + r), i.e. P^2 + qP - qr = 0; the RTS smoother's steady state is
    # P_s = P (P + q) / (2P + q) = q r / sqrt(q^2 + 4 q r) (using P^2 + qP = qr).
    q, r, n = 0.04, 1.0, 4001
    rng = np.random.default_rng(1)
    truth = 3.0 + np.cumsum(rng.normal(0.0, math.sqrt(q), n))
    y = truth + rng.normal(0.0, math.sqrt(r), n)
    mean, var = rts_random_walk(y, np.full(n, r), q)
    p_filter = (-q + math.sqrt(q * q + 4 * q * r)) / 2
    p_smooth = q * r / math.sqrt(q * q + 4 * q * r)
    assert p_smooth == pytest.approx(p_filter * (p_filter + q) / (2 * p_filter + q))
    assert var[n // 2] == pytest.approx(p_smooth, rel=1e-9)
    # At the last frame the smoother has only the past: the filter's steady state.
    assert var[-1] == pytest.approx(p_filter, rel=1e-9)
    # On data from the model, the errors have the claimed variance.
    err = (mean - truth)[200:-200]
    assert np.mean(err**2) == pytest.approx(p_smooth, rel=0.15)


def test_no_process_noise_is_the_inverse_variance_weighted_mean():
    y = np.array([1.0, 2.0, np.nan, 4.0])
    r = np.array([1.0, 4.0, 9.0, 0.25])
    mean, var = rts_random_walk(y, r, 0.0)
    w = 1 / r[[0, 1, 3]]
    expected = float(np.sum(w * y[[0, 1, 3]]) / np.sum(w))
    np.testing.assert_allclose(mean, expected, rtol=1e-12)
    np.testing.assert_allclose(var, 1 / np.sum(w), rtol=1e-12)


def test_gap_and_edges_by_hand():
    # Two measurements 0 and 2 (r = 1) at t = 0 and t = 2, a missing frame between, q = 1.
    # Filter: t0 m=0 P=1; t1 prior P=2; t2 prior P=3, gain 3/4 -> m=1.5, P=3/4.
    # Smoother: t1 gain J=2/3 (P_f=2, P_pred=3): m = 0 + 2/3 (1.5 - 0) = 1, P = 2 + 4/9 (3/4 - 3)
    # = 1; t0 gain J=1/2: m = 0 + 1/2 (1 - 0) = 1/2, P = 1 + 1/4 (1 - 2) = 3/4.
    mean, var = rts_random_walk(np.array([0.0, np.nan, 2.0]), np.ones(3), 1.0)
    np.testing.assert_allclose(mean, [0.5, 1.0, 1.5])
    np.testing.assert_allclose(var, [0.75, 1.0, 0.75])
    # The same with explicit times (a --stride 2 recording without the middle row).
    mean_t, var_t = rts_random_walk(np.array([0.0, 2.0]), np.ones(2), 1.0, np.array([10.0, 12.0]))
    np.testing.assert_allclose(mean_t, [0.5, 1.5])
    np.testing.assert_allclose(var_t, [0.75, 0.75])
    # Before the first and after the last measurement the variance grows by q per frame.
    mean, var = rts_random_walk(np.array([np.nan, np.nan, 5.0, np.nan]), np.ones(4), 0.5)
    np.testing.assert_allclose(mean, 5.0)
    np.testing.assert_allclose(var, [2.0, 1.5, 1.0, 1.5])


def test_degenerate_inputs():
    mean, var = rts_random_walk(np.full(3, np.nan), np.ones(3), 1.0)
    assert np.isnan(mean).all() and np.isnan(var).all()
    assert rts_random_walk(np.zeros(0), np.zeros(0), 1.0)[0].shape == (0,)
    # Zero measurement variance and zero process noise: finite, pinned to the measurements' mean.
    mean, var = rts_random_walk(np.array([1.0, 1.0]), np.zeros(2), 0.0)
    assert np.isfinite(mean).all() and np.isfinite(var).all()
    with pytest.raises(ValueError, match="non-decreasing"):
        rts_random_walk(np.ones(2), np.ones(2), 1.0, np.array([1.0, 0.0]))
    with pytest.raises(ValueError, match="--process-std-mm"):
        SmoothingOptions(process_std_mm=-1.0)
    with pytest.raises(ValueError, match="--measurement-std-deg"):
        SmoothingOptions(measurement_std_deg=0.0)


def _row(image: str, status: str = "ok", z: str = "", z_std: str = "") -> dict[str, str]:
    row = dict.fromkeys(COLUMNS, "")
    row.update(image=image, status=status, sinkage_mm=z, sinkage_std_mm=z_std)
    row.update(theta1_deg=z, theta2_deg=z)
    return row


def test_series_time_and_segments():
    images = ["v.mp4#000000", "v.mp4#000004", "a.png", "b.png", "w.mp4#000002", "c.png"]
    keys, t = series_time(images)
    assert keys == ["v.mp4", "v.mp4", "", "", "w.mp4", ""]
    np.testing.assert_array_equal(t, [0, 4, 0, 1, 2, 0])
    rows = [
        _row("v.mp4#000000", z="1", z_std="1"),
        _row("v.mp4#000001", status="no_wheel"),
        _row("v.mp4#000002", z="3", z_std="1"),
        _row("w.mp4#000000", z="10"),  # classic: no std -> the fallback std
        _row("w.mp4#000001", status="unreadable"),
    ]
    options = SmoothingOptions(process_std_mm=1.0, measurement_std_mm=1.0)
    out = smooth_rows(rows, options)
    # v.mp4 is the hand-computed gap case above (values 1 and 3 instead of 0 and 2).
    assert [o["sinkage_smooth_mm"] for o in out[:3]] == pytest.approx([1.5, 2.0, 2.5])
    assert out[1]["sinkage_smooth_std_mm"] == pytest.approx(1.0)
    # w.mp4 is its own series: one measurement, the failed frame one step later.
    assert out[3]["sinkage_smooth_mm"] == pytest.approx(10.0)
    assert out[4]["sinkage_smooth_std_mm"] == pytest.approx(math.sqrt(2.0))


def test_smooth_csv_adds_columns_after_the_contract(tmp_path):
    src = tmp_path / "r.csv"
    with open(src, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(COLUMNS)
        for i, z in enumerate(["1.5", "2.5", ""]):
            status = "ok" if z else "no_wheel"
            w.writerow([f"f{i}.png", status, z, "0.5", z, "1", z, "1", "", "", "", ""])
    before = src.read_text().splitlines()
    smooth_csv(src, options=SmoothingOptions())
    after = src.read_text().splitlines()
    assert after[0] == ",".join((*COLUMNS, *SMOOTH_COLUMNS))
    for old, new in zip(before[1:], after[1:], strict=True):
        assert new.startswith(old + ",")  # the contract's cells are untouched
    with open(src, newline="") as f:
        rows = list(csv.DictReader(f))
    assert all(rows[i]["sinkage_smooth_mm"] for i in range(3))  # the failed frame is bridged
    # Smoothing twice gives the same file.
    text = src.read_text()
    smooth_csv(src)
    assert src.read_text() == text
