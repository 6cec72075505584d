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


def test_hint_keeps_the_first_keys_in_order_and_reads_only_names(tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(early, "_asked", [])
    for key in (KEYS[0], KEYS[1], KEYS[0], KEYS[2], KEYS[3]):
        early.note(tmp_path, key)
    assert early.read_hint(tmp_path) == KEYS[:3]
    # A process asking for what the hint begins with leaves it as it is ...
    monkeypatch.setattr(early, "_asked", [])
    early.note(tmp_path, KEYS[0])
    assert early.read_hint(tmp_path) == KEYS[:3]
    # ... one that starts otherwise rewrites it.
    early.note(tmp_path, KEYS[4])
    assert early.read_hint(tmp_path) == [KEYS[0], KEYS[4]]
    (tmp_path / early.HINT).write_text(f"../etc/passwd\n{KEYS[1].upper()}\n{KEYS[2]}\n\n")
    assert early.read_hint(tmp_path) == [KEYS[2]]
    (tmp_path / early.HINT).write_bytes(b"\xff\xfe")
    assert early.read_hint(tmp_path) == []
    assert early.read_hint(tmp_path / "missing") == []


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
    hint = early.read_hint(cache / "executables")
    kept = sorted(p.stem for p in (cache / "executables").glob("*.exe"))
    # prepare, finish, rechoose in the order first called. What compiled afresh is kept:
    # prepare and finish on an idle machine (rechoose compiles in under JAX's threshold; which
    # compiles count as fresh can move with the machine's load).
    assert len(hint) == 3 and kept and set(kept) <= set(hint)
    warm = _cli(folder, tmp_path / "warm.csv", cache)
    assert warm["code"] == 0 and sorted(warm["taken"]) == kept
    # A compiled file of the first layout is not loaded ahead, but loaded and rewritten.
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
