"""Errors of estimates against a known truth: ONE definition for the experiments, demo and README.

Every function takes per-frame arrays (or sequences) of the truth, the estimates and the frames'
statuses, in the units of the quantity (mm for sinkage, degrees for angles), and applies the same
rule for frames that did not give an ordinary measurement (:data:`RULE`, quoted in every table
caption):

- a frame is *measured* when its status is ``ok`` or ``no_contact`` (:attr:`Status.measured`);
- ``no_contact`` is a measurement of 0: sinkage 0 and both angles 0 (docs/conventions.md §1),
  whatever the value column holds;
- every other status is *failed*: its errors are NaN, so it is left out of every error statistic
  (median, percentile, maximum) and counted in :func:`failed_pct` instead;
- only ``ok`` frames report a one-sigma uncertainty: :func:`coverage_pct` is over the ``ok``
  frames with a finite sigma > 0.

Which frames enter a statistic by their TRUTH (sinkage above 5 mm, contact frames only, ...) is
the caller's choice, made with a boolean mask before calling; these functions never select by
truth except where a relative error has no denominator (truth 0).

Example::

    >>> import numpy as np
    >>> from sinkjax import metrics
    >>> truth = np.array([10.0, 4.0, 8.0])
    >>> est = np.array([10.5, 0.0, np.nan])
    >>> status = ["ok", "no_contact", "fit_failed"]
    >>> metrics.relative_error_pct(truth, est, status).tolist()
    [5.0, 100.0, nan]
    >>> metrics.failed_pct(status)
    33.33333333333333
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np
from jaxtyping import Bool, Float

from .status import Status

RULE = (
    "failed frames (any status but `ok` and `no_contact`) are left out of the error statistics "
    "and counted as failed; `no_contact` counts as a measurement of 0 (sinkage and both angles)"
)
RULE_COVERAGE = "coverage is over the `ok` frames with a finite reported σ > 0"

Values = Float[np.ndarray, " n"] | Sequence[float | None]
Statuses = Sequence[str] | np.ndarray


def _status(status: Statuses) -> np.ndarray:
    return np.asarray([str(s) for s in status], dtype=object)


def _floats(values: Values | Iterable[float | None]) -> Float[np.ndarray, " n"]:
    """A float64 array; None (a missing CSV cell or result field) becomes NaN."""
    return np.asarray([math.nan if v is None else v for v in values], dtype=np.float64)


def measured(status: Statuses) -> Bool[np.ndarray, " n"]:
    """True for frames with a measurement: status ``ok`` or ``no_contact``."""
    s = _status(status)
    return (s == Status.OK.value) | (s == Status.NO_CONTACT.value)


def failed(status: Statuses) -> Bool[np.ndarray, " n"]:
    """True for failed frames: any status but ``ok`` and ``no_contact``."""
    return ~measured(status)


def failed_pct(status: Statuses) -> float:
    """Percentage of frames that failed (NaN for no frames)."""
    bad = failed(status)
    return 100 * int(bad.sum()) / bad.size if bad.size else math.nan


def measured_values(estimate: Values, status: Statuses) -> Float[np.ndarray, " n"]:
    """The estimates as the error statistics read them: ``ok`` its value, ``no_contact`` 0,
    failed NaN. Shape (n,), the unit of ``estimate``."""
    est = _floats(estimate)
    s = _status(status)
    if est.shape != s.shape:
        raise ValueError(
            f"estimate and status must have one entry per frame, got {est.shape} and {s.shape}"
        )
    out = np.where(s == Status.NO_CONTACT.value, 0.0, est)
    return np.where(measured(s), out, math.nan)


def signed_error(truth: Values, estimate: Values, status: Statuses) -> Float[np.ndarray, " n"]:
    """Estimate - truth per frame (NaN for failed frames), in the quantity's unit."""
    t = _floats(truth)
    est = measured_values(estimate, status)
    if t.shape != est.shape:
        raise ValueError(
            f"truth and estimate must have one entry per frame, got {t.shape} and {est.shape}"
        )
    return est - t


def abs_error(truth: Values, estimate: Values, status: Statuses) -> Float[np.ndarray, " n"]:
    """|estimate - truth| per frame (NaN for failed frames), in the quantity's unit."""
    return np.abs(signed_error(truth, estimate, status))


