"""The recording-level rim (issue 12, item 2): one robust circle per recording, frames measured
with it, a hidden rim still measures, a moved rim is said, chunks and resumes agree."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sinkjax import RecordingRim, SoftRecording, Status
from sinkjax.soft.batch import estimate_batch
from sinkjax.soft.estimator import measure
from sinkjax.soft.rim import AGREE_PX, MIN_RIM_STD_PX, combine_rims


def test_combine_rims_is_robust_and_says_when_there_is_no_consensus() -> None:
    rng = np.random.default_rng(0)
    truth = np.array([160.0, 100.0, 80.0])
    circles = truth + 0.2 * rng.standard_normal((8, 3))
    circles[2] = [190.0, 120.0, 95.0]  # a frame that saw lug tips / another circle
    support = np.full(8, 0.6)
    support[5] = 0.01  # a frame that hardly saw a rim does not vote
    circles[5] = [0.0, 0.0, 10.0]
    rim = combine_rims(circles, support, min_support=0.2)
    assert rim is not None
    good = np.delete(circles, [2, 5], axis=0)
    np.testing.assert_allclose(
        [float(rim.cx_px), float(rim.cy_px), float(rim.r_px)], good.mean(0), atol=1e-9
    )
    # The standard error of the mean of six frames, from their spread.
    want = np.max(good.std(0, ddof=1)) / np.sqrt(6)
    assert float(rim.std_px) == pytest.approx(max(want, MIN_RIM_STD_PX), rel=1e-6)
    # Scattered circles (a folder of unrelated pictures): no recording rim.
    scattered = truth + rng.uniform(-40, 40, (6, 3))
    assert combine_rims(scattered, np.full(6, 0.6), min_support=0.2) is None
    assert combine_rims(circles, np.zeros(8), min_support=0.2) is None


def _hide_rim(image: np.ndarray, truth, rig) -> np.ndarray:
    """Paint everything outside the rim and above the soil with the wheel's own colour (the
    colour cast of hard footage): the frame's own rim edge is gone, lugs included."""
    height, width = image.shape[:2]
    yy, xx = np.mgrid[0:height, 0:width]
    outside = np.hypot(xx - truth.center_x_px, yy - truth.center_y_px) > truth.radius_px + 1.0
    above = yy < truth.center_y_px + truth.radius_px - truth.sinkage_px - 3
    x, y, w, h = rig.confidence_rect
    colour = np.median(image[y : y + h, x : x + w].reshape(-1, 3), axis=0)
    out = image.copy()
    out[outside & above] = colour.astype(np.uint8)
    return out


def test_a_frame_with_its_rim_hidden_is_measured_with_the_recordings_rim(rendered) -> None:
    images, truths, rig = rendered("clean", n=6, seed=21)
    hidden = [*images[:5], _hide_rim(images[5], truths[5], rig)]
    names = [f"f{i}" for i in range(6)]
    per_frame = estimate_batch(hidden, rig, names, rim="frame")
    alone = per_frame[5]
    rows = estimate_batch(hidden, rig, names)
    row, t = rows[5], truths[5]
    # Its own rim is gone: per frame it is not measured right (no wheel, or a wrong circle).
    assert alone.status != Status.OK or abs(alone.radius_px - t.radius_px) > 1.0
    assert row.status == Status.OK, row.message
    assert "measured with the recording's rim" in row.message
    assert abs(row.radius_px - t.radius_px) < 0.5
    assert abs(row.sinkage_mm - t.sinkage_mm) < 0.05 * t.sinkage_mm + 0.1
    # The frames that see their rim all carry the same circle (to the prior's width), and
    # measure what they measured alone, to a fraction of a pixel.
    radii = [r.radius_px for r in rows[:5]]
    assert max(radii) - min(radii) < 0.2
    mm_per_px = rig.wheel_radius_mm / t.radius_px
    for r, a in zip(rows[:5], per_frame[:5], strict=True):
        assert r.status == a.status and "recording's rim" not in r.message
        if r.status == Status.OK:
            assert abs(r.sinkage_mm - a.sinkage_mm) < 0.3 * mm_per_px


def test_a_frame_whose_rim_moved_is_measured_with_its_own_and_says_so(rendered) -> None:
    images, truths, rig = rendered("clean", n=5, seed=22)
    shift = 24  # px to the left: the camera was bumped
    moved = np.roll(images[4], -shift, axis=1)
    moved[:, -shift:] = moved[:, -shift - 1 : -shift]
    rows = estimate_batch([*images[:4], moved], rig, [f"f{i}" for i in range(5)], rim="recording")
    row = rows[4]
    assert "is not the recording's: measured with its own rim" in row.message
    assert abs(row.center_x_px - (truths[4].center_x_px - shift)) < 1.0
    assert abs(row.radius_px - truths[4].radius_px) < 1.0
    assert shift > AGREE_PX


