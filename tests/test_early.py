"""The command line's early start (sinkjax.app.early): which processes load ahead, the hint of
what to load, and the hand-over of what was loaded; a heavy test runs the command twice and
checks that the second run used the executables loaded ahead, with identical rows."""

from __future__ import annotations

import hashlib
import io
import json
import subprocess
import sys
import threading

import pytest

from sinkjax.app import early
from sinkjax.app.executables import (
    _COMPILED_MAGIC_1,
    COMPILED_MAGIC,
    _Pickler,
    _Unpickler,
    read_checked,
)

KEYS = [hashlib.sha256(bytes([i])).hexdigest() for i in range(5)]


@pytest.mark.parametrize(
    ("orig_argv", "argv", "expected"),
    [
        (["py", "-m", "sinkjax.app.cli", "estimate", "d"], ["-m", "estimate"], ["estimate", "d"]),
        (["py", "-X", "importtime", "-m", "sinkjax.app.cli", "estimate"], ["x"], ["estimate"]),
        (["py", "/venv/bin/sinkjax", "estimate", "d"], ["/venv/bin/sinkjax", "estimate", "d"],
         ["estimate", "d"]),
        (["py", "-m", "pytest", "tests"], ["/venv/pytest", "tests"], None),
        (["py", "-c", "import sinkjax"], ["-c"], None),
        (["py", "script.py", "estimate"], ["script.py", "estimate"], None),
        (["py", "-m"], ["-m"], None),
    ],
)  # fmt: skip
def test_command_args_recognise_the_command_line_only(orig_argv, argv, expected) -> None:
    assert early.command_args(orig_argv, argv) == expected


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["estimate", "rec"], True),
        (["estimate", "rec", "--method", "soft", "--rim", "frame"], True),
        (["estimate", "rec", "--method=soft"], True),
        (["estimate", "rec", "--method", "classic"], False),
        (["estimate", "rec", "--method=classic"], False),
        (["estimate", "rec", "--meth", "classic"], False),  # argparse's abbreviation
        (["estimate", "rec", "--method"], False),
        (["estimate", "rec", "--workers", "2"], False),
        (["estimate", "rec", "--sch", "tcp://x:8786"], False),
        (["estimate", "rec", "--no-compile-cache"], False),
        (["estimate", "rec", "--segmenter", "net.eqx"], False),
        (["synth", "rec"], False),
        (["calibrate", "labels.csv"], False),
        ([], False),
    ],
)
def test_only_a_soft_estimate_with_its_cache_loads_ahead(args, expected) -> None:
    assert early.loads_soft(args) is expected


