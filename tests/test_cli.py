"""The ``sinkjax`` command line (conventions §3, §4), run in-process with a fake method."""

from __future__ import annotations

import csv
import subprocess
import sys
import types
from pathlib import Path

import cv2
import numpy as np
import pytest

from sinkjax.app import pipeline as _pipeline
from sinkjax.app.cli import COMMANDS, main
from sinkjax.app.results import COLUMNS
from sinkjax.result import FrameResult, Overlay

RIG_FLAGS = ["--wheel-radius-mm", "100", "--confidence-rect", "2,2,4,4"]


@pytest.fixture
def fake(use_method):
    """Replace both methods by a fake that records the rig and names it was given."""

    class Fake:
        def __init__(self) -> None:
            self.rigs: list = []
            self.names: list[str] = []

        def __call__(self, images, rig, names):
            self.rigs.append(rig)
            self.names.extend(names)
            return [
                FrameResult(
                    image=n,
                    status="ok",
                    sinkage_mm=float(im.mean()) / 10,
                    theta1_deg=30.0,
                    theta2_deg=20.0,
                    center_x_px=im.shape[1] / 2,
                    center_y_px=im.shape[0] / 2,
                    radius_px=im.shape[0] / 3,
                    overlay=Overlay(centre_px=(im.shape[1] / 2, im.shape[0] / 2), radius_px=5.0),
                )
                for im, n in zip(images, names, strict=True)
            ]

    f = Fake()
    use_method(f)
    return f


def png(path: Path, value: int = 100, size: tuple[int, int] = (24, 32)) -> Path:
    assert cv2.imwrite(str(path), np.full((*size, 3), value, np.uint8))
    return path


