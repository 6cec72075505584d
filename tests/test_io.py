"""Inputs (PATHs, pixels, rig), the pipeline's ordering and failure isolation, overlays, plots."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from sinkjax.app.frames import Frame, iter_frames, read_image, to_rgb8
from sinkjax.app.overlay import OverlayWriter, draw_overlay, overlay_name
from sinkjax.app.pipeline import estimate_paths, estimate_stream, iter_estimates, load_method
from sinkjax.app.plots import match_truth, plot_accuracy
from sinkjax.app.sources import InputError, expand_paths, parse_rect, resolve_rig
from sinkjax.result import FrameResult, Overlay
from sinkjax.rig import Rig, RigError, rect_problem

RIG = Rig(wheel_radius_mm=100.0, confidence_rect=(2, 2, 4, 4), travel="right")


def rgb_image(h: int = 24, w: int = 32, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def write_rgb(path: Path, rgb: np.ndarray) -> Path:
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return path


# --- pixel conversions -------------------------------------------------------------------------


def test_grey_becomes_three_equal_channels():
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4)
    for a in (grey, grey[:, :, None]):
        out = to_rgb8(a)
        assert out.shape == (3, 4, 3) and out.dtype == np.uint8
        for c in range(3):
            np.testing.assert_array_equal(out[:, :, c], grey)


def test_bgra_drops_alpha_and_reorders():
    bgra = np.zeros((2, 2, 4), np.uint8)
    bgra[..., 0], bgra[..., 1], bgra[..., 2], bgra[..., 3] = 10, 20, 30, 0  # fully transparent
    out = to_rgb8(bgra)
    assert out.shape == (2, 2, 3)
    np.testing.assert_array_equal(out[0, 0], [30, 20, 10])
    np.testing.assert_array_equal(to_rgb8(bgra, bgr=False)[0, 0], [10, 20, 30])


def test_sixteen_bit_scales_full_range():
    k = np.arange(256, dtype=np.uint16)
    a = np.stack([k * 257] * 3, axis=-1)[None]  # exact 8-bit values in 16-bit
    np.testing.assert_array_equal(to_rgb8(a)[0, :, 0], np.arange(256))
    edge = np.array([[[0, 128, 65535]]], np.uint16)
    np.testing.assert_array_equal(to_rgb8(edge, bgr=False)[0, 0], [0, 0, 255])  # 128/257 ~ 0.5


def test_unsupported_pixel_type_says_so():
    with pytest.raises(ValueError, match="unsupported pixel type float32"):
        to_rgb8(np.zeros((2, 2, 3), np.float32))
    with pytest.raises(ValueError, match="unsupported image shape"):
        to_rgb8(np.zeros((2, 2, 5), np.uint8))


def test_read_image_formats_agree(tmp_path):
    rgb = rgb_image()
    for ext in ("png", "bmp", "tif"):
        np.testing.assert_array_equal(read_image(write_rgb(tmp_path / f"a.{ext}", rgb)), rgb)
    jpg = read_image(write_rgb(tmp_path / "a.JPG", rgb))
    assert jpg.shape == rgb.shape and jpg.dtype == np.uint8
    # Colour order: a pure red image reads back red.
    red = np.zeros((8, 8, 3), np.uint8)
    red[..., 0] = 255
    np.testing.assert_array_equal(
        read_image(write_rgb(tmp_path / "red.png", red))[0, 0], [255, 0, 0]
    )


def test_read_image_grey_rgba_16bit_files(tmp_path):
    grey = np.arange(64, dtype=np.uint8).reshape(8, 8)
    cv2.imwrite(str(tmp_path / "g.png"), grey)
    assert read_image(tmp_path / "g.png").shape == (8, 8, 3)
    bgra = np.zeros((8, 8, 4), np.uint8)
    bgra[..., 2], bgra[..., 3] = 200, 7
    cv2.imwrite(str(tmp_path / "rgba.png"), bgra)
    np.testing.assert_array_equal(read_image(tmp_path / "rgba.png")[0, 0], [200, 0, 0])
    sixteen = np.full((8, 8, 3), 257 * 100, np.uint16)
    cv2.imwrite(str(tmp_path / "s.png"), sixteen)
    out = read_image(tmp_path / "s.png")
    assert out.dtype == np.uint8 and (out == 100).all()


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "empty file"),
        (b"this is not an image\n", "not an image"),
    ],
)
def test_unreadable_content(tmp_path, content, message):
    p = tmp_path / "bad.png"
    p.write_bytes(content)
    with pytest.raises(ValueError, match=message):
        read_image(p)


def test_truncated_png_and_jpeg(tmp_path):
    rgb = rgb_image(40, 50)
    for ext, word in (("png", "truncated PNG"), ("jpg", "truncated JPEG")):
        data = write_rgb(tmp_path / f"full.{ext}", rgb).read_bytes()
        cut = tmp_path / f"cut.{ext}"
        cut.write_bytes(data[: len(data) * 2 // 3])
        with pytest.raises(ValueError, match=word):
            read_image(cut)


# --- PATH expansion ----------------------------------------------------------------------------


def test_expand_paths_order_and_names(tmp_path, monkeypatch, write_video):
    monkeypatch.chdir(tmp_path)
    d = tmp_path / "rec"
    d.mkdir()
    for n in ("b.png", "a.PNG", "c.jpeg", ".hidden.png", "notes.txt", "rig.toml"):
        (d / n).write_bytes(b"x")
    (d / "sub").mkdir()
    (tmp_path / "single.bmp").write_bytes(b"x")
    write_video(tmp_path / "v.avi", 2)
    inputs = expand_paths(["single.bmp", "rec/", "v.avi", "rec"])
    names = [s.name for s in inputs.sources]
    assert names == [
        "single.bmp",
        "rec/a.PNG",
        "rec/b.png",
        "rec/c.jpeg",
        "v.avi",
        os.path.join("rec", "a.PNG"),
        os.path.join("rec", "b.png"),
        os.path.join("rec", "c.jpeg"),
    ]
    assert [s.kind for s in inputs.sources][4] == "video"
    assert inputs.directory_rigs == (Path("rec/rig.toml"), Path("rec/rig.toml"))


def test_expand_paths_errors(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        expand_paths([str(tmp_path / "nope.png")])
    (tmp_path / "rig.toml").write_text("")
    with pytest.raises(InputError, match="--rig"):
        expand_paths([str(tmp_path / "rig.toml")])
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no images or videos"):
        expand_paths([str(tmp_path / "empty")])


def test_video_frames_streamed_and_named(tmp_path, write_video):
    for ext in ("avi", "mp4"):
        v = write_video(tmp_path / f"clip.{ext}", 3)
        frames = list(iter_frames(expand_paths([str(v)]).sources))
        assert [f.name for f in frames] == [f"{v}#{i:06d}" for i in range(3)]
        assert [f.stem for f in frames] == [f"clip_{i:06d}" for i in range(3)]
        for i, f in enumerate(frames):
            assert f.image is not None and f.image.shape == (24, 32, 3)
            assert abs(float(f.image.mean()) - 40 * i) < 6


def test_broken_video_is_one_unreadable_row(tmp_path):
    v = tmp_path / "broken.mp4"
    v.write_bytes(b"not a video at all")
    frames = list(iter_frames(expand_paths([str(v)]).sources))
    assert len(frames) == 1
    assert frames[0].image is None and frames[0].status == "unreadable"
    assert frames[0].name == str(v)


def test_unreadable_files_become_frames_with_reasons(tmp_path):
    write_rgb(tmp_path / "0_good.png", rgb_image())
    (tmp_path / "1_empty.png").write_bytes(b"")
    (tmp_path / "2_text.png").write_text("hello")
    frames = list(iter_frames(expand_paths([str(tmp_path)]).sources))
    assert [f.status for f in frames] == ["", "unreadable", "unreadable"]
    assert "empty" in frames[1].message and "not an image" in frames[2].message


# --- rig resolution ----------------------------------------------------------------------------


def _write_rig(d: Path, radius: float = 140.0, rect=(1, 2, 3, 4), travel="right") -> Path:
    x, y, w, h = rect
    p = d / "rig.toml"
    p.write_text(
        f'wheel_radius_mm = {radius}\nconfidence_rect = [{x}, {y}, {w}, {h}]\ntravel = "{travel}"\n'
    )
    return p


def test_rig_from_directory_and_overrides(tmp_path):
    d = tmp_path / "rec"
    d.mkdir()
    write_rgb(d / "a.png", rgb_image())
    _write_rig(d)
    inputs = expand_paths([str(d)])
    rig = resolve_rig(inputs)
    assert (rig.wheel_radius_mm, rig.confidence_rect, rig.travel) == (140.0, (1, 2, 3, 4), "right")
    rig = resolve_rig(inputs, wheel_radius_mm=99.0, travel="left")
    assert (rig.wheel_radius_mm, rig.confidence_rect, rig.travel) == (99.0, (1, 2, 3, 4), "left")
    other = tmp_path / "other"
    other.mkdir()
    rig = resolve_rig(inputs, rig_path=_write_rig(other, 50.0), confidence_rect=(5, 6, 7, 8))
    assert (rig.wheel_radius_mm, rig.confidence_rect) == (50.0, (5, 6, 7, 8))


def test_rig_from_flags_only_and_errors(tmp_path):
    rig = resolve_rig(None, wheel_radius_mm=120.0, confidence_rect=(0, 0, 5, 5))
    assert rig.wheel_radius_mm == 120.0 and rig.travel == "right"
    with pytest.raises(RigError) as e:
        resolve_rig(None)
    for needed in ("--rig", "--wheel-radius-mm", "--confidence-rect", "rig.toml"):
        assert needed in str(e.value)
    with pytest.raises(RigError, match="confidence_rect"):
        resolve_rig(None, wheel_radius_mm=120.0)
    with pytest.raises(RigError, match="wheel_radius_mm must be a positive"):
        resolve_rig(None, wheel_radius_mm=-1.0, confidence_rect=(0, 0, 5, 5))
    with pytest.raises(RigError, match="does not exist"):
        resolve_rig(None, rig_path=tmp_path / "missing.toml")


def test_parse_rect():
    assert parse_rect("1,2,3,4") == (1, 2, 3, 4)
    assert parse_rect(" 1, 2 ,3,4 ") == (1, 2, 3, 4)
    for bad in ("1,2,3", "a,b,c,d", "1.5,2,3,4", ""):
        with pytest.raises(RigError, match="X,Y,W,H"):
            parse_rect(bad)


def test_rect_problem():
    rect = (10, 10, 5, 5)
    assert rect_problem(rect, 15, 15) is None
    msg = rect_problem(rect, 14, 20)
    assert msg is not None and "20x14" in msg and "--confidence-rect" in msg
    assert rect_problem((-1, 0, 5, 5), 100, 100) is not None


# --- pipeline ----------------------------------------------------------------------------------


class FakeMethod:
    """Records batches; sinkage = image mean; raises for images whose top-left pixel is 13."""

    def __init__(self) -> None:
        self.batches: list[list[str]] = []

    def __call__(self, images, rig, names):
        self.batches.append(list(names))
        if any(int(im[0, 0, 0]) == 13 for im in images):
            raise RuntimeError("boom")
        return [
            FrameResult(image="wrong name", status="ok", sinkage_mm=float(im.mean()))
            for im in images
        ]


def _frames(*specs) -> list[Frame]:
    out = []
    for i, spec in enumerate(specs):
        if spec is None:
            out.append(Frame(f"f{i}", None, "unreadable", "empty file (0 bytes)"))
        else:
            h, w, first = spec
            im = np.full((h, w, 3), 50, np.uint8)
            im[0, 0, 0] = first
            out.append(Frame(f"f{i}", im))
    return out


def test_stream_keeps_order_and_batches_by_size():
    fake = FakeMethod()
    frames = _frames((20, 20, 1), None, (20, 20, 2), (24, 20, 3), (24, 20, 4), (20, 20, 5))
    results = list(estimate_stream(frames, RIG, method=fake, batch_size=8))
    assert [r.image for r in results] == [f"f{i}" for i in range(6)]
    assert [r.status for r in results] == ["ok", "unreadable", "ok", "ok", "ok", "ok"]
    assert results[1].message == "empty file (0 bytes)"
    assert fake.batches == [["f0", "f2"], ["f3", "f4"], ["f5"]]


def test_batch_size_limits_batches():
    fake = FakeMethod()
    list(estimate_stream(_frames(*[(16, 16, 0)] * 5), RIG, method=fake, batch_size=2))
    assert fake.batches == [["f0", "f1"], ["f2", "f3"], ["f4"]]


def test_failing_frame_retried_alone_and_isolated():
    fake = FakeMethod()
    frames = _frames((16, 16, 1), (16, 16, 13), (16, 16, 2))
    results = list(estimate_stream(frames, RIG, method=fake))
    assert [r.status for r in results] == ["ok", "error", "ok"]
    assert results[1].message == "RuntimeError: boom"
    assert fake.batches == [["f0", "f1", "f2"], ["f0"], ["f1"], ["f2"]]


def test_wrong_result_count_is_error():
    results = list(estimate_stream(_frames((16, 16, 1)), RIG, method=lambda ims, rig, names: []))
    assert results[0].status == "error" and "0 results for 1 frames" in results[0].message


def test_bad_rect_frames_skip_the_method():
    fake = FakeMethod()
    rig = Rig(wheel_radius_mm=1.0, confidence_rect=(0, 0, 17, 17))
    pairs = list(iter_estimates(_frames((18, 18, 1), (16, 16, 2), (18, 18, 3)), rig, method=fake))
    assert [r.status for _, r in pairs] == ["ok", "bad_rect", "ok"]
    assert "16x16" in pairs[1][1].message
    assert fake.batches == [["f0", "f2"]]
    assert pairs[1][0].image is not None  # the frame itself still travels (for its overlay)


def test_tuple_frames_and_method_validation():
    results = list(estimate_stream([("x.png", rgb_image())], RIG, method=FakeMethod()))
    assert results[0].image == "x.png"
    with pytest.raises(ValueError, match="unknown method"):
        load_method("magic")
    with pytest.raises(ValueError, match="batch_size"):
        iter_estimates([], RIG, method=FakeMethod(), batch_size=0)


# --- overlays and plots ------------------------------------------------------------------------


def _full_result() -> FrameResult:
    return FrameResult(
        image="a.png",
        status="ok",
        sinkage_mm=12.5,
        sinkage_std_mm=0.4,
        theta1_deg=30.0,
        theta2_deg=20.0,
        center_x_px=80.0,
        center_y_px=60.0,
        radius_px=40.0,
        overlay=Overlay(
            centre_px=(80.0, 60.0),
            radius_px=40.0,
            boundary_px=np.array([[50.0, 90.0], [80.0, 92.0], [110.0, 90.0]]),
            line_px=((50.0, 91.0), (110.0, 91.0)),
            a_px=(110.0, 90.0),
            b_px=(50.0, 90.0),
        ),
    )


def test_draw_overlay_draws_and_keeps_input():
    image = np.zeros((120, 160, 3), np.uint8)
    out = draw_overlay(image, _full_result(), RIG)
    assert out.shape == image.shape and out.dtype == np.uint8
    assert not image.any()  # input untouched
    assert (out != 0).any(axis=2).mean() > 0.02
    # A failed frame gets its status written, no crash without overlay data.
    bad = draw_overlay(image, FrameResult(image="b", status="no_wheel", message="no wheel found"))
    assert (bad != 0).any()


def test_overlay_names_unique_and_safe(tmp_path):
    used: set[str] = set()
    assert overlay_name("video_000123", used) == "video_000123.png"
    assert overlay_name("video_000123", used) == "video_000123_2.png"
    assert overlay_name("we?ird name", used) == "we_ird_name.png"
    writer = OverlayWriter(tmp_path / "ov")
    p = writer.write(np.zeros((120, 160, 3), np.uint8), _full_result(), "a", RIG)
    assert p is not None and p.name == "a.png" and cv2.imread(str(p)).shape == (120, 160, 3)
    assert writer.write(None, _full_result(), "b") is None


def test_plot_accuracy_and_matching(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rec = tmp_path / "rec"
    rec.mkdir()
    with open(rec / "truth.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["image", "sinkage_mm", "theta1_deg", "theta2_deg", "extra"])
        for i in range(4):
            w.writerow([f"frame_{i}.png", 10 + i, 30 + i, 20 + i, "x"])
    rows = [
        ["rec/frame_0.png", "ok", "10.5", "0.5", "31", "1", "19", "1"] + [""] * 4,
        ["rec/frame_1.png", "ok", "11.2", "", "31", "", "21", ""] + [""] * 4,
        ["rec/frame_2.png", "no_wheel", "", "", "", "", "", ""] + [""] * 3 + ["lost"],
        ["elsewhere/frame_3.png", "ok", "13", "", "33", "", "23", ""] + [""] * 4,
    ]
    from sinkjax.app.results import COLUMNS

    with open("results.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        w.writerows(rows)
    matched = match_truth("results.csv", rec / "truth.csv")
    assert [m.truth["image"] if m.truth else None for m in matched] == [
        f"frame_{i}.png" for i in range(4)
    ]
    out = plot_accuracy("results.csv", rec / "truth.csv", tmp_path / "plots" / "acc.png")
    png = cv2.imread(str(out))
    assert png is not None and png.shape[0] > 300 and png.shape[1] > 900


def test_failed_rows_do_not_pile_up_behind_a_batch():
    fake = FakeMethod()
    frames = _frames((16, 16, 1), *[None] * 40, (16, 16, 2))
    pairs = iter_estimates(iter(frames), RIG, method=fake, batch_size=2)
    seen = [result.image for _, result in pairs]
    assert seen == [f"f{i}" for i in range(42)]
    assert fake.batches == [["f0"], ["f41"]]  # flushed early instead of holding 40 rows


def test_estimate_paths_finds_rig_in_directory(tmp_path):
    d = tmp_path / "rec"
    d.mkdir()
    write_rgb(d / "a.png", rgb_image())
    (d / "b.png").write_bytes(b"")
    _write_rig(d, rect=(0, 0, 4, 4))
    results = list(estimate_paths([str(d)], method=FakeMethod()))
    assert [(r.image, r.status) for r in results] == [
        (os.path.join(str(d), "a.png"), "ok"),
        (os.path.join(str(d), "b.png"), "unreadable"),
    ]
    # An image file given on its own uses the rig.toml of its folder (docs/conventions.md §2).
    alone = list(estimate_paths([str(d / "a.png")], method=FakeMethod()))
    assert [(r.image, r.status) for r in alone] == [(str(d / "a.png"), "ok")]
    bare = tmp_path / "bare"
    bare.mkdir()
    write_rgb(bare / "c.png", rgb_image())
    with pytest.raises(RigError, match="no rig"):
        estimate_paths([str(bare / "c.png")], method=FakeMethod())


def test_estimate_paths_on_a_synthetic_recording(synthetic_recording):
    """A rendered recording through the real classic method: its rig.toml is found, every frame
    has a row in order, each row is what the method gives on that frame read directly, and the
    rows are near the recording's truth.csv (conventions §4)."""
    from sinkjax.classic.estimator import estimate_classic
    from sinkjax.rig import load_rig

    rec = synthetic_recording()
    results = list(estimate_paths([str(rec)], method="classic"))
    with open(rec / "truth.csv", newline="") as f:
        truth = list(csv.DictReader(f))
    assert [Path(r.image).name for r in results] == [t["image"] for t in truth]
    rig = load_rig(rec / "rig.toml")
    for row, t in zip(results, truth, strict=True):
        direct = estimate_classic(read_image(rec / t["image"]), rig)
        assert (row.status, row.sinkage_mm, row.theta1_deg) == (
            direct.status,
            direct.sinkage_mm,
            direct.theta1_deg,
        )
        assert row.status in ("ok", "no_contact"), row.message
        if row.status == "ok":
            # The paper's integer-pixel method on 160x120 frames: within ~15 % of the truth.
            assert row.sinkage_mm == pytest.approx(float(t["sinkage_mm"]), rel=0.15, abs=1.0)