def test_hint_keeps_each_sizes_first_keys_this_runs_sizes_first(tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(early, "_asked", {})
    monkeypatch.setattr(early, "_size", [])
    a, b = (640, 480), (800, 600)
    early.note(tmp_path, KEYS[4], None)  # no size noted yet: nothing to file it under
    for key, size in ((KEYS[0], a), (KEYS[1], a), (KEYS[0], a), (KEYS[2], None), (KEYS[3], a)):
        early.note(tmp_path, key, size)
    assert early.read_hints(tmp_path) == {a: KEYS[:3]}
    # The next process: another size first; the hint keeps the old size after it ...
    monkeypatch.setattr(early, "_asked", {})
    early.note(tmp_path, KEYS[4], b)
    assert list(early.read_hints(tmp_path).items()) == [(b, [KEYS[4]]), (a, KEYS[:3])]
    # ... and a process whose keys the hint goes on from leaves the rest of them.
    monkeypatch.setattr(early, "_asked", {})
    early.note(tmp_path, KEYS[0], a)
    assert list(early.read_hints(tmp_path).items()) == [(a, KEYS[:3]), (b, [KEYS[4]])]
    (tmp_path / early.HINT).write_text(
        f"640x480 ../etc/passwd {KEYS[1].upper()} {KEYS[2]}\nAxB {KEYS[0]}\n800x600\n\n"
    )
    assert early.read_hints(tmp_path) == {a: [KEYS[2]]}
    (tmp_path / early.HINT).write_bytes(b"\xff\xfe")
    assert early.read_hints(tmp_path) == {}
    assert early.read_hints(tmp_path / "missing") == {}


def test_first_size_reads_the_first_paths_header(tmp_path) -> None:
    import cv2
    import numpy as np

    folder = tmp_path / "rec"
    folder.mkdir()
    cv2.imwrite(str(folder / "b.png"), np.zeros((30, 40, 3), np.uint8))
    cv2.imwrite(str(folder / "a.jpg"), np.zeros((20, 50, 3), np.uint8))
    (folder / ".hidden.png").write_bytes(b"")
    (folder / "rig.toml").write_text("")
    rig = str(folder / "rig.toml")
    assert early.first_size([str(folder)]) == (50, 20)
    assert early.first_size(["--rig", rig, "--resume", str(folder / "b.png"), "x"]) == (40, 30)
    assert early.first_size(["--out=r.csv", str(folder)]) == (50, 20)
    assert early.first_size([str(tmp_path / "run.mp4")]) is None
    assert early.first_size([str(tmp_path / "missing.png")]) is None
    assert early.first_size(["--rig", rig]) is None


def test_no_value_options_are_the_command_lines() -> None:
    import argparse

    from sinkjax.app.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    estimate = sub.choices["estimate"]
    flags = {o for a in estimate._actions if a.nargs == 0 for o in a.option_strings}
    assert flags == set(early.NO_VALUE)
    assert all(a.nargs is None for a in estimate._actions if a.option_strings and a.nargs != 0)


def test_take_waits_for_a_load_under_way_and_leaves_unstarted_ones(monkeypatch) -> None:
    monkeypatch.setattr(early, "_ahead", {})
    monkeypatch.setattr(early, "THREADS", 1)
    release = threading.Event()
    started: list[str] = []

    def load(key: str) -> str:
        started.append(key)
        if key == KEYS[0]:
            release.wait(10)
        if key == KEYS[2]:
            raise ValueError("a spoilt file")
        return f"parts of {KEYS.index(key)}"

    early.start([KEYS[0], KEYS[1], KEYS[2]], load)
    assert early.take(KEYS[1]) is None  # queued behind the first: the caller loads it
    release.set()
    assert early.take(KEYS[0]) == "parts of 0"
    assert early.take(KEYS[0]) is None  # handed out once
    assert early.take(KEYS[2]) is None  # its load failed: the caller reads it (and says why)
    assert early.take(KEYS[3]) is None  # never asked for
    assert KEYS[1] not in started


# The command line in a fresh process, as the `sinkjax` script (argv[0]), so that importing
# sinkjax starts the early load; prints the keys whose executables were taken from it.
_CLI = """
import json, sys
sys.argv = ["sinkjax", "estimate", sys.argv[1], "--out", sys.argv[2]]
from sinkjax.app import cli, early
taken = []
plain = early.take
def spy(key):
    parts = plain(key)
    if parts is not None:
        taken.append(key)
    return parts
early.take = spy
code = cli.main(sys.argv[1:])
print(json.dumps({"code": code, "taken": taken}))
"""


def _cli(folder, out, cache) -> dict:
    env = {"SINKJAX_CACHE_DIR": str(cache), "PATH": "/usr/bin:/bin"}
    proc = subprocess.run(
        [sys.executable, "-c", _CLI, str(folder), str(out)],
        capture_output=True,
        text=True,
        check=True,
        env=env,
    )
    return json.loads(proc.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


@pytest.mark.heavy
@pytest.mark.slow
def test_the_second_run_takes_the_executables_loaded_ahead_with_identical_rows(tmp_path) -> None:
    from sinkjax import synth as S

    folder = tmp_path / "rec"
    S.write_recording(folder, n_frames=3, seed=7, width=200, height=150, progress=False)
    cache = tmp_path / "cache"
    cold = _cli(folder, tmp_path / "cold.csv", cache)
    assert cold == {"code": 0, "taken": []}
    hint = early.read_hints(cache / "executables")[(200, 150)]
    kept = sorted(p.stem for p in (cache / "executables").glob("*.exe"))
    # prepare, finish, rechoose in the order first called, each compiled afresh and kept.
    assert len(hint) == 3 and set(kept) == set(hint)
    warm = _cli(folder, tmp_path / "warm.csv", cache)
    assert warm["code"] == 0 and sorted(warm["taken"]) == kept
    # A run on another image size puts its own keys first in the hint ...
    other = tmp_path / "other"
    S.write_recording(other, n_frames=2, seed=8, width=240, height=180, progress=False)
    assert _cli(other, tmp_path / "other.csv", cache) == {"code": 0, "taken": []}
    assert list(early.read_hints(cache / "executables")) == [(240, 180), (200, 150)]
    # ... and the next run on the first size finds that size's (from its first image's
    # header). A compiled file of the first layout is not loaded ahead, but loaded and
    # rewritten.
    first = cache / "executables" / f"{kept[0]}.exe"
    _to_layout_1(first)
    again = _cli(folder, tmp_path / "again.csv", cache)
    assert again["code"] == 0 and sorted(again["taken"]) == kept[1:]
    assert first.read_bytes().startswith(COMPILED_MAGIC)
    rows = [(tmp_path / f"{n}.csv").read_text() for n in ("cold", "warm", "again")]
    assert rows[0] == rows[1] == rows[2]


def _to_layout_1(path) -> None:
    """Rewrite a compiled file in the first layout: one pickle of key, blob and pytrees."""
    body = read_checked(path, COMPILED_MAGIC)
    stream = io.BytesIO(body)
    key, blob = _Unpickler(stream).load()
    in_tree, out_tree = _Unpickler(stream).load()
    buffer = io.BytesIO()
    _Pickler(buffer).dump((key, blob, in_tree, out_tree))
    old = buffer.getvalue()
    path.write_bytes(_COMPILED_MAGIC_1 + hashlib.sha256(old).hexdigest().encode() + b"\n" + old)