def relative_error_pct(
    truth: Values, estimate: Values, status: Statuses
) -> Float[np.ndarray, " n"]:
    """100 |estimate - truth| / |truth| per frame: the paper's REDS, REEA and REDA (%; for the
    angles by name: :func:`reea_pct`, :func:`reda_pct`).

    NaN for failed frames and where the truth is 0 (no denominator: a frame without true
    contact). A ``no_contact`` frame with true contact has a 100 % error.
    """
    t = _floats(truth)
    err = abs_error(t, estimate, status)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(t != 0, 100.0 * err / np.abs(t), math.nan)


def reea_pct(
    true_theta1_deg: Values, theta1_deg: Values, status: Statuses
) -> Float[np.ndarray, " n"]:
    """The paper's REEA per frame: the relative error of the entry angle,
    100 |θ1_estimate - θ1_true| / |θ1_true| (%), θ1 as docs/conventions.md §1 defines it.

    The paper quotes it (with REDS and REDA) over frames whose true sinkage is above 5 mm, where
    it reports about 5 %; that selection is the caller's. NaN for failed frames and where the true
    angle is 0 (no true contact); a ``no_contact`` frame with true contact reads θ1 = 0, a 100 %
    error. Pairs with :func:`abs_error` of the same arguments, the absolute error in degrees.
    """
    return relative_error_pct(true_theta1_deg, theta1_deg, status)


def reda_pct(
    true_theta2_deg: Values, theta2_deg: Values, status: Statuses
) -> Float[np.ndarray, " n"]:
    """The paper's REDA per frame: the relative error of the exit (departure) angle,
    100 |θ2_estimate - θ2_true| / |θ2_true| (%); otherwise as :func:`reea_pct`."""
    return relative_error_pct(true_theta2_deg, theta2_deg, status)


def covered(
    truth: Values, estimate: Values, std: Values, status: Statuses, *, k: float = 1.96
) -> Float[np.ndarray, " n"]:
    """1.0 where |estimate - truth| <= k std, 0.0 where not, NaN for frames without an interval
    (status not ``ok``, no value, or std not finite or <= 0). ``std``: the reported one-sigma, in
    the quantity's unit."""
    sd = _floats(std)
    s = _status(status)
    err = abs_error(truth, estimate, s)
    with np.errstate(invalid="ignore"):
        has = (s == Status.OK.value) & np.isfinite(sd) & (sd > 0) & np.isfinite(err)
    with np.errstate(invalid="ignore"):
        return np.where(has, (err <= k * sd).astype(np.float64), math.nan)


def coverage_pct(
    truth: Values, estimate: Values, std: Values, status: Statuses, *, k: float = 1.96
) -> float:
    """Percentage of the frames with an interval whose ±k std interval holds the truth (NaN when
    no frame has one). k = 1.96 is the nominal 95 % interval of a Gaussian."""
    return 100 * mean(covered(truth, estimate, std, status, k=k))


def finite(values: Values | Iterable[float | None]) -> Float[np.ndarray, " m"]:
    """The finite entries of ``values`` (the frames an error statistic is over)."""
    v = _floats(values)
    return v[np.isfinite(v)]


def percentile(values: Values | Iterable[float | None], q: float) -> float:
    """The q-th percentile (linear interpolation) of the finite values; NaN when there are none."""
    v = finite(values)
    return float(np.percentile(v, q)) if v.size else math.nan


def median(values: Values | Iterable[float | None]) -> float:
    """The median of the finite values; NaN when there are none."""
    v = finite(values)
    return float(np.median(v)) if v.size else math.nan


def mean(values: Values | Iterable[float | None]) -> float:
    """The mean of the finite values; NaN when there are none."""
    v = finite(values)
    return float(np.mean(v)) if v.size else math.nan


def maximum(values: Values | Iterable[float | None]) -> float:
    """The largest finite value; NaN when there are none."""
    v = finite(values)
    return float(np.max(v)) if v.size else math.nan


def count(values: Values | Iterable[float | None]) -> int:
    """How many values are finite (the frames a statistic is over)."""
    return int(finite(values).size)