def rows(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        return list(reader.fieldnames or []), list(reader)


def test_estimate_one_row_per_input_in_order(tmp_path, monkeypatch, fake, capsys):
    monkeypatch.chdir(tmp_path)
    d = tmp_path / "rec"
    d.mkdir()
    png(d / "frame_2.png", 20)
    png(d / "frame_1.png", 10)
    (d / "frame_3.png").write_bytes(b"")  # zero bytes
    (d / "frame_4.png").write_text("not an image, just text")
    good = png(d / "frame_5.png", 50).read_bytes()
    (d / "frame_6.png").write_bytes(good[: len(good) // 2])  # truncated
    png(tmp_path / "single.png", 70)
    code = main(["estimate", "single.png", "rec", *RIG_FLAGS, "--method", "classic"])
    assert code == 0
    header, out = rows(tmp_path / "results.csv")
    assert header == list(COLUMNS)
    assert [r["image"] for r in out] == [
        "single.png",
        "rec/frame_1.png",
        "rec/frame_2.png",
        "rec/frame_3.png",
        "rec/frame_4.png",
        "rec/frame_5.png",
        "rec/frame_6.png",
    ]
    assert [r["status"] for r in out] == ["ok", "ok", "ok"] + ["unreadable"] * 2 + ["ok"] + [
        "unreadable"
    ]
    assert out[0]["sinkage_mm"] == "7.0" and out[0]["sinkage_std_mm"] == ""
    assert all(r["message"] for r in out if r["status"] != "ok")
    assert "truncated PNG" in out[6]["message"]
    summary = capsys.readouterr().out.strip().splitlines()[-1]
    assert "7 frames: 4 ok; failed: 3 unreadable" in summary and "results.csv" in summary


def test_video_rows_and_overlays(tmp_path, monkeypatch, fake):
    monkeypatch.chdir(tmp_path)
    writer = cv2.VideoWriter("video.mp4", cv2.VideoWriter_fourcc(*"mp4v"), 5, (32, 24))
    for i in range(3):
        writer.write(np.full((24, 32, 3), 30 * i, np.uint8))
    writer.release()
    png(tmp_path / "still.png")
    (tmp_path / "empty.png").write_bytes(b"")
    options = ["--overlay", "ov", "--out", "out/r.csv", "--batch-size", "2"]
    code = main(["estimate", "video.mp4", "still.png", "empty.png", *RIG_FLAGS, *options])
    assert code == 0
    _, out = rows(tmp_path / "out" / "r.csv")
    assert [r["image"] for r in out] == [
        "video.mp4#000000",
        "video.mp4#000001",
        "video.mp4#000002",
        "still.png",
        "empty.png",
    ]
    written = sorted(p.name for p in (tmp_path / "ov").iterdir())
    assert written == ["still.png", "video_000000.png", "video_000001.png", "video_000002.png"]


def test_rig_in_directory_used_and_flags_override(tmp_path, fake):
    d = tmp_path / "rec"
    d.mkdir()
    png(d / "a.png")
    (d / "rig.toml").write_text(
        'wheel_radius_mm = 140.0\nconfidence_rect = [1, 2, 3, 4]\ntravel = "left"\n'
    )
    out = str(tmp_path / "r.csv")
    assert main(["estimate", str(d), "--out", out]) == 0
    assert (fake.rigs[-1].wheel_radius_mm, fake.rigs[-1].travel) == (140.0, "left")
    args = ["estimate", str(d), "--out", out, "--wheel-radius-mm", "90", "--travel", "right"]
    assert main(args) == 0
    rig = fake.rigs[-1]
    assert (rig.wheel_radius_mm, rig.confidence_rect, rig.travel) == (90.0, (1, 2, 3, 4), "right")
    # --rig serves the recordings without a rig.toml of their own (docs/conventions.md §2).
    rig_file = tmp_path / "other.toml"
    rig_file.write_text("wheel_radius_mm = 50\nconfidence_rect = [0, 0, 8, 8]\n")
    bare = tmp_path / "bare"
    bare.mkdir()
    png(bare / "b.png")
    assert main(["estimate", str(d), str(bare), "--out", out, "--rig", str(rig_file)]) == 0
    assert [r.wheel_radius_mm for r in fake.rigs[-2:]] == [140.0, 50.0]


def test_missing_rig_is_exit_2_with_what_to_pass(tmp_path, fake, capsys):
    png(tmp_path / "a.png")
    code = main(["estimate", str(tmp_path / "a.png"), "--out", str(tmp_path / "r.csv")])
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("sinkjax estimate: error: no rig")
    assert "--rig" in err and "--wheel-radius-mm" in err and "--confidence-rect" in err
    assert "Traceback" not in err
    assert not (tmp_path / "r.csv").exists()
    assert fake.names == []


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--confidence-rect", "1,2,3"], "X,Y,W,H"),
        (["--wheel-radius-mm", "-5", "--confidence-rect", "1,2,3,4"], "wheel_radius_mm"),
        (["--batch-size", "0", *RIG_FLAGS], "--batch-size"),
        (["--rig", "nowhere.toml"], "does not exist"),
    ],
)
def test_bad_arguments_exit_2(tmp_path, monkeypatch, fake, capsys, extra, needle):
    monkeypatch.chdir(tmp_path)
    png(tmp_path / "a.png")
    assert main(["estimate", "a.png", *extra]) == 2
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err


def test_missing_path_exit_2(tmp_path, fake, capsys):
    assert main(["estimate", str(tmp_path / "nope"), *RIG_FLAGS]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_nothing_readable_exit_2_but_rows_written(tmp_path, monkeypatch, fake, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "a.png").write_bytes(b"")
    (tmp_path / "b.jpg").write_text("text")
    assert main(["estimate", "a.png", "b.jpg", *RIG_FLAGS]) == 2
    assert "could be read" in capsys.readouterr().err
    _, out = rows(tmp_path / "results.csv")
    assert [r["status"] for r in out] == ["unreadable", "unreadable"]


def test_bad_rect_frame_status_and_all_bad_rect(tmp_path, monkeypatch, fake, capsys):
    monkeypatch.chdir(tmp_path)
    png(tmp_path / "big.png", size=(40, 40))
    png(tmp_path / "small.png", size=(20, 20))
    flags = ["--wheel-radius-mm", "100", "--confidence-rect", "5,5,20,20"]
    assert main(["estimate", "big.png", "small.png", *flags]) == 0
    _, out = rows(tmp_path / "results.csv")
    assert [r["status"] for r in out] == ["ok", "bad_rect"]
    assert "20x20" in out[1]["message"] and out[1]["sinkage_mm"] == ""
    assert main(["estimate", "small.png", *flags]) == 2
    assert "confidence rectangle" in capsys.readouterr().err


def test_method_exception_becomes_error_row(tmp_path, monkeypatch, capsys):
    def explode(images, rig, names):
        raise ZeroDivisionError("no pixels")

    monkeypatch.setitem(_pipeline._LOADERS, "classic", lambda *_: explode)
    monkeypatch.chdir(tmp_path)
    png(tmp_path / "a.png")
    assert main(["estimate", "a.png", *RIG_FLAGS, "--method", "classic"]) == 0
    _, out = rows(tmp_path / "results.csv")
    assert out[0]["status"] == "error" and out[0]["message"] == "ZeroDivisionError: no pixels"


def test_soft_unavailable_is_clear(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "sinkjax.soft.batch", None)  # import fails
    png(tmp_path / "a.png")
    code = main(["estimate", str(tmp_path / "a.png"), *RIG_FLAGS, "--out", str(tmp_path / "r")])
    assert code == 2
    err = capsys.readouterr().err
    assert "soft method" in err and "--method classic" in err


def test_subcommand_registry_and_usage(capsys):
    assert {"estimate", "synth", "demo", "smooth", "plot"} <= set(COMMANDS)
    with pytest.raises(SystemExit) as e:
        main([])
    assert e.value.code == 2
    with pytest.raises(SystemExit) as e:
        main(["estimate", "--method", "magic", "x.png"])
    assert e.value.code == 2


def test_console_entry_point_no_traceback(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "sinkjax.app.cli", "estimate", str(tmp_path / "missing.png")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert "does not exist" in proc.stderr and "Traceback" not in proc.stderr


def _fake_synth(monkeypatch) -> list[dict]:
    calls: list[dict] = []

    def write_recording(out_dir, *, n_frames=12, seed=0, preset="full", progress=True, **kw):
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        calls.append(dict(n_frames=n_frames, seed=seed, preset=preset, **kw))
        (out / "rig.toml").write_text("wheel_radius_mm = 100.0\nconfidence_rect = [2, 2, 4, 4]\n")
        with open(out / "truth.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["image", "sinkage_mm", "theta1_deg", "theta2_deg"])
            for i in range(n_frames):
                png(out / f"frame_{i:03d}.png", 10 * i)
                w.writerow([f"frame_{i:03d}.png", float(i), 30.0, 20.0])
        return out

    module = types.ModuleType("sinkjax.synth")
    module.write_recording = write_recording  # type: ignore[attr-defined]
    module.PRESETS = {"full": None, "flat": None}  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "sinkjax.synth", module)
    return calls


def test_demo_writes_everything(tmp_path, monkeypatch, fake, capsys):
    _fake_synth(monkeypatch)
    monkeypatch.chdir(tmp_path)
    assert main(["demo", "--method", "classic"]) == 0
    out = tmp_path / "sinkjax-demo"
    _, results = rows(out / "results.csv")
    assert len(results) == 12 and all(r["status"] == "ok" for r in results)
    assert len(list((out / "overlays").glob("*.png"))) == 12
    assert cv2.imread(str(out / "accuracy.png")) is not None
    printed = capsys.readouterr().out
    assert "|sinkage error| [mm]" in printed and "failures: 0 of 12" in printed


def test_synth_command(tmp_path, monkeypatch, capsys):
    calls = _fake_synth(monkeypatch)
    args = ["synth", str(tmp_path / "s"), "--frames", "3", "--seed", "4", "--preset", "flat"]
    assert main([*args, "--width", "64", "--height", "48", "--travel", "left"]) == 0
    want = dict(n_frames=3, seed=4, preset="flat", width=64, height=48, travel="left")
    assert calls == [{**want, "encoding": "linear"}]
    assert "sinkjax estimate" in capsys.readouterr().out
    assert (
        main([*args, "--width", "64", "--height", "48", "--travel", "left", "--encoding", "srgb"])
        == 0
    )
    assert calls[-1] == {**want, "encoding": "srgb"}
    capsys.readouterr()
    assert main(["synth", str(tmp_path / "t"), "--preset", "nope"]) == 2
    assert "full, flat" in capsys.readouterr().err