def test_rows_do_not_depend_on_how_the_recording_is_cut(rendered) -> None:
    """A chunk or a resumed run finds the rim from the recording's first frames: its rows are
    the whole run's."""
    images, _, rig = rendered("clean", n=6, seed=23)
    names = [f"f{i}" for i in range(6)]
    whole = SoftRecording()
    rows = whole(images[:4], rig, names[:4]) + whole(images[4:], rig, names[4:])
    chunk = SoftRecording(first_frames=lambda h, w: images[:4])
    later = chunk(images[4:], rig, names[4:])
    for a, b in zip(rows[4:], later, strict=True):
        assert a == b
    rim = whole.rims[images[0].shape[:2]]
    assert float(rim.use) == 1.0
    assert chunk.rims[images[0].shape[:2]] == rim


def test_first_frames_are_segmented_again_when_the_mask_uses_the_rim(rendered) -> None:
    """A metal wheel's mask uses the rim (``Segmenter.with_rim``): the recording's first frames,
    segmented before its rim was known, are segmented again with it, so that they give the rows
    that any later frame (measured with the rim from the start) would."""
    from sinkjax.soft.adaptive import AdaptiveSegmenter

    images, _, rig = rendered("hard_metal", n=4, seed=5)
    names = [f"f{i}" for i in range(4)]
    whole = SoftRecording()
    first = whole(images, rig, names)
    rim = whole.rims[images[0].shape[:2]]
    assert float(rim.use) == 1.0
    given = SoftRecording(rim=rim)(images, rig, names)
    for a, b in zip(first, given, strict=True):
        assert a == b
    assert {r.segmenter_features for r in first} == {"intensity+texture"}
    # The rim changes these masks: the test above would see first frames left as they were.
    seg = AdaptiveSegmenter(rig.segmentation)
    rect = jnp.asarray(rig.confidence_rect)
    changed = 0
    for im in images:
        x = jnp.asarray(im, jnp.float64) / 255.0
        changed += int(not np.array_equal(seg(x, rect), seg.with_rim(x, rect, rim.disc())))
    assert changed >= 1


@pytest.mark.heavy
@pytest.mark.slow
def test_gradients_pass_through_a_fixed_recording_rim(rendered) -> None:
    """Calibration differentiates through the fit with the rim held: finite, and equal to a
    central finite difference."""
    images, truths, rig = rendered("clean", n=1, seed=24)
    t = truths[0]
    rim = RecordingRim.fixed(t.center_x_px, t.center_y_px, t.radius_px, 0.1)
    image = jnp.asarray(images[0], jnp.float64) / 255.0
    kw = dict(rect=rig.confidence_rect, travel=rig.travel, wheel_radius_mm=rig.wheel_radius_mm)

    # P_d of saturation moves this frame's soil line (the soil is the less saturated side);
    # P_a of saturation would not (no pixel near its band edge: a gradient of 1e-12).
    def sinkage(p_d_sat: jnp.ndarray, im: jnp.ndarray) -> jnp.ndarray:
        seg = dataclasses.replace(rig.segmentation, p_d_sat=p_d_sat)
        return measure(im, seg, rim=rim, **kw).sinkage_mm

    # One compiled function for the gradient and the differences (value and grad: one compile,
    # where grad of a jitted function and the function itself compile three). The image is an
    # argument: closed over, XLA would constant-fold the work done on it.
    value_grad = jax.jit(jax.value_and_grad(sinkage))
    x0 = jnp.asarray(float(rig.segmentation.p_d_sat), jnp.float64)
    g = float(value_grad(x0, image)[1])
    h = 1e-3
    fd = (float(value_grad(x0 + h, image)[0]) - float(value_grad(x0 - h, image)[0])) / (2 * h)
    assert np.isfinite(g) and abs(fd) > 0.01  # mm per unit of P_d: a gradient to check
    assert g == pytest.approx(fd, rel=0.05, abs=1e-3)


def test_rows_do_not_depend_on_frames_measured_side_by_side(
    rendered, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two frames at a time on two cores (sinkjax.xla.side_by_side) or one after another: the
    same rows, in the same order."""
    images, _, rig = rendered("clean", n=6, seed=23)
    names = [f"f{i}" for i in range(6)]
    rows = {}
    for threads in ("1", "2"):
        monkeypatch.setenv("SINKJAX_FRAME_THREADS", threads)
        rows[threads] = SoftRecording()(images, rig, names)
    assert [r.image for r in rows["2"]] == names
    assert rows["1"] == rows["2"]
    assert sum(r.status is Status.OK for r in rows["2"]) >= 4  # frames that measured
