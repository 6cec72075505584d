"""Long recordings: --start/--stop/--stride, --resume (byte-identical), --overlay-video,
--smooth, and the ``smooth`` and ``plot`` commands. Deterministic fake method throughout."""

from __future__ import annotations

import csv
import functools
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from sinkjax.app.cli import main
from sinkjax.app.frames import FrameSelection, count_frames, iter_frames
from sinkjax.app.results import COLUMNS
from sinkjax.app.smoothing import SMOOTH_COLUMNS
from sinkjax.app.sources import expand_paths
from sinkjax.result import FrameResult

RIG_FLAGS = ["--wheel-radius-mm", "100", "--confidence-rect", "2,2,4,4"]


def fake_rows(images, rig, names):
    """Deterministic: sinkage from the pixels, a std, and one failure per 7 grey levels."""
    out = []
    for im, n in zip(images, names, strict=True):
        level = float(im.mean())
        if int(level) % 7 == 3:
            out.append(FrameResult(image=n, status="fit_failed", message="fake failure"))
            continue
        out.append(
            FrameResult(
                image=n,
                status="ok",
                sinkage_mm=level / 10,
                sinkage_std_mm=0.5,
                theta1_deg=30.0 + level / 100,
                theta1_std_deg=1.0,
                theta2_deg=20.0,
                theta2_std_deg=1.0,
                center_x_px=16.0,
                center_y_px=12.0,
                radius_px=8.0,
            )
        )
    return out


class Interrupting:
    """The fake method, but Ctrl-C arrives when it is asked for the ``after``-th frame."""

    def __init__(self, after: int) -> None:
        self.after = after
        self.seen = 0

    def __call__(self, images, rig, names):
        self.seen += len(names)
        if self.seen > self.after:
            raise KeyboardInterrupt
        return fake_rows(images, rig, names)


@pytest.fixture
def method(use_method):
    """The fake method under both names; returns the setter for another one."""
    use_method(fake_rows)
    return use_method


@pytest.fixture
def write_video(write_video):
    """conftest's video writer with levels 9 i mod 250: fake_rows fails one level in 7."""
    return functools.partial(write_video, step=9)


def images_dir(path: Path, n: int) -> Path:
    path.mkdir()
    for i in range(n):
        assert cv2.imwrite(str(path / f"im_{i:02d}.png"), np.full((20, 24, 3), 10 * i, np.uint8))
    return path


def names(csv_path: Path) -> list[str]:
    with open(csv_path, newline="") as f:
        return [row["image"] for row in csv.DictReader(f)]


# --- frame selection ---------------------------------------------------------------------------


def test_start_stop_stride_on_videos_and_image_sequences(
    tmp_path, monkeypatch, method, write_video
):
    monkeypatch.chdir(tmp_path)
    write_video(tmp_path / "v.mp4", 10)
    images_dir(tmp_path / "ims", 4)
    flags = ["--start", "1", "--stop", "9", "--stride", "3", *RIG_FLAGS]
    assert main(["estimate", "v.mp4", "ims", "ims/im_00.png", *flags]) == 0
    # Video: its frame numbers 1, 4, 7. Images: the 5 image files as one sequence -> 1, 4.
    assert names(tmp_path / "results.csv") == [
        "v.mp4#000001",
        "v.mp4#000004",
        "v.mp4#000007",
        os.path.join("ims", "im_01.png"),
        "ims/im_00.png",
    ]
    sources = expand_paths(["v.mp4", "ims", "ims/im_00.png"]).sources
    select = FrameSelection(1, 9, 3)
    assert count_frames(sources, select=select) == 5
    frames = list(iter_frames(sources, select=select))
    assert all(f.image is not None for f in frames)
    # The frame read is the frame named (skipping does not lose sync): level 9 * index.
    assert [round(float(f.image.mean()) / 9) for f in frames[:3]] == [1, 4, 7]  # type: ignore[union-attr]


@pytest.mark.parametrize(
    "flags, needle",
    [
        (["--start", "-1"], "--start must be >= 0"),
        (["--stride", "0"], "--stride must be >= 1"),
        (["--start", "5", "--stop", "5"], "--stop (5) must be greater than --start (5)"),
        (["--start", "50"], "no frames selected"),
        (["--overlay-video", "out.avi"], "--overlay-video must name an .mp4"),
        (["--smooth", "--process-std-mm", "-1"], "--process-std-mm must be a number >= 0"),
    ],
)
def test_bad_long_run_flags_exit_2(
    tmp_path, monkeypatch, method, capsys, flags, needle, write_video
):
    monkeypatch.chdir(tmp_path)
    write_video(tmp_path / "v.mp4", 4)
    assert main(["estimate", "v.mp4", *RIG_FLAGS, *flags]) == 2
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err


