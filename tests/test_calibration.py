"""Calibration (``sinkjax calibrate``) and the lighting augmentations.

Three tiers: label validation and augmentations (no estimator compile), the loss and optimiser on
a cheap stand-in estimator, and one small synthetic recording through the real soft estimator
(gradient against finite differences, loss decrease, CLI, rig round trip), which compiles the
loss once for the whole module.
"""

from __future__ import annotations

import csv
import dataclasses
import itertools
import math
import shutil
import subprocess
import sys
import types
from pathlib import Path

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sinkjax.calibration as C
from sinkjax.app.cli import main
from sinkjax.calibration import cli as calibration_cli, compiled as CL, loss as L, optimise as O
from sinkjax.calibration.augment import (
    MIRED_LOG_GAINS_PER_100,
    brightness_contrast,
    colour_temperature_gains,
    gaussian_noise,
    smooth_field,
    soft_shadow,
)
from sinkjax.rig import Rig, SegmentationParams, load_rig
from sinkjax.soft.adaptive import default_segmenter
from sinkjax.soft.batch import SoftRecording
from sinkjax.soft.rim import RecordingRim


def same_rig(a: Rig, b: Rig) -> bool:
    return (a.wheel_radius_mm, a.confidence_rect, a.travel, a.segmentation.as_dict()) == (
        b.wheel_radius_mm,
        b.confidence_rect,
        b.travel,
        b.segmentation.as_dict(),
    )


# ----------------------------------------------------------------------------- labels


def write_labels(folder: Path, rows: list[list[str]], header: str | None = None) -> Path:
    path = folder / "LABELS.csv"
    text = (header or ",".join(C.LABEL_COLUMNS)) + "\n"
    text += "".join(",".join(r) + "\n" for r in rows)
    path.write_text(text, encoding="utf-8")
    return path


@pytest.fixture
def small_set(tmp_path: Path) -> Path:
    """Two tiny frames and a rig.toml; LABELS.csv is written by each test."""
    for name in ("a.png", "b.png"):
        assert cv2.imwrite(str(tmp_path / name), np.full((24, 32, 3), 120, np.uint8))
    (tmp_path / "rig.toml").write_text(
        "wheel_radius_mm = 100.0\nconfidence_rect = [2, 2, 4, 4]\n", encoding="utf-8"
    )
    return tmp_path


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """Bad labels must stop before any calibration work."""

    def boom(*args: object, **kwargs: object) -> None:
        raise AssertionError("calibrate() ran although the labels are bad")

    monkeypatch.setattr(calibration_cli, "calibrate", boom)


BAD_LABELS = [
    (
        "missing column",
        [["a.png", "10", "30"]],
        "image,sinkage_mm,theta1_deg",
        ["row 1", "theta2_deg"],
    ),
    (
        "missing image",
        [["a.png", "10", "30", "20"], ["c.png", "1", "2", "3"]],
        None,
        ["row 3, column image", "c.png", "does not exist"],
    ),
    (
        "unparsable",
        [["a.png", "10", "30", "20"], ["b.png", "1", '"2,5"', "3"]],
        None,
        ["row 3, column theta1_deg", "not a number"],
    ),
    (
        "unit in cell",
        [["a.png", "10 mm", "30", "20"]],
        None,
        ["row 2, column sinkage_mm", "not a number"],
    ),
    ("negative", [["a.png", "-1", "30", "20"]], None, ["row 2, column sinkage_mm", "range"]),
    ("angle", [["a.png", "1", "30", "-181"]], None, ["row 2, column theta2_deg", "[-180, 180]"]),
    (
        "all empty",
        [["a.png", "", "", ""], ["b.png", "", "", ""]],
        None,
        ["rows 2-3", "sinkage_mm, theta1_deg, theta2_deg", "empty"],
    ),
    ("empty image cell", [["", "1", "2", "3"]], None, ["row 2, column image", "empty"]),
]


@pytest.mark.parametrize(
    ("case", "rows", "header", "expected"), BAD_LABELS, ids=[b[0] for b in BAD_LABELS]
)
def test_bad_labels_stop_with_row_and_column(
    small_set: Path,
    no_work: None,
    capsys: pytest.CaptureFixture[str],
    case: str,
    rows: list[list[str]],
    header: str | None,
    expected: list[str],
) -> None:
    labels = write_labels(small_set, rows, header)
    code = main(["calibrate", str(labels), "--out", str(small_set / "out.toml")])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith("sinkjax calibrate: error: ")
    for part in expected:
        assert part in err
    assert not (small_set / "out.toml").exists()


def test_first_bad_row_is_reported_before_reading_images(small_set: Path) -> None:
    (small_set / "b.png").write_bytes(b"not an image")  # unreadable, but row 3 fails first
    labels = write_labels(small_set, [["b.png", "1", "2", "3"], ["a.png", "x", "", ""]])
    with pytest.raises(C.LabelError, match="row 3, column sinkage_mm"):
        C.read_labels(labels)


def test_unreadable_and_mismatched_images(small_set: Path) -> None:
    (small_set / "b.png").write_bytes(b"not an image")
    labels = write_labels(small_set, [["a.png", "1", "", ""], ["b.png", "2", "", ""]])
    with pytest.raises(C.LabelError, match="row 3, column image: cannot read"):
        C.read_labels(labels)
    assert cv2.imwrite(str(small_set / "b.png"), np.zeros((30, 40, 3), np.uint8))
    with pytest.raises(C.LabelError, match=r"row 3, column image: 'b.png' is 40x30 px"):
        C.read_labels(labels)


