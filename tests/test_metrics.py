"""sinkjax.metrics: every statistic against numbers worked out by hand, and the one rule for
failed and no_contact frames."""

from __future__ import annotations

import math
import statistics

import numpy as np
import pytest

import sinkjax as sj
from sinkjax import metrics as sm

# Five frames: two ok, one no_contact (its value column says 3 but it reads 0), one failed (its
# value 99 must never count), one ok without a value.
TRUTH = [10.0, 4.0, 2.0, 8.0, 5.0]
EST = [10.5, 3.0, 3.0, 99.0, None]
STATUS = ["ok", "ok", "no_contact", "fit_failed", "ok"]
STD = [0.2, 0.8, None, 1.0, 0.5]


def test_measured_and_failed_follow_the_status() -> None:
    assert sm.measured(STATUS).tolist() == [True, True, True, False, True]
    assert sm.failed(STATUS).tolist() == [False, False, False, True, False]
    # Status members and plain strings are the same thing.
    assert sm.measured([sj.Status.NO_CONTACT, sj.Status.NO_WHEEL]).tolist() == [True, False]
    assert [s for s in sj.Status if s.measured] == [s for s in sj.Status if sm.measured([s])[0]]


def test_failed_pct_counts_every_status_but_ok_and_no_contact() -> None:
    assert sm.failed_pct(STATUS) == pytest.approx(20.0)  # 1 of 5
    assert sm.failed_pct(["ok", "no_contact", "no_wheel", "bad_rect"]) == 50.0
    assert math.isnan(sm.failed_pct([]))


def test_no_contact_reads_zero_and_failed_frames_are_nan() -> None:
    v = sm.measured_values(EST, STATUS)
    assert v[:3].tolist() == [10.5, 3.0, 0.0]
    assert math.isnan(v[3]) and math.isnan(v[4])


def test_errors_by_hand() -> None:
    signed = sm.signed_error(TRUTH, EST, STATUS)
    assert signed[:3].tolist() == [0.5, -1.0, -2.0]
    absolute = sm.abs_error(TRUTH, EST, STATUS)
    assert absolute[:3].tolist() == [0.5, 1.0, 2.0]
    assert np.isnan(absolute[3:]).all()
    rel = sm.relative_error_pct(TRUTH, EST, STATUS)
    # 0.5 / 10, 1 / 4, and the no_contact frame: 2 / 2 = a 100 % error.
    assert rel[:3].tolist() == pytest.approx([5.0, 25.0, 100.0])
    assert np.isnan(rel[3:]).all()


def test_relative_error_has_no_value_without_true_sinkage() -> None:
    rel = sm.relative_error_pct([0.0, -20.0], [1.0, -19.0], ["ok", "ok"])
    assert math.isnan(rel[0])
    assert rel[1] == pytest.approx(5.0)  # |(-19) - (-20)| / |-20|


def test_paper_reea_example() -> None:
    """The paper's REEA: a measured entry angle of 27.0 deg against 30.0 deg is 10 %."""
    assert sm.relative_error_pct([30.0], [27.0], ["ok"])[0] == pytest.approx(10.0)


def test_reea_and_reda_by_hand() -> None:
    """REEA / REDA = 100 |θ_est - θ_true| / |θ_true| over measured frames, worked by hand."""
    status = ["ok", "ok", "no_contact", "fit_failed", "ok", "ok"]
    true_t1 = [30.0, 20.0, 12.0, 25.0, 0.0, 16.0]
    est_t1 = [27.0, 21.0, 9.0, 25.0, 1.0, 16.4]
    # 3/30, 1/20, no_contact reads 0: 12/12, failed, no true angle, 0.4/16.
    expect_t1 = [10.0, 5.0, 100.0, math.nan, math.nan, 2.5]
    np.testing.assert_allclose(sm.reea_pct(true_t1, est_t1, status), expect_t1)
    true_t2 = [18.0, 10.0, 8.0, 20.0, 0.0, -4.0]  # the last: B ahead of O (hollow terrain)
    est_t2 = [18.9, 9.2, 5.0, 1.0, 0.5, -3.0]
    # 0.9/18, 0.8/10, 8/8, failed, no true angle, |-3 - (-4)| / |-4|.
    expect_t2 = [5.0, 8.0, 100.0, math.nan, math.nan, 25.0]
    np.testing.assert_allclose(sm.reda_pct(true_t2, est_t2, status), expect_t2)
    # Beside the absolute errors of the same frames (deg): REEA = 100 |error| / |truth|.
    np.testing.assert_allclose(
        sm.abs_error(true_t1, est_t1, status), [3.0, 1.0, 12.0, math.nan, 1.0, 0.4], atol=1e-12
    )


def test_statistics_leave_out_failed_frames() -> None:
    absolute = sm.abs_error(TRUTH, EST, STATUS)
    assert sm.count(absolute) == 3
    assert sm.median(absolute) == 1.0
    assert sm.mean(absolute) == pytest.approx(3.5 / 3)
    assert sm.maximum(absolute) == 2.0
    # numpy's linear percentile of (0.5, 1, 2): 90 % lies 0.8 of the way from 1 to 2.
    assert sm.percentile(absolute, 90) == pytest.approx(1.8)
    assert sm.median([1.0, 2.0, 4.0, 8.0]) == statistics.median([1.0, 2.0, 4.0, 8.0]) == 3.0
    for f in (sm.median, sm.mean, sm.maximum):
        assert math.isnan(f([math.nan, None]))
    assert math.isnan(sm.percentile([], 50))


def test_coverage_only_over_ok_frames_with_a_sigma() -> None:
    # Frame 0: |0.5| <= 1.96 * 0.2 = 0.392? no. Frame 1: |1| <= 1.96 * 0.8 = 1.568? yes. The
    # no_contact and failed frames and the ok frame without a value have no interval.
    hits = sm.covered(TRUTH, EST, STD, STATUS)
    assert hits[:2].tolist() == [0.0, 1.0]
    assert np.isnan(hits[2:]).all()
    assert sm.coverage_pct(TRUTH, EST, STD, STATUS) == 50.0
    assert sm.coverage_pct(TRUTH, EST, STD, STATUS, k=3.0) == 100.0  # 0.5 <= 0.6, 1 <= 2.4
    assert sm.coverage_pct(TRUTH, EST, STD, STATUS, k=1.0) == 0.0  # 0.5 > 0.2, 1 > 0.8
    # A zero or NaN sigma is no interval.
    assert math.isnan(sm.coverage_pct([1.0, 1.0], [1.0, 1.0], [0.0, math.nan], ["ok", "ok"]))


def test_coverage_of_gaussian_errors_is_nominal() -> None:
    rng = np.random.default_rng(0)
    sd = rng.uniform(0.5, 2.0, 20000)
    est = rng.standard_normal(20000) * sd
    status = ["ok"] * est.size
    for k, p in ((1.0, 68.27), (1.96, 95.0), (2.576, 99.0)):
        assert sm.coverage_pct(np.zeros_like(est), est, sd, status, k=k) == pytest.approx(
            p, abs=1.0
        )


def test_mismatched_lengths_raise() -> None:
    with pytest.raises(ValueError, match="one entry per frame"):
        sm.abs_error([1.0, 2.0], [1.0], ["ok"])
    with pytest.raises(ValueError, match="one entry per frame"):
        sm.measured_values([1.0, 2.0], ["ok"])


def test_the_rule_is_stated() -> None:
    assert "no_contact" in sm.RULE and "failed" in sm.RULE
    assert sj.metrics is sm