# --- resume ------------------------------------------------------------------------------------


def _recording(tmp_path: Path, write_video) -> list[str]:
    write_video(tmp_path / "v.mp4", 23)
    images_dir(tmp_path / "ims", 5)
    (tmp_path / "ims" / "im_03.png").write_bytes(b"")  # an unreadable frame on the way
    return ["v.mp4", "ims"]


@pytest.mark.parametrize("extra", [[], ["--batch-size", "3", "--method", "soft", "--smooth"]])
@pytest.mark.parametrize("after", [0, 1, 11, 26])
def test_interrupted_then_resumed_is_byte_identical(
    tmp_path, monkeypatch, method, extra, after, write_video
):
    monkeypatch.chdir(tmp_path)
    paths = _recording(tmp_path, write_video)
    flags = [*RIG_FLAGS, "--stride", "1", *extra]
    assert main(["estimate", *paths, *flags, "--out", "full.csv"]) == 0
    full = (tmp_path / "full.csv").read_bytes()

    method(Interrupting(after))
    assert main(["estimate", *paths, *flags, "--out", "part.csv"]) == 130
    part = tmp_path / "part.csv"
    kept = part.read_bytes()
    assert kept.startswith(",".join(COLUMNS).encode() + b"\n")  # smoothing comes at the end
    if "--smooth" not in extra:
        assert len(kept) < len(full) and full.startswith(kept)  # only whole rows, in order

    method(fake_rows)
    assert main(["estimate", *paths, *flags, "--out", "part.csv", "--resume"]) == 0
    assert part.read_bytes() == full
    # Resuming a finished file changes nothing.
    assert main(["estimate", *paths, *flags, "--out", "part.csv", "--resume"]) == 0
    assert part.read_bytes() == full


def test_resume_cuts_a_half_written_row_and_keeps_one_header(
    tmp_path, monkeypatch, method, write_video
):
    monkeypatch.chdir(tmp_path)
    paths = _recording(tmp_path, write_video)
    assert main(["estimate", *paths, *RIG_FLAGS, "--out", "full.csv"]) == 0
    full = (tmp_path / "full.csv").read_bytes()
    lines = full.splitlines(keepends=True)
    # Killed in the middle of writing row 6.
    (tmp_path / "part.csv").write_bytes(b"".join(lines[:6]) + lines[6][:17])
    assert main(["estimate", *paths, *RIG_FLAGS, "--out", "part.csv", "--resume"]) == 0
    assert (tmp_path / "part.csv").read_bytes() == full
    assert full.count(b"image,status") == 1
    # --resume without an existing file is a fresh run; an empty file gets its header.
    assert main(["estimate", *paths, *RIG_FLAGS, "--out", "new.csv", "--resume"]) == 0
    assert (tmp_path / "new.csv").read_bytes() == full
    (tmp_path / "empty.csv").write_bytes(b"")
    assert main(["estimate", *paths, *RIG_FLAGS, "--out", "empty.csv", "--resume"]) == 0
    assert (tmp_path / "empty.csv").read_bytes() == full


def test_resume_refuses_a_file_that_is_not_a_results_csv(
    tmp_path, monkeypatch, method, capsys, write_video
):
    monkeypatch.chdir(tmp_path)
    write_video(tmp_path / "v.mp4", 3)
    other = tmp_path / "labels.csv"
    other.write_text("image,sinkage_mm\na.png,3\n")
    assert main(["estimate", "v.mp4", *RIG_FLAGS, "--out", "labels.csv", "--resume"]) == 2
    assert "not a sinkjax results CSV" in capsys.readouterr().err
    assert other.read_text() == "image,sinkage_mm\na.png,3\n"


_KILLABLE = textwrap.dedent(
    """
    import sys, time
    sys.path.insert(0, {tests!r})
    from sinkjax.app import pipeline as _pipeline
    from test_long_runs import fake_rows

    def slow(images, rig, names):
        time.sleep(0.1)
        return fake_rows(images, rig, names)

    _pipeline._LOADERS["classic"] = lambda *_: slow
    from sinkjax.app.cli import main
    sys.exit(main(sys.argv[1:]))
    """
)


