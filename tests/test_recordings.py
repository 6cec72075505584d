"""One command over several recordings = the same commands run one recording at a time.

Each recording (a directory, a video, or image files from one folder) uses its own rig.toml
(docs/conventions.md §2); the recordings here differ in image size, rig and travel direction,
so a run that used one rig for all of them would give other numbers.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import pytest

from sinkjax import synth
from sinkjax.app.cli import main
from sinkjax.app.sources import RigOverrides, open_recordings
from sinkjax.rig import load_rig

SETUPS = (  # (name, width, height, travel, seed)
    ("rec_a", 480, 360, "right", 11),
    ("rec_b", 640, 480, "left", 12),
    ("rec_c", 400, 300, "right", 13),
)


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("campaign")
    for name, width, height, travel, seed in SETUPS:
        synth.write_recording(
            root / name,
            n_frames=2,
            seed=seed,
            preset="clean",
            width=width,
            height=height,
            travel=travel,
            progress=False,
        )
    # A video recording with its rig.toml beside it (in its own folder).
    vid_dir = root / "vid"
    vid_dir.mkdir()
    src = root / "rec_b"
    frames = sorted(src.glob("frame_*.png"))
    first = cv2.imread(str(frames[0]))
    writer = cv2.VideoWriter(
        str(vid_dir / "run.avi"),
        cv2.VideoWriter_fourcc(*"MJPG"),  # type: ignore[attr-defined]
        5.0,
        (first.shape[1], first.shape[0]),
    )
    for f in frames:
        writer.write(cv2.imread(str(f)))
    writer.release()
    shutil.copy(src / "rig.toml", vid_dir / "rig.toml")
    return root


def _run(paths: list[str], out: Path, *extra: str) -> bytes:
    assert main(["estimate", *paths, "--out", str(out), "--method", "classic", *extra]) == 0
    return out.read_bytes()


def test_rigs_differ_between_recordings(recordings):
    rigs = [load_rig(recordings / name / "rig.toml") for name, *_ in SETUPS]
    assert len({(r.confidence_rect, r.travel, r.wheel_radius_mm) for r in rigs}) == len(rigs)
    inputs = open_recordings([str(recordings / name) for name, *_ in SETUPS])
    assert [rec.rig for rec in inputs.recordings] == rigs
    assert [rec.rig_source for rec in inputs.recordings] == [
        str(recordings / name / "rig.toml") for name, *_ in SETUPS
    ]


def test_one_command_equals_one_command_per_recording(recordings, tmp_path):
    paths = [str(recordings / name) for name, *_ in SETUPS]
    paths.append(str(recordings / "vid" / "run.avi"))
    # Image files given one by one: one recording per folder, with that folder's rig.
    loose = sorted(str(p) for p in (recordings / "rec_a").glob("frame_*.png"))
    paths += loose
    together = _run(paths, tmp_path / "all.csv").decode().splitlines()
    header, rows = together[0], together[1:]
    separate: list[str] = []
    for i, p in enumerate(paths[: len(SETUPS) + 1]):
        lines = _run([p], tmp_path / f"one_{i}.csv").decode().splitlines()
        assert lines[0] == header
        separate += lines[1:]
    lines = _run(loose, tmp_path / "loose.csv").decode().splitlines()
    separate += lines[1:]
    assert rows == separate
    statuses = [r.split(",")[1] for r in rows]
    assert len(rows) == 2 * len(SETUPS) + 2 + 2 and statuses.count("ok") >= len(rows) - 2


def test_flags_override_every_recording_and_rig_serves_the_rest(recordings, tmp_path):
    bare = tmp_path / "bare"
    shutil.copytree(recordings / "rec_c", bare)
    (bare / "rig.toml").unlink()
    rig_path = recordings / "rec_c" / "rig.toml"
    inputs = open_recordings(
        [str(recordings / "rec_a"), str(bare)],
        rig_path=rig_path,
        overrides=RigOverrides(wheel_radius_mm=77.0),
    )
    own, served = (rec.rig for rec in inputs.recordings)
    assert own is not None and served is not None
    assert own.confidence_rect == load_rig(recordings / "rec_a" / "rig.toml").confidence_rect
    assert served.confidence_rect == load_rig(rig_path).confidence_rect
    assert own.wheel_radius_mm == served.wheel_radius_mm == 77.0
