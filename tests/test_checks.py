"""Plausibility checks (issue 12 item 5): the soft stage ``soft.checks`` and the classic one."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sinkjax import synth as S
from sinkjax.classic.estimator import implausibility, recording_radius_px
from sinkjax.result import FrameResult
from sinkjax.soft.checks import TESTS, message
from sinkjax.soft.estimator import measure_from_mask
from sinkjax.soft.segmentation import wheel_mask
from sinkjax.status import Status

_measure = jax.jit(measure_from_mask, static_argnames=("travel", "wheel_radius_mm"))


def test_soft_checks_pass_a_clean_frame_and_flag_a_mask_that_lost_part_of_the_rim() -> None:
    rng = np.random.default_rng(4)
    scenes = S.recording_scenes(rng, 1, preset="clean", width=200, height=150)
    img, truth = S.render(scenes[0], seed=1)
    rig = S.rig_for(scenes[0])
    image = jnp.asarray(img, jnp.float64) / 255.0
    mask = wheel_mask(image, rig.segmentation, rig.confidence_rect)
    good = _measure(image, mask, wheel_radius_mm=rig.wheel_radius_mm)
    assert int(good.check) == 0 and Status.from_code(int(good.status)) == Status.OK
    assert abs(float(good.sinkage_mm) - truth.sinkage_mm) < 0.1 * truth.sinkage_mm + 1.0
    # Erase a 70-degree wedge of the upper wheel from the mask: the ring just inside the fitted
    # rim no longer agrees with "wheel above the soil line" over a fifth of its length.
    yy, xx = np.mgrid[0:150, 0:200]
    ang = np.degrees(np.arctan2(yy - scenes[0].centre_y_px, xx - scenes[0].centre_x_px))
    wedge = (ang > -150) & (ang < -80)
    bad = _measure(image, jnp.where(jnp.asarray(wedge), 0.0, mask), wheel_radius_mm=140.0)
    assert Status.from_code(int(bad.status)) in (Status.IMPLAUSIBLE, Status.NO_WHEEL)
    if Status.from_code(int(bad.status)) == Status.IMPLAUSIBLE:
        assert int(bad.check) >= 1 and message(int(bad.check)).startswith(TESTS[int(bad.check) - 1])


def test_classic_implausibility() -> None:
    r = 100.0
    x = np.linspace(-60, 60, 121)
    flat = np.column_stack([x, np.full_like(x, 80.0)])
    a, b = np.array([60.0, 80.0]), np.array([-60.0, 80.0])  # on the rim: 60^2 + 80^2 = 100^2
    assert implausibility(flat, a, b, r, 1.0) == ""
    assert implausibility(flat, a, b, r, 1.0, recording_radius_px=101.0) == ""
    assert "recording" in implausibility(flat, a, b, r, 1.0, recording_radius_px=120.0)
    high = flat.copy()
    high[:, 1] = -10.0
    assert "above the wheel centre" in implausibility(high, a, b, r, 1.0)
    short = np.array([30.0, 80.0])  # 85 px from O: 15 px short of the rim
    assert "short of the rim" in implausibility(flat, short, b, r, 1.0)
    rows = [
        FrameResult(image="a", status=Status.OK, radius_px=100.0),
        FrameResult(image="b", status=Status.NO_WHEEL),
        FrameResult(image="c", status=Status.OK, radius_px=140.0),
        FrameResult(image="d", status=Status.NO_CONTACT, radius_px=101.0),
    ]
    assert recording_radius_px(rows) == pytest.approx(101.0)
    assert recording_radius_px(rows[1:2]) is None


def test_implausible_status() -> None:
    s = Status.IMPLAUSIBLE
    assert str(s) == "implausible" and not s.measured and Status.from_code(s.code) is s
    assert "calibrate" in s.message and math.isfinite(s.code)