def test_rig_problems_stop_before_work(
    small_set: Path, no_work: None, capsys: pytest.CaptureFixture[str]
) -> None:
    labels = write_labels(small_set, [["a.png", "1", "2", "3"]])
    (small_set / "rig.toml").unlink()
    assert main(["calibrate", str(labels), "--out", str(small_set / "o.toml")]) == 2
    assert "pass --rig RIG.toml" in capsys.readouterr().err
    (small_set / "rig.toml").write_text("wheel_radius_mm = 100.0\n", encoding="utf-8")
    assert main(["calibrate", str(labels), "--out", str(small_set / "o.toml")]) == 2
    assert "confidence_rect" in capsys.readouterr().err
    (small_set / "rig.toml").write_text(
        "wheel_radius_mm = 100.0\nconfidence_rect = [30, 2, 4, 4]\n", encoding="utf-8"
    )
    assert main(["calibrate", str(labels), "--out", str(small_set / "o.toml")]) == 2
    assert "extends beyond the 32x24 image" in capsys.readouterr().err
    (small_set / "rig.toml").write_text(
        "wheel_radius_mm = 100.0\nconfidence_rect = [2, 2, 4, 4]\n", encoding="utf-8"
    )
    assert main(["calibrate", str(labels), "--out", str(small_set / "no" / "o.toml")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_steps_zero_is_passed_on_and_negative_steps_are_refused(
    small_set: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    labels = write_labels(small_set, [["a.png", "1", "2", "3"]])
    seen: list[int] = []

    def stop(frames: object, rig: object, *, steps: int, **kwargs: object) -> None:
        seen.append(steps)
        raise KeyboardInterrupt  # enough: the CLI got this far (it says "interrupted")

    monkeypatch.setattr(calibration_cli, "calibrate", stop)
    out = str(small_set / "o.toml")
    assert main(["calibrate", str(labels), "--out", out, "--steps", "0"]) != 0
    assert seen == [0]
    with pytest.raises(SystemExit):
        main(["calibrate", str(labels), "--out", out, "--steps", "-1"])
    assert "must be 0 (the grid search alone) or more" in capsys.readouterr().err


def test_labels_read_with_extra_columns_and_empty_cells(small_set: Path) -> None:
    path = small_set / "LABELS.csv"
    path.write_text(
        "image,terrain,sinkage_mm,theta1_deg,theta2_deg\na.png,flat,12.5,30,\n\nb.png,rough,,,7\n",
        encoding="utf-8",
    )
    frames = C.read_labels(path)
    assert frames.names == ("a.png", "b.png")
    assert frames.images.shape == (2, 24, 32, 3)
    np.testing.assert_array_equal(
        frames.targets, [[12.5, 30.0, math.nan], [math.nan, math.nan, 7.0]]
    )


def test_negative_angles_are_labels(small_set: Path) -> None:
    """atan2 angles (docs/conventions.md §1) turn negative when a boundary end passes below the
    centre (hollow terrain): such labels are read, not refused."""
    path = write_labels(small_set, [["a.png", "3.5", "-4.25", "-12"], ["b.png", "1", "180", ""]])
    frames = C.read_labels(path)
    np.testing.assert_array_equal(frames.targets, [[3.5, -4.25, -12.0], [1.0, 180.0, math.nan]])


# ----------------------------------------------------------------------------- parameters


def test_raw_parameters_round_trip_and_stay_valid() -> None:
    seg = SegmentationParams(
        p_d_hue=0.83,
        p_a_hue=1.07,
        p_d_sat=0.4,
        p_a_sat=2.5,
        temperature_hue_deg=3.0,
        temperature_sat=0.05,
        veto_fraction=0.6,
    )
    back = C.from_raw(C.to_raw(seg)).as_dict()
    for k, v in seg.as_dict().items():
        assert back[k] == pytest.approx(v, rel=1e-12)
    for value in (-1e3, -30.0, 0.0, 30.0, 1e3):
        d = C.from_raw(jnp.full(len(C.RAW_NAMES), value, jnp.float32)).as_dict()
        assert 0 < d["p_d_hue"] < 1 < d["p_a_hue"] and 0 < d["p_d_sat"] < 1 < d["p_a_sat"]
        assert d["temperature_hue_deg"] > 0 and d["temperature_sat"] > 0
        assert d["veto_fraction"] > 0


def naive_residuals(p: jax.Array, ev) -> jax.Array:
    """The model's residuals with the weights' square roots taken by plain ``jnp.sqrt``."""
    from sinkjax.soft import model as _model

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(_model, "_sqrt_weight", jnp.sqrt)
        return _model.residuals(p, ev)


def test_residuals_have_finite_weight_gradients_at_zero_weight() -> None:
    from sinkjax.soft import model as _model

    rng = np.random.default_rng(0)
    w = jnp.asarray(rng.uniform(0, 1, 6)).at[::2].set(0.0)  # half the points have weight 0
    ev = _model.Evidence(
        x_px=jnp.asarray(rng.uniform(-50, 50, 6)),
        y_px=jnp.asarray(rng.uniform(0, 50, 6)),
        w_rim=w,
        w_line=w[::-1],
        w_a=w,
        w_b=w[::-1],
        sign=jnp.asarray(1.0),
        start=jnp.zeros(_model.N_PARAMS),
    )
    p = jnp.asarray([1.0, 2.0, 40.0, 0.1, 20.0, 0.1, 20.0, -0.1, 20.0, 0.01, -0.02])

    def total(fn, w_line):
        return jnp.sum(fn(p, eqx.tree_at(lambda e: e.w_line, ev, w_line)) ** 3)

    np.testing.assert_array_equal(_model.residuals(p, ev), naive_residuals(p, ev))
    g = jax.grad(lambda wl: total(_model.residuals, wl))(ev.w_line)
    g_naive = jax.grad(lambda wl: total(naive_residuals, wl))(ev.w_line)
    positive = np.asarray(ev.w_line) > 0
    np.testing.assert_allclose(g[positive], g_naive[positive], rtol=1e-12)
    assert not np.all(np.isfinite(np.asarray(g_naive)))  # d sqrt(w) = inf at w = 0
    assert np.all(np.asarray(g)[~positive] == 0.0)


def test_pseudo_huber() -> None:
    x = jnp.array([0.0, 1e-3, 1.0, 100.0])
    np.testing.assert_allclose(
        C.pseudo_huber(x), [0.0, 0.5e-6, math.sqrt(2) - 1, math.sqrt(1 + 1e4) - 1], rtol=1e-6
    )


# ----------------------------------------------------------------------------- loss (stand-in)

FAKE_SHAPE = (2, 8, 8, 3)  # a shape the real estimator never sees here (separate jit cache)
FAKE_RIG = Rig(wheel_radius_mm=100.0, confidence_rect=(0, 0, 2, 2))


def _stand_in(monkeypatch: pytest.MonkeyPatch, measure) -> None:
    """The loss measures with ``measure`` (a stand-in for the estimator) and the default mask
    of the thresholds it is given (as the estimator's own mask would be)."""

    def measure_and_mask(image, seg, *, rect, **kw):
        return measure(image, seg, rect=rect, **kw), default_segmenter(seg)(image, rect)

    monkeypatch.setattr(L, "measure_and_mask", measure_and_mask)


@pytest.fixture
def fake_measure(monkeypatch: pytest.MonkeyPatch):
    """A cheap smooth stand-in for the estimator: sinkage 40 P_d(S), theta1 60 P_d(H)."""
    state = {"status": 0, "boundary": 100.0, "nan": False}

    def measure(image, seg, *, rect, travel, wheel_radius_mm, rim=None, srgb=False):
        nan = jnp.nan if state["nan"] else 0.0
        return types.SimpleNamespace(
            sinkage_mm=40.0 * seg.p_d_sat + jnp.mean(image) + nan,
            theta1_rad=jnp.radians(60.0 * seg.p_d_hue),
            theta2_rad=jnp.radians(20.0 * seg.p_a_sat),
            status=jnp.asarray(state["status"], jnp.int32),
            boundary_weight=jnp.full(5, state["boundary"] / 5) * seg.p_a_hue,
            params=jnp.asarray([4.0, 4.0, 3.0, 0, 0, 0, 0, 0, 0]),
        )

    _stand_in(monkeypatch, measure)
    # No rim to find in the stand-in's blank frames (and no real estimator to compile).
    monkeypatch.setattr(O, "labelled_rim", lambda frames, rig, rim: RecordingRim.per_frame())
    _clear_loss_caches()
    yield state
    _clear_loss_caches()


def _clear_loss_caches() -> None:
    """Drop the compiled losses: the next call traces the stand-in that is installed now."""
    CL._loss_and_grad.clear_cache()
    CL._loss_value.clear_cache()


def fake_frames(theta2: float = math.nan) -> C.LabelledFrames:
    targets = np.array([[28.0, 57.0, theta2], [28.0, math.nan, theta2]])
    return C.LabelledFrames(np.zeros(FAKE_SHAPE, np.uint8), targets, ("a", "b"))


def fake_loss(frames: C.LabelledFrames, seg: SegmentationParams | None = None):
    return C.loss_and_grad(
        C.to_raw(seg or SegmentationParams()),
        jnp.asarray(frames.images),
        jnp.asarray(frames.targets),
        jax.random.key(0),
        rect=(0, 0, 2, 2),
        travel="right",
        wheel_radius_mm=100.0,
    )


def test_loss_masks_empty_cells_and_averages_over_measured(fake_measure) -> None:
    out = fake_loss(fake_frames())
    # sinkage 20 vs 28 (twice), theta1 54 vs 57 (once); theta2 not measured: 3 cells.
    expected = (2 * C.pseudo_huber(8.0) + C.pseudo_huber(3.0)) / 3
    assert float(out.loss) == pytest.approx(float(expected), rel=1e-12)
    assert float(out.grad[3]) == 0.0  # P_a(S) only moves theta2, which nobody measured
    with_theta2 = fake_loss(fake_frames(theta2=36.0))  # = 20 * 1.8: zero error, one more cell
    assert float(with_theta2.loss) == pytest.approx(float(expected) * 3 / 5, rel=1e-12)


def test_loss_value_is_the_loss_without_its_gradient(fake_measure) -> None:
    frames = fake_frames(theta2=30.0)
    seg = SegmentationParams(p_d_sat=0.6, p_a_sat=1.6)
    full = fake_loss(frames, seg)
    alone = C.loss_value(
        C.to_raw(seg),
        jnp.asarray(frames.images),
        jnp.asarray(frames.targets),
        rect=(0, 0, 2, 2),
        travel="right",
        wheel_radius_mm=100.0,
    )
    # sinkage 24 vs 28 (twice), theta1 54 vs 57, theta2 32 vs 30 (twice): 5 cells.
    expected = (2 * C.pseudo_huber(4.0) + C.pseudo_huber(3.0) + 2 * C.pseudo_huber(2.0)) / 5
    assert float(alone.loss) == pytest.approx(float(expected), rel=1e-12)
    assert float(alone.loss) == pytest.approx(float(full.loss), rel=1e-12)
    np.testing.assert_array_equal(np.asarray(alone.frames.values), np.asarray(full.frames.values))
    assert not np.any(np.asarray(alone.grad)) and np.any(np.asarray(full.grad))
    # Compiled for one frame: any number of frames, one compile.
    images, targets = jnp.asarray(frames.images), jnp.asarray(frames.targets)
    for n in (1, 3):
        more = C.loss_value(
            C.to_raw(seg), jnp.concatenate([images] * 2)[:n],
            jnp.concatenate([targets] * 2)[:n], rect=(0, 0, 2, 2), travel="right",
            wheel_radius_mm=100.0,
        )  # fmt: skip
        assert more.frames.values.shape == (n, 3)
    assert CL._loss_value._cache_size() == 1


def test_one_compiled_loss_serves_every_rig(fake_measure, monkeypatch: pytest.MonkeyPatch) -> None:
    """The rig's rectangle, travel and radius reach the compiled loss as traced arrays: a
    second rig of the same image size compiles nothing, and each rig's numbers are its own."""

    def measure(image, seg, *, rect, travel, wheel_radius_mm, rim=None, srgb=False):
        # Sinkage from every rig number: radius / 5 + rect x + 10 (travel sign) + 7 (sRGB).
        x = jnp.asarray(rect[0]).astype(jnp.result_type(float))
        sinkage = wheel_radius_mm / 5.0 + x + 10.0 * travel + 7.0 * srgb + 0.0 * seg.p_d_sat
        return types.SimpleNamespace(
            sinkage_mm=sinkage,
            theta1_rad=jnp.radians(60.0 * seg.p_d_hue),
            theta2_rad=jnp.radians(20.0 * seg.p_a_sat),
            status=jnp.asarray(0, jnp.int32),
            boundary_weight=jnp.full(5, 20.0),
            params=jnp.asarray([4.0, 4.0, 3.0, 0, 0, 0, 0, 0, 0]),
        )

    _stand_in(monkeypatch, measure)
    _clear_loss_caches()
    frames = C.LabelledFrames(
        np.zeros(FAKE_SHAPE, np.uint8), np.array([[28.0, np.nan, np.nan]] * 2), ("a", "b")
    )
    raw = C.to_raw(SegmentationParams())
    args = (jnp.asarray(frames.images), jnp.asarray(frames.targets))
    rigs = [
        ((0, 0, 2, 2), "right", 100.0, "linear"),
        ((3, 1, 2, 2), "left", 150.0, "linear"),
        ((3, 1, 2, 2), "left", 150.0, "srgb"),
    ]
    for (rect, travel, radius, coding), sinkage in zip(rigs, (30.0, 23.0, 30.0), strict=True):
        out = C.loss_value(
            raw, *args, rect=rect, travel=travel, wheel_radius_mm=radius, encoding=coding
        )
        np.testing.assert_allclose(np.asarray(out.frames.values)[:, 0], sinkage, rtol=1e-12)
        assert float(out.loss) == pytest.approx(float(C.pseudo_huber(sinkage - 28.0)), rel=1e-12)
    assert CL._loss_value._cache_size() == 1
    with pytest.raises(ValueError, match="confidence"):
        C.loss_value(raw, *args, rect=(6, 6, 4, 4), travel="right", wheel_radius_mm=100.0)
    _clear_loss_caches()


def test_gradient_compiled_in_background_is_not_compiled_again(fake_measure) -> None:
    # A compile, or its executable read from the session's persistent cache (conftest).
    compiles: list[str] = []
    kinds = ("backend_compile_duration", "cache_retrieval_time_sec")
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, secs, **kw: compiles.append(name) if name.endswith(kinds) else None
    )
    frames = fake_frames(theta2=30.0)
    seg = SegmentationParams(p_d_sat=0.6, p_a_sat=1.6)
    args = (C.to_raw(seg), jnp.asarray(frames.images), jnp.asarray(frames.targets))
    rig = dict(rect=(0, 0, 2, 2), travel="right", wheel_radius_mm=100.0)
    # As calibrate() starts it before the rim is found: per_frame() has any rim's shapes.
    found = RecordingRim.fixed(1.0, 1.0, 2.0, 0.1)
    key = jax.random.key(0)
    CL.compile_in_background(*args, key, RecordingRim.per_frame(), value=True, **rig).join()
    assert len(compiles) >= 2, "the threads did not compile the loss and its gradient"
    before = len(compiles)
    out = C.loss_and_grad(*args, key, found, **rig)
    alone = C.loss_value(*args, found, **rig)
    assert len(compiles) == before  # found compiled
    assert float(alone.loss) == pytest.approx(float(out.loss), rel=1e-12)
    expected = (2 * C.pseudo_huber(4.0) + C.pseudo_huber(3.0) + 2 * C.pseudo_huber(2.0)) / 5
    assert float(out.loss) == pytest.approx(float(expected), rel=1e-12)


def test_failed_frames_count_as_zeros_and_keep_gradients_finite(
    fake_measure, monkeypatch: pytest.MonkeyPatch
) -> None:
    fake_measure.update(status=3, nan=True)
    monkeypatch.setattr(L, "boundary_contrast", lambda *a, **k: 0.0)  # tested on its own
    out = fake_loss(fake_frames())
    expected = (2 * C.pseudo_huber(28.0) + C.pseudo_huber(57.0)) / 3
    assert float(out.loss) == pytest.approx(float(expected), rel=1e-12)
    assert np.all(np.isfinite(np.asarray(out.grad)))


def test_weak_boundary_is_penalised_with_a_gradient(fake_measure) -> None:
    fake_measure.update(boundary=2.0)
    weak = fake_loss(fake_frames())
    fake_measure.update(boundary=100.0)
    _clear_loss_caches()
    strong = fake_loss(fake_frames())
    assert float(weak.loss) > float(strong.loss)
    assert float(weak.grad[1]) < 0.0  # more P_a(H) -> more boundary weight -> lower loss
    assert float(strong.grad[1]) == 0.0


def test_calibrate_converges_on_stand_in_and_is_deterministic(fake_measure) -> None:
    frames = fake_frames()
    a = C.calibrate(frames, FAKE_RIG, steps=80, learning_rate=0.1, patience=80, grid=None)
    b = C.calibrate(frames, FAKE_RIG, steps=80, learning_rate=0.1, patience=80, grid=None)
    assert same_rig(a.rig, b.rig) and a.losses == b.losses
    assert a.loss_after < 0.01 * a.loss_before
    seg = a.rig.segmentation.as_dict()
    assert seg["p_d_sat"] == pytest.approx(0.7, abs=2e-3)
    assert seg["p_d_hue"] == pytest.approx(0.95, abs=2e-3)
    assert seg["p_a_sat"] == pytest.approx(1.8, rel=1e-9)  # no gradient: untouched
    assert a.after.sinkage_mm < 0.1 < a.before.sinkage_mm
    assert "loss" in a.summary() and "after" in a.summary()


def test_failing_frames_get_a_surrogate_gradient(fake_measure, monkeypatch) -> None:
    real = L.measure_and_mask  # the fixture's stand-in

    def picky(image, seg, **kw):  # measures nothing unless P_d(S) > 0.6: flat loss at 0.5
        est, _ = real(image, seg, **kw)
        return types.SimpleNamespace(**{**vars(est), "status": jnp.where(seg.p_d_sat > 0.6, 0, 1)})

    calls = []

    def contrast(mask, circle, target, **kw):  # the stand-in's mask ignores the thresholds
        calls.append(circle)
        return 1.0 - C.from_raw(raw_now[0]).p_d_sat

    raw_now = [C.to_raw(SegmentationParams())]
    _stand_in(monkeypatch, picky)
    monkeypatch.setattr(L, "boundary_contrast", contrast)
    _clear_loss_caches()
    out = fake_loss(fake_frames())
    assert calls and np.all(np.isfinite(np.asarray(out.grad)))
    assert float(out.loss) > float((2 * C.pseudo_huber(28.0) + C.pseudo_huber(57.0)) / 3)


def test_boundary_contrast_is_zero_for_an_edge_at_the_labelled_line() -> None:
    r, z0_px, radius_mm = 40.0, 10.0, 140.0
    cx, cy = 50.0, 45.0
    yy, xx = np.mgrid[0:100, 0:100].astype(float)
    z0_mm = z0_px * radius_mm / r
    theta = math.degrees(math.acos(1 - z0_px / r))  # flat ground: theta1 = theta2
    u, v = jnp.asarray(xx - cx), jnp.asarray(yy - cy)
    flat = C.labelled_soil_side(u, v, r, jnp.array([z0_mm, np.nan, np.nan]), radius_mm)
    chord = C.labelled_soil_side(u, v, r, jnp.array([z0_mm, theta, theta]), radius_mm)
    np.testing.assert_allclose(chord, flat, atol=1e-9)
    np.testing.assert_allclose(flat, yy - cy - (r - z0_px))
    wheel_above = jnp.asarray((yy - cy < r - z0_px).astype(float))
    circle = jnp.array([cx, cy, r])
    target = jnp.array([z0_mm, theta, theta])

    def contrast(mask: jax.Array) -> float:
        return float(C.boundary_contrast(mask, circle, target, sign=1.0, wheel_radius_mm=radius_mm))

    assert contrast(wheel_above) == 0.0
    assert contrast(1.0 - wheel_above) == 2.0
    assert contrast(jnp.ones((100, 100))) == 1.0
    shifted = jnp.asarray((yy - cy < r - z0_px + 0.2 * r).astype(float))  # soil called wheel
    assert contrast(shifted) == pytest.approx(1.0)


def test_calibrate_backs_off_when_a_step_lands_where_frames_fail(
    fake_measure, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = L.measure_and_mask  # the fixture's stand-in

    def cliff(image, seg, **kw):  # the optimum P_d(S) = 0.7 lies just before a failure region
        est, _ = real(image, seg, **kw)
        return types.SimpleNamespace(**{**vars(est), "status": jnp.where(seg.p_d_sat < 0.72, 0, 3)})

    _stand_in(monkeypatch, cliff)
    monkeypatch.setattr(L, "boundary_contrast", lambda *a, **k: 0.0)
    _clear_loss_caches()
    res = C.calibrate(fake_frames(), FAKE_RIG, steps=80, learning_rate=0.5, patience=80, grid=None)
    jumps = [i for i, x in enumerate(res.losses) if x > C.BACKTRACK * min(res.losses[: i + 1])]
    assert jumps, res.losses  # it did step over the cliff ...
    assert res.after.n_ok == 2  # ... and came back (without backing off it stays at 1.6)
    assert res.loss_after < 1e-3 * res.loss_before
    assert res.rig.segmentation.as_dict()["p_d_sat"] == pytest.approx(0.7, abs=5e-3)


def test_calibrate_keeps_the_best_step_and_stops_early(fake_measure) -> None:
    res = C.calibrate(fake_frames(), FAKE_RIG, steps=200, learning_rate=3.0, patience=5, grid=None)
    assert len(res.losses) < 201
    assert res.losses[res.best_step] == min(res.losses)
    assert len(res.losses) - 1 - res.best_step <= 5


def test_grid_start_escapes_a_plateau_and_is_never_worse_than_the_grid(
    fake_measure, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = L.measure_and_mask  # the fixture's stand-in

    def plateau(image, seg, **kw):  # nothing measures unless P_d(S) > 0.6: flat loss below
        est, _ = real(image, seg, **kw)
        return types.SimpleNamespace(**{**vars(est), "status": jnp.where(seg.p_d_sat > 0.6, 0, 3)})

    _stand_in(monkeypatch, plateau)
    monkeypatch.setattr(L, "boundary_contrast", lambda *a, **k: 0.0)
    _clear_loss_caches()
    stuck = C.calibrate(fake_frames(), FAKE_RIG, steps=30, grid=None, polish_measurements=0)
    assert stuck.loss_after == stuck.loss_before  # gradient descent alone cannot move
    # The polish's compass steps (0.5 raw: P_d(S) 0.5 -> 0.62) leave the plateau without a grid.
    polished = C.calibrate(fake_frames(), FAKE_RIG, steps=30, grid=None)
    assert polished.polished is not None and polished.polished[0] == stuck.loss_after
    assert polished.loss_after < 0.1 * stuck.loss_after
    assert polished.rig.segmentation.as_dict()["p_d_sat"] > 0.6
    res = C.calibrate(fake_frames(), FAKE_RIG, steps=30)
    assert res.loss_after <= res.grid_best_loss < stuck.loss_after
    assert res.after.n_ok == 2 and res.loss_after < 1e-2 * res.loss_before
    # 0.7 is the only grid value of P_d(S) that measures, and 28 / 40 = 0.7 the optimum.
    assert res.rig.segmentation.as_dict()["p_d_sat"] == pytest.approx(0.7, abs=5e-3)
    assert "best grid point" in res.summary() and "leave-one-out" in res.summary()


def test_loss_value_stops_once_the_loss_is_above_its_bound(fake_measure) -> None:
    # Frame losses (sinkage 20 vs the labels): 8 mm off, 18 mm off, 0 off, over 3 cells.
    images = jnp.zeros((3, *FAKE_SHAPE[1:]), jnp.uint8)
    targets = jnp.asarray([[28.0, np.nan, np.nan], [38.0, np.nan, np.nan], [20.0, np.nan, np.nan]])
    rig = dict(rect=(0, 0, 2, 2), travel="right", wheel_radius_mm=100.0)
    raw = C.to_raw(SegmentationParams())
    full = C.loss_value(raw, images, targets, **rig)
    huber = [float(C.pseudo_huber(e)) for e in (8.0, 18.0, 0.0)]
    assert float(full.loss) == pytest.approx(sum(huber) / 3, rel=1e-12) and CL.complete(full)
    # Frame 1 alone is above a bound of 5: frames 0 and 2 are not measured.
    cut = C.loss_value(raw, images, targets, **rig, bound=5.0, order=[1, 0, 2])
    assert float(cut.loss) == pytest.approx(huber[1] / 3, rel=1e-12) and huber[1] / 3 > 5.0
    assert not CL.complete(cut) and list(np.asarray(cut.frames.status)) == [-1, 0, -1]
    assert np.isnan(np.asarray(cut.frames.loss)[[0, 2]]).all()
    # A bound the whole loss stays under: every frame, the same numbers.
    kept = C.loss_value(raw, images, targets, **rig, bound=float(full.loss), order=[1, 0, 2])
    assert CL.complete(kept) and float(kept.loss) == pytest.approx(float(full.loss), rel=1e-12)
    np.testing.assert_array_equal(np.asarray(kept.frames.values), np.asarray(full.frames.values))


class _Counted:
    """The compiled one-frame loss, appending 1 to ``measured`` for each frame it measures."""

    def __init__(self, real, measured: list[int]):
        self.real, self.measured = real, measured

    def __call__(self, *args, **kwargs):
        self.measured.append(1)
        return self.real(*args, **kwargs)

    def __getattr__(self, name):  # lower(), for the background compile
        return getattr(self.real, name)


def test_pruning_changes_nothing_but_the_frames_measured(
    fake_measure, monkeypatch: pytest.MonkeyPatch
) -> None:
    measured: list[int] = []  # one entry per frame measured by the compiled loss
    monkeypatch.setattr(CL, "_loss_value", _Counted(CL._loss_value, measured))
    results, counts = [], []
    for prune in (False, True):
        measured.clear()
        results.append(C.calibrate(fake_frames(theta2=30.0), FAKE_RIG, steps=6, prune=prune))
        counts.append(sum(measured))
    whole, pruned = results
    assert pruned.rig == whole.rig and pruned.loss_after == whole.loss_after
    assert pruned.grid_best_loss == whole.grid_best_loss and pruned.losses == whole.losses
    assert counts[1] < 0.8 * counts[0], counts  # grid points that cannot be lowest stop early


@pytest.mark.parametrize("bars", [True, False])
def test_the_grid_shows_its_progress_in_frames_measured(
    bars: bool, fake_measure, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    measured: list[int] = []
    monkeypatch.setattr(CL, "_loss_value", _Counted(CL._loss_value, measured))
    in_grid: list[int] = []  # frames measured inside the grid's scoring, counted apart
    score = O.score_pruned

    def counted(*args, **kwargs):
        before = len(measured)
        out = score(*args, **kwargs)
        in_grid.append(len(measured) - before)
        return out

    monkeypatch.setattr(O, "score_pruned", counted)
    stages: list[tuple[str, int, int]] = []
    C.calibrate(
        fake_frames(theta2=30.0),
        FAKE_RIG,
        steps=2,
        polish_measurements=3,
        progress=bars,
        on_stage=lambda *a: stages.append(a),
    )
    err = capsys.readouterr().err.replace("\r", "\n")
    shown = [line for line in err.splitlines() if line.startswith("grid:")]
    assert bool(shown) == bars
    n = sum(in_grid)
    if bars:
        done = shown[-1].split("|")[2].split()[0]
        assert done == f"{n}/{n}", (done, in_grid)
    # The grid and its relaxed veto points (pruned: fewer than every point on both frames).
    assert len(in_grid) == 2 and n > 0
    assert n < 2 * (len(list(itertools.product(*C.GRID.values()))) + O.N_RELAXED)
    grid = [s for s in stages if s[0] == "grid"]
    assert [s[1] for s in grid] == sorted(s[1] for s in grid) and grid[-1] == ("grid", n, n)
    assert all(s[1] <= s[2] for s in grid)
    polish = [s[1:] for s in stages if s[0] == "polish"]
    assert polish == [(k, 3) for k in range(1, len(polish) + 1)] and 1 <= len(polish) <= 3
    assert [s[0] for s in stages] == ["grid"] * len(grid) + ["polish"] * len(polish)


def test_zero_steps_is_the_grid_search_alone_without_a_gradient(
    fake_measure, monkeypatch: pytest.MonkeyPatch
) -> None:
    def no_gradient(*args: object, **kwargs: object) -> None:
        raise AssertionError("a gradient was asked for with steps=0")

    compile_loss = O.compile_in_background

    def loss_alone(*args: object, gradient: bool = True, **kwargs: object) -> CL.Compiling:
        if gradient:
            no_gradient()
        return compile_loss(*args, gradient=gradient, **kwargs)

    monkeypatch.setattr(O, "compile_in_background", loss_alone)
    monkeypatch.setattr(O, "loss_and_grad", no_gradient)
    res = C.calibrate(fake_frames(), FAKE_RIG, steps=0)
    assert res.losses == (res.loss_after,) and res.best_step == 0
    assert res.checks is not None and res.checks.converged
    assert "grid search alone" in res.summary() and "converged: the loss" not in res.summary()
    # The lowest point of the grid (the rig's own point is not on it), scored as with steps.
    assert res.loss_after == pytest.approx(res.grid_best_loss, rel=1e-12)
    assert res.loss_after < res.loss_before
    grid = {k: v for k, v in C.GRID.items()}
    best = min(
        itertools.product(*grid.values()),
        key=lambda c: float(
            fake_loss(fake_frames(), SegmentationParams(**dict(zip(grid, c, strict=True)))).loss
        ),
    )
    got = res.rig.segmentation.as_dict()
    for name, value in zip(grid, best, strict=True):
        assert got[name] == pytest.approx(value, rel=1e-9), name


def test_calibration_checks_convergence_disagreement_and_leave_one_out(fake_measure) -> None:
    short = C.calibrate(fake_frames(), FAKE_RIG, steps=3, learning_rate=0.01, grid=None)
    assert short.checks is not None and not short.checks.converged
    assert "NOT converged" in short.summary()
    # Three frames agree on 28 mm (P_d(S) = 0.7); "d" says 5 mm with the same picture.
    targets = np.array([[28.0, np.nan, np.nan]] * 3 + [[5.0, np.nan, np.nan]])
    frames = C.LabelledFrames(np.zeros((4, *FAKE_SHAPE[1:]), np.uint8), targets, tuple("abcd"))
    res = C.calibrate(frames, FAKE_RIG, steps=80, learning_rate=0.1, grid=None)
    assert res.checks is not None and res.checks.converged
    assert [d[0] for d in res.checks.disagreeing] == ["d"]
    # Leave-one-out: without "d" the others choose ~28 mm, so "d" is 23 mm (460 %) off; each of
    # the others is chosen for by two 28s and one 5: the mean of the losses, near 28 mm still.
    loo = {r[0]: r for r in res.checks.loo}
    assert loo["d"][1] == pytest.approx(23.0, abs=0.5) and loo["d"][5]
    assert all(loo[n][1] < 2.5 for n in "abc")


def test_run_checks_by_hand() -> None:
    frames = C.LabelledFrames(
        np.zeros((2, 1, 1, 3), np.uint8), np.array([[10.0, 20.0, np.nan], [10.0, 20.0, 30.0]]),
        ("x", "y"),
    )  # fmt: skip
    # Two evaluated points: the first fits x, the second fits y.
    losses = [np.array([0.0, 8.0]), np.array([6.0, 0.0])]
    values = [
        np.array([[10, 20, 0], [12, 20, 30]], float),
        np.array([[13, 20, 0], [10, 20, 30]], float),
    ]
    status = [np.zeros(2, int), np.array([0, 3])]
    tail = [9.0] + [8.0] * 6  # the best loss has not moved over the last 5 steps
    chk = C.run_checks(losses, values, status, 0, frames, tail, stopped_early=False)
    # Leaving x out, y's loss picks point 2 (where x reads 13: 3 mm); leaving y out, point 1,
    # where y reads 12 mm (2 mm, 20 %). Point 2 has y failed, but y was left out there.
    assert chk.loo[0][:3] == ("x", 3.0, 0.3) and chk.loo[1][:3] == ("y", 2.0, 0.2)
    assert chk.converged
    # At point 1, y's loss per value (8 / 3) is above 2 while x's is 0: y disagrees.
    assert [d[0] for d in chk.disagreeing] == ["y"]
    # Leave-one-out median 25 % (30 % and 20 %): above 10 %, the summary warns.
    assert chk.loo_median_rel == pytest.approx(0.25)
    assert any(line.startswith("WARNING") and "25 %" in line for line in chk.lines())
    good = [np.array([[10, 20, 0], [10.5, 20, 30]], float)] * 2
    fine = C.run_checks(losses, good, status, 0, frames, tail, stopped_early=False)
    assert fine.loo_median_rel == pytest.approx(0.025)  # 0 and 5 %: no warning
    assert not any(line.startswith("WARNING") for line in fine.lines())


# ----------------------------------------------------------------------------- augmentations


def test_augment_is_seeded_and_in_range() -> None:
    img = jnp.asarray(np.random.default_rng(0).uniform(0, 1, (40, 56, 3)), jnp.float32)
    a = C.augment(img, jax.random.key(3))
    b = C.augment(img, jax.random.key(3))
    c = C.augment(img, jax.random.key(4))
    assert a.shape == img.shape and a.dtype == img.dtype
    np.testing.assert_array_equal(a, b)
    assert float(jnp.abs(a - c).mean()) > 1e-3
    assert float(a.min()) >= 0.0 and float(a.max()) <= 1.0
    with pytest.raises(ValueError, match=r"shape \(H, W, 3\), got \(40, 56\)"):
        C.augment(img[..., 0], jax.random.key(0))


def test_augment_parts() -> None:
    warm = colour_temperature_gains(jnp.asarray(100.0))
    np.testing.assert_allclose(warm, np.exp(MIRED_LOG_GAINS_PER_100), rtol=1e-6)
    assert warm[0] > 1.0 == warm[1] > warm[2]  # warmer: redder, less blue
    np.testing.assert_allclose(colour_temperature_gains(jnp.asarray(0.0)), 1.0)
    img = jnp.linspace(0.1, 0.9, 24 * 3).reshape(4, 6, 3)
    np.testing.assert_allclose(brightness_contrast(img, 1.0, 1.0), img, atol=1e-7)
    np.testing.assert_allclose(brightness_contrast(img, 0.5, 1.0), 0.5 * img, atol=1e-7)
    field = smooth_field(jax.random.key(1), 60, 80)
    assert float(field.min()) == 0.0 and float(field.max()) == pytest.approx(1.0)
    # Smooth: neighbouring pixels differ by a few percent of the range at most.
    assert float(jnp.abs(jnp.diff(field, axis=1)).max()) < 0.1
    shaded = soft_shadow(jnp.ones((60, 80, 3)), field, jnp.asarray(0.5))
    assert float(shaded.min()) == pytest.approx(0.5) and float(shaded.max()) == 1.0
    noisy = gaussian_noise(jnp.full((60, 80, 3), 0.5), jax.random.key(2), jnp.asarray(0.02))
    assert float(jnp.std(noisy)) == pytest.approx(0.02, rel=0.05)


# ----------------------------------------------------------------------------- real estimator


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """3 synthetic 'dust' frames (160x120) where the default thresholds are far off."""
    from sinkjax.synth import write_recording

    out = write_recording(
        tmp_path_factory.mktemp("dust"),
        n_frames=3,
        seed=1,
        preset="dust",
        width=160,
        height=120,
        progress=False,
    )
    with (out / "truth.csv").open(encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    rows[1]["theta2_deg"] = ""  # one cell not measured
    with (out / "LABELS.csv").open("w", encoding="utf-8", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(C.LABEL_COLUMNS)
        writer.writerows([[r[c] for c in C.LABEL_COLUMNS] for r in rows])
    return out


STEPS = 4


@pytest.fixture(scope="module")
def cli_run(recording: Path) -> tuple[Path, str]:
    out = recording / "calibrated.toml"
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(
            ["calibrate", str(recording / "LABELS.csv"), "--out", str(out), "--steps", str(STEPS)]
        )
    assert code == 0
    return out, buf.getvalue()


@pytest.mark.heavy
@pytest.mark.slow
def test_cli_writes_a_complete_calibrated_rig(recording: Path, cli_run: tuple[Path, str]) -> None:
    out, printed = cli_run
    rig, start = load_rig(out), load_rig(recording / "rig.toml")
    assert (rig.wheel_radius_mm, rig.confidence_rect, rig.travel) == (
        start.wheel_radius_mm,
        start.confidence_rect,
        start.travel,
    )
    assert rig.segmentation.as_dict() != start.segmentation.as_dict()
    assert "median |error| before" in printed and "median |error| after" in printed
    # The fixture's folder holds the three labelled frames: the rim is found from them.
    assert "rim circle found from the first 3 frames of the recording in" in printed
    assert "polish (each point measured with the rim it finds): loss" in printed
    assert "calibrated by `sinkjax calibrate LABELS.csv`" in out.read_text(encoding="utf-8")


@pytest.mark.heavy
def test_calibration_lowers_the_loss_deterministically(
    recording: Path, cli_run: tuple[Path, str]
) -> None:
    rig = load_rig(recording / "rig.toml")
    frames = C.read_labels(recording / "LABELS.csv", rig)
    res = C.calibrate(frames, rig, steps=STEPS)
    assert res.loss_after < 0.8 * res.loss_before
    # Same labels, same steps: the CLI wrote exactly this rig.
    assert same_rig(load_rig(cli_run[0]), res.rig)


def test_loss_measures_the_labelled_frames_as_estimate_does(recording: Path) -> None:
    """Calibration minimises the error of the numbers the rig will report: each labelled
    frame's values in the loss are those `sinkjax estimate` gives it (one SoftRecording over
    the frames, which finds their rim itself), not those of the frame's own rim."""
    rig = load_rig(recording / "rig.toml")
    frames = C.read_labels(recording / "LABELS.csv", rig)
    rim = O.labelled_rim(frames, rig, "recording")
    assert float(rim.use) == 1.0  # the three frames show one rim
    static = dict(
        rect=rig.confidence_rect, travel=rig.travel, wheel_radius_mm=float(rig.wheel_radius_mm)
    )
    args = (jnp.asarray(frames.images), jnp.asarray(frames.targets), jax.random.key(0))
    raw = C.to_raw(rig.segmentation)
    held = C.loss_and_grad(raw, *args, rim, **static).frames
    # Each frame's own rim (the same compiled function as a recording's: one compile).
    own = C.loss_and_grad(raw, *args, RecordingRim.per_frame(), **static).frames
    rows = SoftRecording()([np.asarray(im) for im in frames.images], rig, list(frames.names))
    for row, values, status in zip(rows, np.asarray(held.values), held.status, strict=True):
        assert row.status.code == int(status)
        reported = [row.sinkage_mm, row.theta1_deg, row.theta2_deg]
        np.testing.assert_allclose(np.array(reported, float), values, rtol=1e-6, atol=1e-6)
    # Each frame's own rim gives other numbers: the test above can tell the two apart.
    assert np.max(np.abs(np.asarray(own.values) - np.asarray(held.values))) > 1e-3


def test_labels_in_a_recording_folder_are_measured_with_the_recordings_rim(
    tmp_path: Path,
) -> None:
    """`sinkjax calibrate` measures the labelled frames with the rim `sinkjax estimate` of the
    labels' folder finds: from the recording's first frames of that size, not the labelled
    ones."""
    from sinkjax.app.sources import expand_paths
    from sinkjax.calibration.labels import recording_rim_images
    from sinkjax.synth import write_recording

    rec = write_recording(
        tmp_path / "rec", n_frames=11, seed=5, preset="full", width=160, height=120,
        progress=False,
    )  # fmt: skip
    files = sorted(rec.glob("frame_*"))
    # An image of another size, sorted among the first: estimate finds its rim elsewhere.
    cv2.imwrite(str(rec / "frame_0000b.png"), np.full((150, 200, 3), 90, np.uint8))
    labelled = [files[i].name for i in (4, 7, 10)]
    with (rec / "LABELS.csv").open("w", encoding="utf-8", newline="") as fh:
        csv.writer(fh).writerows([C.LABEL_COLUMNS, *[[n, "10", "", ""] for n in labelled]])
    rig = load_rig(rec / "rig.toml")
    bare = C.read_labels(rec / "LABELS.csv")  # no rig: no rim frames
    assert bare.rim_images is None and bare.rim_source is bare.images
    frames = dataclasses.replace(C.read_labels(rec / "LABELS.csv", rig), rim_images=None)
    got = recording_rim_images(rec / "LABELS.csv", frames, rig)
    assert got is not None and got.shape == (8, 120, 160, 3)
    # read_labels with the rig finds them itself (as `sinkjax calibrate` and the review do).
    auto = C.read_labels(rec / "LABELS.csv", rig).rim_images
    assert auto is not None and np.array_equal(auto, got)
    # The first 8 frames of 160x120 by name, read by OpenCV (BGR on disk).
    want = np.stack([cv2.imread(str(f))[..., ::-1] for f in files[:8]])
    np.testing.assert_array_equal(got, want)
    # The rim calibration holds is the one `sinkjax estimate` of the folder uses.
    with_rim = dataclasses.replace(frames, rim_images=got)
    held = O.labelled_rim(with_rim, rig, "recording")
    estimate = SoftRecording()
    sources = expand_paths([rec]).recordings[0].sources
    images = [cv2.imread(str(s.path))[..., ::-1] for s in sources]
    images = [im for im in images if im.shape[:2] == (120, 160)]
    estimate(images, rig, [f"{i}" for i in range(len(images))])
    want_rim = estimate.rim_for(120, 160)
    assert want_rim is not None
    for a, b in zip(jax.tree.leaves(held), jax.tree.leaves(want_rim), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-9)
    # Found from the labelled frames alone it is another circle: the test can tell them apart.
    alone = O.labelled_rim(frames, rig, "recording")
    assert (
        abs(float(alone.r_px) - float(held.r_px)) + abs(float(alone.cx_px) - float(held.cx_px)) > 0
    )
    # Labels whose images lie outside their folder's recordings: the labelled frames' own rim.
    other = tmp_path / "other"
    other.mkdir()
    (other / "LABELS.csv").write_text(
        f"image,sinkage_mm,theta1_deg,theta2_deg\n../rec/{labelled[0]},10,,\n", encoding="utf-8"
    )
    frames2 = C.read_labels(other / "LABELS.csv", rig)
    assert recording_rim_images(other / "LABELS.csv", frames2, rig) is None


@pytest.mark.heavy
def test_gradient_matches_finite_differences(recording: Path, cli_run: tuple[Path, str]) -> None:
    rig = load_rig(recording / "rig.toml")
    frames = C.read_labels(recording / "LABELS.csv", rig)
    images, targets = jnp.asarray(frames.images), jnp.asarray(frames.targets)
    static = dict(
        rect=rig.confidence_rect, travel=rig.travel, wheel_radius_mm=float(rig.wheel_radius_mm)
    )

    def loss(r: jax.Array):
        # Each frame's own rim, as a RecordingRim: the function calibrate() compiled.
        return C.loss_and_grad(
            r, images, targets, jax.random.key(0), RecordingRim.per_frame(), **static
        )

    raw = C.to_raw(rig.segmentation)
    assert raw.dtype == jnp.float64
    g = np.asarray(loss(raw).grad)
    assert np.all(np.isfinite(g)) and np.abs(g).max() > 0

    def central(i: int, h: float) -> float:
        e = jnp.zeros(len(C.RAW_NAMES)).at[i].set(h)
        return (float(loss(raw + e).loss) - float(loss(raw - e).loss)) / (2 * h)

    checked = 0
    for i in range(len(C.RAW_NAMES)):
        fd1, fd2 = central(i, 1e-4), central(i, 2e-5)
        # The loss is piecewise smooth (an outline point appears, the Hough circle moves a bin);
        # where the two step sizes disagree a jump lies within the step: no derivative to test.
        if abs(fd1 - fd2) > 0.01 * abs(fd1) + 1e-7:
            continue
        checked += 1
        assert g[i] == pytest.approx(fd1, rel=0.03, abs=1e-6), (i, g, fd1)
    assert checked >= 4


@pytest.mark.heavy
@pytest.mark.slow
def test_frame_gradient_is_finite_where_plain_sqrt_weights_are_not(
    recording: Path, cli_run: tuple[Path, str]
) -> None:
    """A real frame's evidence has points of weight 0 in every group, where d sqrt(w) is inf: the
    implicit gradient of the fit would multiply that by 0 (NaN). The frame's own loss gradient
    (not the batch's, which drops non-finite frames) must be finite and match central differences.
    """
    from sinkjax.geometry import travel_sign
    from sinkjax.soft.fit import build_evidence
    from sinkjax.soft.hough import hough_rim
    from sinkjax.soft.outline import extract_outline, refine_outline
    from sinkjax.soft.segmentation import wheel_mask
    from sinkjax.soft.settings import SoftSettings

    rig = load_rig(recording / "rig.toml")
    frames = C.read_labels(recording / "LABELS.csv", rig)
    image = jnp.asarray(frames.images[0], jnp.float64) / 255.0
    target = jnp.asarray(frames.targets[0])
    raw = C.to_raw(rig.segmentation)

    # The removed guard's probe, on this frame's evidence: with plain square roots of the weights
    # the residuals' derivative with respect to the boundary weights is not finite.
    # Jitted: run op by op, these stages compile every primitive on first use (slower).
    @jax.jit
    def probe(image: jax.Array, raw: jax.Array) -> tuple[jax.Array, jax.Array]:
        mask = wheel_mask(image, C.from_raw(raw), rig.confidence_rect)
        s = SoftSettings()
        outline = refine_outline(image, extract_outline(mask, s), s)
        rim = hough_rim(outline, *mask.shape, s)
        ev = build_evidence(outline, rim, travel_sign(rig.travel), s)
        g_naive = jax.grad(
            lambda w: jnp.sum(naive_residuals(ev.start, eqx.tree_at(lambda e: e.w_line, ev, w)))
        )(ev.w_line)
        return ev.w_line, g_naive

    w_line, g_naive = probe(image, raw)
    assert np.any(np.asarray(w_line) == 0) and np.any(np.asarray(w_line) > 0)
    assert not np.all(np.isfinite(np.asarray(g_naive)))

    static = dict(
        rect=rig.confidence_rect, travel=rig.travel, wheel_radius_mm=float(rig.wheel_radius_mm)
    )
    # One compiled function for the gradient and the differences (value and grad: one compile).
    # The image is an argument: closed over, XLA would constant-fold the work done on it.
    loss_grad = jax.jit(jax.value_and_grad(lambda r, im: C.frame_loss(r, im, target, **static)[0]))
    g = np.asarray(loss_grad(raw, image)[1])
    assert np.all(np.isfinite(g)) and np.abs(g).max() > 0

    def central(i: int, h: float) -> float:
        e = jnp.zeros(len(C.RAW_NAMES)).at[i].set(h)
        return (float(loss_grad(raw + e, image)[0]) - float(loss_grad(raw - e, image)[0])) / (2 * h)

    checked = 0
    for i in range(len(C.RAW_NAMES)):
        fd1, fd2 = central(i, 1e-4), central(i, 2e-5)
        if abs(fd1 - fd2) > 0.01 * abs(fd1) + 1e-7:  # a jump within the step: see above
            continue
        checked += 1
        assert g[i] == pytest.approx(fd1, rel=0.03, abs=1e-6), (i, g, fd1)
    assert checked >= 3


@pytest.mark.heavy
@pytest.mark.slow
def test_calibrated_rig_round_trips(recording: Path, cli_run: tuple[Path, str]) -> None:
    from sinkjax.rig import save_rig

    out = cli_run[0]
    rig = load_rig(out)
    again = recording / "again.toml"
    save_rig(rig, again)
    back = load_rig(again)
    assert same_rig(back, rig)
    # Dropped next to the images as rig.toml it is what estimate picks up.
    copy = recording / "copy"
    copy.mkdir()
    shutil.copy(out, copy / "rig.toml")
    assert same_rig(load_rig(copy / "rig.toml"), rig)
    # Same estimates: every parameter is the same float, so the estimator sees the same input.
    frames = C.read_labels(recording / "LABELS.csv", rig)
    images, targets = jnp.asarray(frames.images), jnp.asarray(frames.targets)

    def values(r: Rig) -> np.ndarray:
        return np.asarray(
            C.loss_and_grad(
                C.to_raw(r.segmentation),
                images,
                targets,
                jax.random.key(0),
                rect=r.confidence_rect,
                travel=r.travel,
                wheel_radius_mm=float(r.wheel_radius_mm),
            ).frames.values
        )

    np.testing.assert_array_equal(values(back), values(rig))
    assert not np.array_equal(values(back), values(load_rig(recording / "rig.toml")))


def test_the_returned_point_is_scored_with_the_rim_it_finds_itself() -> None:
    # Points scored with the start's rim: the lowest (index 3) hides the rim, so with the rim
    # it finds itself (none: each frame's own) its loss is 35; the grid's best (index 1) finds
    # the start's rim and keeps its 0.5. The grid's best is returned, with that loss.
    held = RecordingRim.fixed(100.0, 80.0, 60.0, 0.1)
    losses = (2.0, 0.5, 0.9, 0.2)
    points = [
        (jnp.full(7, float(i)), types.SimpleNamespace(loss=jnp.asarray(v)))
        for i, v in enumerate(losses)
    ]
    rims = {0: held, 1: held, 2: held, 3: RecordingRim.per_frame()}
    scored: list[int] = []

    def loss_with(raw, rim):
        scored.append(int(raw[0]))
        assert rim is rims[int(raw[0])]
        return types.SimpleNamespace(loss=jnp.asarray(35.0))

    chosen, measured = O._as_estimate_measures(
        list(points), 3, 3, loss_with, lambda raw: rims[int(raw[0])], held
    )
    assert chosen == 1 and measured == {3, 0, 1}
    assert scored == [3]  # only the point whose own rim differs is scored again
    # The lowest point measures 35 with its own rim; the grid point of 0.5 finds another rim
    # too, and measures 0.7 with it: the start (2.0) is returned if nothing else is lower.
    rims[1] = RecordingRim.fixed(101.0, 80.0, 60.0, 0.1)
    scored.clear()
    own_losses = {1: 0.7, 3: 35.0}

    def loss_own(raw, rim):
        scored.append(int(raw[0]))
        return types.SimpleNamespace(loss=jnp.asarray(own_losses[int(raw[0])]))

    rescored = list(points)
    chosen, measured = O._as_estimate_measures(
        rescored, 3, 3, loss_own, lambda raw: rims[int(raw[0])], held
    )
    # Scored lowest first: 3 (35), the start (2.0, its own rim), then grid point 1 (0.5 with the
    # start's rim, 0.7 with its own) beats it; grid point 2 (0.9 > 0.7) is not scored.
    assert chosen == 1 and scored == [3, 1] and float(rescored[1][1].loss) == 0.7
    assert measured == {3, 0, 1}
    assert float(rescored[3][1].loss) == 35.0 and float(rescored[2][1].loss) == 0.9
    # When the lowest point finds the same rim, it stays, unscored again.
    rims[3] = RecordingRim.fixed(100.0, 80.0, 60.0, 0.1)
    rims[1] = held
    scored.clear()
    chosen, _ = O._as_estimate_measures(
        list(points), 3, 3, loss_with, lambda raw: rims[int(raw[0])], held
    )
    assert chosen == 3 and scored == []


def test_polish_walks_down_a_staircase_and_never_goes_up() -> None:
    from sinkjax.calibration import rescore as R

    # A loss measured as estimate does: piecewise constant (each threshold moves pixels in
    # steps), no gradient. Its minimum lies at raw (1.0, -0.5, 0.75, x): reachable by steps of
    # 0.5 and 0.25 from 0. Raw 4..6 (temperatures, veto) are never moved.
    target = np.array([1.0, -0.5, 0.75])

    def score(raw, bound=math.inf):  # a staircase: nothing to stop early
        r = np.asarray(raw)
        loss = float(np.sum(np.round(np.abs(r[:3] - target) / 0.125)) + 0.1 * abs(r[6]))
        return types.SimpleNamespace(loss=jnp.asarray(loss))

    start = jnp.zeros(7).at[6].set(0.3)
    seen: list[float] = []
    trail = R.polish(start, score(start), score, 200, seen.append)
    best = min(trail, key=lambda p: float(p[1].loss))
    np.testing.assert_allclose(np.asarray(best[0])[:3], target, atol=1e-12)
    assert float(best[1].loss) == pytest.approx(0.03)
    assert all(float(np.asarray(r)[6]) == pytest.approx(0.3) for r, _ in trail)
    assert seen == [float(o.loss) for _, o in trail]
    # A budget is a budget; a start that is already the minimum stays the minimum.
    assert len(R.polish(start, score(start), score, 5)) == 5
    at_min = best[0]
    assert min(float(o.loss) for _, o in R.polish(at_min, score(at_min), score, 100)) >= 0.03


def test_polish_never_returns_a_point_it_stopped_early() -> None:
    from sinkjax.calibration import rescore as R

    # A measurement stopped early returns a lower bound just above its bound (the tightest a
    # pruned loss can be), marked incomplete; the lowest point is always a complete one.
    def loss(raw):
        return float(np.sum(np.abs(np.asarray(raw)[:4] - 0.3)))

    def score(raw, bound=math.inf):
        full = loss(raw)
        if full > bound:
            return types.SimpleNamespace(loss=jnp.asarray(bound * (1 + 1e-9)), complete=False)
        return types.SimpleNamespace(loss=jnp.asarray(full), complete=True)

    start = jnp.zeros(7)
    points = [(start, score(start))]
    i_best, (before, after, n) = R.polish_best(points, 0, score, 40)
    assert points[i_best][1].complete and after < before and 0 < n <= 40
    assert after == pytest.approx(loss(points[i_best][0]))
    assert any(not o.complete for _, o in points)  # some were stopped early


_LOWER_GRADIENT = """
import jax, jax.numpy as jnp
from sinkjax import calibration as C
from sinkjax.calibration import compiled as CL
from sinkjax.rig import SegmentationParams
from sinkjax.soft.rim import RecordingRim
args = (C.to_raw(SegmentationParams()), jnp.zeros((2, 40, 48, 3), jnp.uint8),
        jnp.full((2, 3), 10.0), jax.random.key(0), RecordingRim.per_frame(),
        CL.loss_rig((10, 10, 5, 5), "right", 100.0), False, C.DEFAULT_CONFIG)
with CL.solve_failures_as_nan():
    text = CL._loss_and_grad.lower(*args).as_text()
print("lapack" in text, "callback" in text)
"""


def test_calibration_gradient_has_no_callback_so_it_can_be_cached() -> None:
    """A compiled function with a Python callback never enters JAX's persistent compilation
    cache: the loss's gradient (through the fit's implicit lineax solve, which checks its
    result with equinox.error_if) is traced with failures as NaN instead. Lowered in a fresh
    process: equinox caches its traced checks, so the first trace decides."""
    proc = subprocess.run(
        [sys.executable, "-c", _LOWER_GRADIENT], capture_output=True, text=True, check=True
    )
    # The linear solves are there (the gradient was lowered), their callback is not.
    assert proc.stdout.split() == ["True", "False"], proc.stdout + proc.stderr[-2000:]


def test_failures_as_nan_is_undone_when_contexts_overlap() -> None:
    """Two threads' contexts that overlap (A enters, B enters, A leaves, B leaves) leave equinox's
    setting as it was, and "nan" while either is inside."""
    import equinox._errors as errors

    before = errors.EQX_ON_ERROR
    a, b = CL.solve_failures_as_nan(), CL.solve_failures_as_nan()
    a.__enter__()
    assert errors.EQX_ON_ERROR == "nan"
    b.__enter__()
    a.__exit__(None, None, None)
    assert errors.EQX_ON_ERROR == "nan"  # B is still inside
    b.__exit__(None, None, None)
    assert errors.EQX_ON_ERROR == before


def test_polish_side_by_side_measures_the_trail_one_after_another_would(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from sinkjax.calibration import rescore as R

    # The step up and the step down are measured together; the step down is kept only where
    # the step up does not lower the loss. A bumpy loss with both kinds of moves, and a budget
    # that ends between the two.
    def score(raw, bound=math.inf):
        r = np.asarray(raw)
        loss = np.sum(np.abs(r[:4] - np.array([0.7, -0.9, 0.2, -0.3]))) + np.sin(9 * r[0]) + 2
        return types.SimpleNamespace(loss=jnp.asarray(float(loss)))

    start = jnp.zeros(7)
    trails = {}
    for threads in ("1", "2"):
        monkeypatch.setenv("SINKJAX_FRAME_THREADS", threads)
        for budget in (7, 40):
            seen: list[float] = []
            trail = R.polish(start, score(start), score, budget, seen.append)
            assert seen == [float(o.loss) for _, o in trail] and len(trail) <= budget
            trails[threads, budget] = [(np.asarray(r).tolist(), float(o.loss)) for r, o in trail]
    assert trails["1", 7] == trails["2", 7] and trails["1", 40] == trails["2", 40]
    best, at, moves = float(score(start).loss), np.zeros(4), []
    for r, loss in trails["1", 40]:
        if loss < best * (1 - R.TIE):
            moves.append(float(np.sum(np.asarray(r[:4]) - at)))
            best, at = loss, np.asarray(r[:4])
    assert min(moves) < 0 < max(moves)  # steps up and steps down were taken


def test_in_order_passes_on_each_channel_after_the_one_before() -> None:
    import threading
    import time

    from sinkjax.calibration.rescore import InOrder

    got: list[tuple[float, bool]] = []
    relay = InOrder(lambda v, first: got.append((v, first)), 3)

    def feed(k: int, delay: float) -> None:
        for j in range(4):
            time.sleep(delay)
            relay.channel(k)(10 * k + j)
        relay.close(k)

    # Channel 2 ends first and channel 0 last: they still come out 0, 1, 2.
    threads = [threading.Thread(target=feed, args=(k, 0.02 * (3 - k))) for k in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert [v for v, _ in got] == [10 * k + j for k in range(3) for j in range(4)]
    assert [first for _, first in got] == [j == 0 for _ in range(3) for j in range(4)]