def test_killed_process_resumed_is_byte_identical(tmp_path, monkeypatch, method, write_video):
    """SIGKILL (no chance to clean up) after a few rows, then --resume."""
    monkeypatch.chdir(tmp_path)
    write_video(tmp_path / "v.mp4", 60)
    flags = ["v.mp4", *RIG_FLAGS, "--method", "classic"]
    assert main(["estimate", *flags, "--out", "full.csv"]) == 0
    full = (tmp_path / "full.csv").read_bytes()

    script = tmp_path / "killable.py"
    script.write_text(_KILLABLE.format(tests=str(Path(__file__).parent)))
    part = tmp_path / "part.csv"
    proc = subprocess.Popen(
        [sys.executable, str(script), "estimate", *flags, "--out", str(part)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and proc.poll() is None:
            if part.exists() and part.read_bytes().count(b"\n") >= 6:
                break
            time.sleep(0.02)
        assert proc.poll() is None, "the run finished before it could be killed"
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(timeout=30)
    rows_before = part.read_bytes().count(b"\n") - 1
    assert 5 <= rows_before < 60
    assert main(["estimate", *flags, "--out", "part.csv", "--resume"]) == 0
    assert part.read_bytes() == full


# --- overlay video, smoothing, plots -----------------------------------------------------------


def test_overlay_video_has_one_frame_per_row(tmp_path, monkeypatch, method, write_video):
    monkeypatch.chdir(tmp_path)
    write_video(tmp_path / "v.mp4", 6, fps=12)
    (tmp_path / "bad.png").write_bytes(b"")
    args = ["estimate", "bad.png", "v.mp4", *RIG_FLAGS, "--stride", "2"]
    assert main([*args, "--overlay-video", "out/annotated.mp4"]) == 0
    capture = cv2.VideoCapture(str(tmp_path / "out" / "annotated.mp4"))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame)
    assert capture.get(cv2.CAP_PROP_FPS) == pytest.approx(6.0)  # 12 fps / stride 2
    capture.release()
    assert len(frames) == len(names(tmp_path / "results.csv")) == 4
    assert all(f.shape == (24, 32, 3) for f in frames)
    # The overlay draws on the frame (the fake's rim circle and numbers).
    assert all(float(np.abs(f.astype(int) - np.median(f)).mean()) > 1 for f in frames[1:])


def test_smooth_flag_adds_columns_only_when_asked(tmp_path, monkeypatch, method, write_video):
    monkeypatch.chdir(tmp_path)
    write_video(tmp_path / "v.mp4", 8)
    assert main(["estimate", "v.mp4", *RIG_FLAGS, "--out", "plain.csv"]) == 0
    assert main(["estimate", "v.mp4", *RIG_FLAGS, "--out", "smooth.csv", "--smooth"]) == 0
    plain = (tmp_path / "plain.csv").read_text().splitlines()
    smooth = (tmp_path / "smooth.csv").read_text().splitlines()
    assert plain[0] == ",".join(COLUMNS)
    assert smooth[0] == ",".join((*COLUMNS, *SMOOTH_COLUMNS))
    for a, b in zip(plain[1:], smooth[1:], strict=True):
        assert b.startswith(a + ",")
    # The separate step gives the same file.
    assert main(["smooth", "plain.csv", "--out", "again.csv"]) == 0
    assert (tmp_path / "again.csv").read_text() == (tmp_path / "smooth.csv").read_text()


def test_plot_command(tmp_path, monkeypatch, method, capsys, write_video):
    monkeypatch.chdir(tmp_path)
    write_video(tmp_path / "v.mp4", 12)
    assert main(["estimate", "v.mp4", *RIG_FLAGS]) == 0
    assert main(["plot", "results.csv"]) == 0
    image = cv2.imread(str(tmp_path / "results.png"))
    assert image is not None and image.shape[0] > 600 and image.shape[1] > 800
    assert main(["plot", "results.csv", "--smoothed", "--out", "p/s.png"]) == 0
    smoothed = cv2.imread(str(tmp_path / "p" / "s.png"))
    assert smoothed is not None and not np.array_equal(smoothed, image)
    (tmp_path / "labels.csv").write_text("image,sinkage_mm\n")
    assert main(["plot", "labels.csv"]) == 2
    assert "not a sinkjax results CSV" in capsys.readouterr().err
    assert main(["plot", "missing.csv"]) == 2


def test_soft_batches_keep_one_shape(tmp_path, monkeypatch, method, write_video):
    """Every call of a padding estimator gets the same batch size: one compile per image size."""
    pads: list[tuple[int, int | None]] = []

    def padded(images, rig, names, *, pad_to=None):
        pads.append((len(names), pad_to))
        return fake_rows(images, rig, names)

    method(padded)
    monkeypatch.chdir(tmp_path)
    write_video(tmp_path / "v.mp4", 7)
    assert main(["estimate", "v.mp4", *RIG_FLAGS, "--method", "soft", "--batch-size", "4"]) == 0
    assert pads == [(4, 4), (3, 4)]
