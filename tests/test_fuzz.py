"""Bad input, tried on purpose (property-based, deterministic).

Every bad frame gets exactly one row, in input order, with a status and a message in words; a bad
rig or bad arguments give one clear error before any work. The pipeline is exercised with the
real classic method and with a fast fake soft method (which also crashes on purpose, to check
that a crash spoils only its own frame); a subset goes through the real soft estimator in a
separate process (float32, as users run it).
"""

from __future__ import annotations

import contextlib
import csv
import functools
import io
import math
import os
import subprocess
import sys
import tempfile
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from unittest import mock

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from sinkjax.app import pipeline as _pipeline
from sinkjax.app.cli import main
from sinkjax.app.frames import MIN_IMAGE_SIDE_PX
from sinkjax.app.results import COLUMNS
from sinkjax.result import FrameResult

# A rectangle that fits frames of at least 28x18 px: narrower frames are "off the rectangle".
RECT = (20, 10, 8, 8)
RIG_FLAGS = ["--wheel-radius-mm", "100", "--confidence-rect", ",".join(map(str, RECT))]
KNOWN = {"ok", "no_contact", "unreadable", "no_wheel", "fit_failed", "bad_rect", "bad_image"}
CRASH_PIXEL = (13, 17, 19)  # the fake soft method raises on frames starting with this pixel
FUZZ = settings(
    derandomize=True,
    database=None,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


@dataclass(frozen=True)
class BadInput:
    """One input file made to be awkward; ``expect``: the statuses allowed for its row(s)."""

    kind: str
    suffix: str
    data: bytes
    expect: frozenset[str] | None = None  # None: any known status (the frame may be measurable)
    video: bool = False


# --- pixels ------------------------------------------------------------------------------------


def scene(h: int, w: int, content: str, seed: int) -> np.ndarray:
    """An RGB uint8 frame: noise, flat colours, bare soil, or a drawn wheel (rect on/off it)."""
    rng = np.random.default_rng(seed)
    if content == "noise":
        return rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    if content in ("black", "white"):
        return np.full((h, w, 3), 0 if content == "black" else 255, np.uint8)
    soil = np.array([150, 120, 70]) + rng.normal(0, 6, (h, w, 3))
    if content == "soil":
        return np.clip(soil, 0, 255).astype(np.uint8)
    image = np.ascontiguousarray(np.clip(soil, 0, 255).astype(np.uint8))
    x, y, rw, rh = RECT
    cx, cy = (x + rw // 2, y + rh // 2) if content == "wheel" else (w // 5, h - 2)
    radius = int(rng.integers(6, 14))
    cv2.circle(image, (cx, cy), radius, (60, 60, 200), -1)
    image[int(rng.integers(h // 2, h)) :] = (150, 120, 70)
    return image


def encode(rgb_or_grey: np.ndarray, ext: str) -> bytes:
    a = rgb_or_grey
    if a.ndim == 3 and a.shape[2] >= 3:
        a = a.copy()
        a[:, :, :3] = a[:, :, 2::-1]  # RGB(A) -> BGR(A)
    ok, buf = cv2.imencode(ext, a)
    assert ok, (ext, a.shape, a.dtype)
    return buf.tobytes()


@functools.cache
def small_video(ext: str) -> bytes:
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / f"v{ext}"
        fourcc = "MJPG" if ext == ".avi" else "mp4v"
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 5, (32, 24))
        for i in range(4):
            writer.write(cv2.cvtColor(scene(24, 32, "wheel", i), cv2.COLOR_RGB2BGR))
        writer.release()
        return path.read_bytes()


# --- strategies for bad inputs -----------------------------------------------------------------

sides = st.tuples(st.integers(18, 48), st.integers(28, 64))
contents = st.sampled_from(["noise", "black", "white", "soil", "wheel", "wheel_elsewhere"])
seeds = st.integers(0, 2**16)
UNREADABLE = frozenset({"unreadable"})


@st.composite
def zero_byte(draw) -> BadInput:
    ext = draw(st.sampled_from([".png", ".jpg", ".bmp", ".tif", ".mp4", ".avi"]))
    return BadInput("zero_byte", ext, b"", UNREADABLE, video=ext in (".mp4", ".avi"))


@st.composite
def truncated_image(draw) -> BadInput:
    ext = draw(st.sampled_from([".png", ".jpg", ".bmp", ".tif"]))
    (h, w), content, seed = draw(sides), draw(contents), draw(seeds)
    data = encode(scene(h, w, content, seed), ext)
    cut = draw(st.integers(1, len(data) - 1))
    # PNG and JPEG are checked for their end marker; BMP/TIFF may decode a damaged picture.
    expect = UNREADABLE if ext in (".png", ".jpg") else None
    return BadInput(f"truncated{ext}", ext, data[:cut], expect)


@st.composite
def not_an_image(draw) -> BadInput:
    ext = draw(st.sampled_from([".png", ".jpg", ".jpeg", ".bmp", ".tiff"]))
    data = draw(
        st.one_of(
            st.binary(min_size=1, max_size=300),
            st.text(min_size=1, max_size=200).map(lambda t: t.encode()),
            st.sampled_from([b"\x89PNG\r\n\x1a\n", b"\xff\xd8", b"BM", b"II*\x00"]).flatmap(
                lambda magic: st.binary(max_size=300).map(lambda tail: magic + tail)
            ),
        )
    )
    return BadInput("not_an_image", ext, data, frozenset({"unreadable", "bad_image"}))


ODD_PIXELS = ("grey8", "grey16", "rgb16", "rgba8", "rgba16")


@st.composite
def odd_pixels(draw, kinds: tuple[str, ...] = ODD_PIXELS) -> BadInput:
    """Grey, grey 16-bit, RGB 16-bit, RGBA (8 and 16 bit): readable, converted to RGB8."""
    kind = draw(st.sampled_from(kinds))
    ext = draw(st.sampled_from([".png", ".tif"]))
    (h, w), content, seed = draw(sides), draw(contents), draw(seeds)
    rgb = scene(h, w, content, seed)
    a: np.ndarray = rgb
    if kind.startswith("grey"):
        a = rgb.mean(axis=2).astype(np.uint8)
    if kind.startswith("rgba"):
        alpha = np.random.default_rng(seed).integers(0, 256, (h, w, 1), dtype=np.uint8)
        a = np.concatenate([rgb, alpha], axis=2)
    if kind.endswith("16"):
        a = a.astype(np.uint16) * 257
    return BadInput(kind, ext, encode(a, ext))


@st.composite
def tiny(draw) -> BadInput:
    h = draw(st.integers(1, 40))
    w = draw(st.integers(1, MIN_IMAGE_SIDE_PX - 1 if h >= MIN_IMAGE_SIDE_PX else 40))
    channels = draw(st.sampled_from([1, 3, 4]))
    ext = draw(st.sampled_from([".png", ".bmp", ".tif"] if channels != 4 else [".png", ".tif"]))
    a = np.random.default_rng(draw(seeds)).integers(0, 256, (h, w, channels), dtype=np.uint8)
    return BadInput(
        "tiny", ext, encode(a[:, :, 0] if channels == 1 else a, ext), frozenset({"bad_image"})
    )


@st.composite
def off_the_rectangle(draw) -> BadInput:
    h = draw(st.integers(MIN_IMAGE_SIDE_PX, 48))
    w = draw(st.integers(MIN_IMAGE_SIDE_PX, RECT[0] + RECT[2] - 1))
    rgb = scene(h, w, draw(contents), draw(seeds))
    return BadInput("rect_off_image", ".png", encode(rgb, ".png"), frozenset({"bad_rect"}))


@st.composite
def no_wheel(draw) -> BadInput:
    """All soil, noise, flat colours, or a wheel that the rectangle misses."""
    content = draw(st.sampled_from(["noise", "black", "white", "soil", "wheel_elsewhere"]))
    (h, w), seed = draw(sides), draw(seeds)
    ext = draw(st.sampled_from([".png", ".jpg", ".bmp"]))
    return BadInput(f"no_wheel_{content}", ext, encode(scene(h, w, content, seed), ext))


@st.composite
def crashing(draw) -> BadInput:
    """A plain frame on which the fake soft method raises (the real methods measure it)."""
    (h, w), seed = draw(sides), draw(seeds)
    rgb = scene(h, w, draw(contents), seed)
    rgb[0, 0] = CRASH_PIXEL
    return BadInput("estimator_crash", ".png", encode(rgb, ".png"))


@st.composite
def broken_video(draw) -> BadInput:
    ext = draw(st.sampled_from([".mp4", ".avi"]))
    data = small_video(ext)
    choice = draw(st.sampled_from(["truncated", "garbage"]))
    if choice == "garbage":
        return BadInput(
            "video_garbage", ext, draw(st.binary(min_size=1, max_size=300)), UNREADABLE, video=True
        )
    cut = draw(st.integers(1, len(data) - 1))
    return BadInput("video_truncated", ext, data[:cut], video=True)


KINDS = {
    "zero_byte": zero_byte(),
    "truncated": truncated_image(),
    "not_an_image": not_an_image(),
    **{kind: odd_pixels((kind,)) for kind in ODD_PIXELS},
    "tiny": tiny(),
    "rect_off_image": off_the_rectangle(),
    "no_wheel": no_wheel(),
    "estimator_crash": crashing(),
    "broken_video": broken_video(),
}
bad_inputs = st.one_of(*KINDS.values())


# --- the fake soft method ------------------------------------------------------------------------


def fake_soft(images, rig, names):
    if any(tuple(int(v) for v in im[0, 0]) == CRASH_PIXEL for im in images):
        raise RuntimeError("fake estimator crash")
    return [
        FrameResult(image=n, status="ok", sinkage_mm=float(im.mean()) / 10, sinkage_std_mm=0.1)
        for im, n in zip(images, names, strict=True)
    ]


# --- checking one run --------------------------------------------------------------------------


def run_cli(args: list[str]) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main(args)
    return code, err.getvalue()


def check_rows(
    rows: list[dict[str, str]], paths: list[str], inputs: list[BadInput | None], method: str
) -> None:
    """Rows match inputs one to one (videos: one or more), in order, each with its reason."""
    i = 0
    for path, bad in zip(paths, inputs, strict=True):
        if bad is not None and bad.video:
            mine = []
            while i < len(rows) and rows[i]["image"].split("#")[0] == path:
                mine.append(rows[i])
                i += 1
            assert mine, f"no row for {path}"
            assert len(mine) == 1 or all("#" in r["image"] for r in mine)
        else:
            assert i < len(rows) and rows[i]["image"] == path, f"row for {path} missing"
            mine = [rows[i]]
            i += 1
        for row in mine:
            status, message = row["status"], row["message"]
            assert status in KNOWN | {"error"}, row
            if status != "ok":
                assert message.strip(), f"{status} without a message: {row}"
            kind = "good" if bad is None else bad.kind
            if kind == "estimator_crash" and method == "fake-soft":
                assert status == "error" and "fake estimator crash" in message, row
                continue
            assert status != "error", f"the {method} method raised on {kind}: {message}"
            if bad is not None and bad.expect is not None:
                assert status in bad.expect, (kind, row)
            if status == "bad_image" and kind == "tiny":
                assert f"at least {MIN_IMAGE_SIDE_PX}x{MIN_IMAGE_SIDE_PX}" in message
    assert i == len(rows), f"extra rows: {rows[i:]}"


@pytest.fixture(scope="module")
def good_png() -> bytes:
    return encode(scene(40, 60, "wheel", 7), ".png")


@pytest.mark.parametrize("method", ["classic", "fake-soft"])
def test_bad_files_each_get_a_row_and_a_reason(method, good_png):
    """>= 200 bad inputs per method, mixed with good frames, through the real classic method or
    a fake soft one (batching, and a frame that crashes it): never a crash, never a lost row.

    Every kind leads a few runs of its own (random draws alone would starve some kinds).
    """
    seen: Counter[str] = Counter()
    led: Counter[str] = Counter()
    runs: Counter[str] = Counter()
    for name, lead_strategy in KINDS.items():

        @settings(FUZZ, max_examples=8)
        @given(
            lead=lead_strategy,
            others=st.lists(st.one_of(bad_inputs, st.none()), min_size=1, max_size=5),
            position=st.integers(0, 5),
            batch_size=st.integers(1, 4),
        )
        def run(lead: BadInput, others: list, position: int, batch_size: int) -> None:
            batch: list[BadInput | None] = list(others)
            batch.insert(min(position, len(batch)), lead)
            with tempfile.TemporaryDirectory() as d:
                paths = []
                for k, bad in enumerate(batch):
                    path = os.path.join(d, f"in_{k:02d}{bad.suffix if bad else '.png'}")
                    Path(path).write_bytes(bad.data if bad else good_png)
                    paths.append(path)
                out = os.path.join(d, "results.csv")
                args = ["estimate", *paths, *RIG_FLAGS, "--out", out]
                args += ["--batch-size", str(batch_size)]
                args += ["--method", "soft" if method == "fake-soft" else method]
                with mock.patch.dict(_pipeline._LOADERS, {"soft": lambda *_: fake_soft}):
                    code, err = run_cli(args)
                if code != 0:
                    assert code == 2, err
                    assert err.count("error:") == 1 and (
                        "could be read" in err or "lies off every image" in err
                    ), err
                with open(out, newline="") as f:
                    reader = csv.DictReader(f)
                    assert tuple(reader.fieldnames or ()) == COLUMNS
                    rows = list(reader)
            check_rows(rows, paths, batch, method)
            seen.update(bad.kind for bad in batch if bad is not None)
            runs["this kind"] += 1

        run()
        led[name] = runs.pop("this kind", 0)
    print(f"{method}: {sum(seen.values())} bad inputs, {dict(sorted(seen.items()))}")
    assert sum(seen.values()) >= 200, seen
    assert all(led[name] >= 6 for name in KINDS), led


# --- bad rigs and bad arguments: one clear error, before any work ------------------------------

FIELDS = {
    "wheel_radius_mm": ["-3.0", "0", "0.0", '"140"', "true", "nan", "inf", "-inf", "[140.0]"],
    "confidence_rect": [
        "[1, 2, 3]",
        "[1, 2, 3, 4, 5]",
        "[1.5, 2, 3, 4]",
        "[-1, 2, 3, 4]",
        "[1, 2, 0, 4]",
        '"1,2,3,4"',
        "[[1, 2], [3, 4]]",
        "[true, 2, 3, 4]",
        "7",
    ],
    "travel": ['"up"', "1", '"Right"', "[]"],
}
SEGMENTATION_BREAKS = [
    "[segmentation]\nbogus = 1.0",
    '[segmentation]\np_d_hue = "low"',
    "[segmentation]\np_d_hue = 1.5",
    "[segmentation]\ntemperature_sat = -1.0",
    "[segmentation]\np_a_sat = nan",
    "segmentation = 3",
]
VALID = {"wheel_radius_mm": "140.0", "confidence_rect": "[20, 10, 8, 8]", "travel": '"right"'}


@st.composite
def bad_rigs(draw) -> tuple[str, set[str]]:
    """TOML text of a rig with 1-3 things wrong, and the words a good message may name."""
    fields = dict(VALID)
    named: set[str] = set()
    breaks = draw(
        st.lists(
            st.sampled_from([*FIELDS, "missing", "segmentation", "syntax"]),
            min_size=1,
            max_size=3,
            unique=True,
        )
    )
    tail = ""
    for b in breaks:
        if b in FIELDS:
            fields[b] = draw(st.sampled_from(FIELDS[b]))
            named.add(b)
        elif b == "missing":
            gone = draw(st.sampled_from(["wheel_radius_mm", "confidence_rect"]))
            fields.pop(gone)
            named.add(gone)
        elif b == "segmentation":
            tail = draw(st.sampled_from(SEGMENTATION_BREAKS))
            named.add("segmentation")
    text = "".join(f"{k} = {v}\n" for k, v in fields.items()) + tail + "\n"
    if "syntax" in breaks:
        text = text.replace(" = ", " == ", 1)
        named.add("TOML")
    return text, named


def test_bad_rigs_fail_once_before_any_work():
    seen = Counter()
    calls: list[str] = []

    def spy(images, rig, names):
        calls.extend(names)
        return fake_soft(images, rig, names)

    @settings(FUZZ, max_examples=80)
    @given(rig=bad_rigs(), via=st.sampled_from(["--rig", "directory"]))
    def run(rig: tuple[str, set[str]], via: str) -> None:
        text, named = rig
        with tempfile.TemporaryDirectory() as d:
            rec = Path(d, "rec")
            rec.mkdir()
            (rec / "a.png").write_bytes(encode(scene(40, 60, "wheel", 1), ".png"))
            (rec / "rig.toml").write_text(text)
            out = Path(d, "results.csv")
            target = (
                ["--rig", str(rec / "rig.toml"), str(rec / "a.png")]
                if via == "--rig"
                else [str(rec)]
            )
            with mock.patch.dict(_pipeline._LOADERS, {"soft": lambda *_: spy}):
                code, err = run_cli(["estimate", *target, "--out", str(out)])
            assert code == 2, (text, err)
            errors = [line for line in err.splitlines() if "error:" in line]
            assert len(errors) == 1 and errors[0].startswith("sinkjax estimate: error: "), err
            assert any(word in err for word in named), (text, err)
            assert not out.exists() and not calls, "work was done before the rig was checked"
        seen["rig"] += 1

    run()
    assert seen["rig"] >= 50


BAD_ARGS = [
    (["--confidence-rect", "1,2,3"], "four integers"),
    (["--confidence-rect", "a,b,c,d"], "four integers"),
    (["--confidence-rect=-1,0,5,5"], "x, y >= 0"),
    (["--confidence-rect", "0,0,0,5"], "w, h >= 1"),
    (["--wheel-radius-mm", "-3"], "positive"),
    (["--wheel-radius-mm", "0"], "positive"),
    (["--wheel-radius-mm", "nan"], "positive"),
    (["--wheel-radius-mm", "inf"], "positive"),
    (["--batch-size", "0"], "--batch-size"),
    (["--start", "-1"], "--start"),
    (["--stride", "0"], "--stride"),
    (["--stop", "0"], "--stop"),
    (["--overlay-video", "x.gif"], "--overlay-video"),
    (["--smooth", "--process-std-deg", "nan"], "--process-std-deg"),
    (["--smooth", "--measurement-std-mm", "0"], "--measurement-std-mm"),
    (["--rig", "missing.toml"], "does not exist"),
    (["--PATH", "missing.png"], "does not exist"),
    (["--PATH", "emptydir"], "no images or videos"),
    (["--PATH", "rig.toml"], "--rig"),
    (["--PATH", "notes.txt"], "neither an image"),
    # No flags: a.png's folder has an incomplete rig.toml, which applies to it (conventions §2).
    (["--NORIG"], "rig.toml: missing confidence_rect"),
]


@pytest.mark.parametrize("extra, needle", BAD_ARGS)
def test_bad_arguments_fail_once_before_any_work(tmp_path, monkeypatch, extra, needle):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "a.png").write_bytes(encode(scene(40, 60, "wheel", 1), ".png"))
    (tmp_path / "emptydir").mkdir()
    (tmp_path / "rig.toml").write_text("wheel_radius_mm = 140.0\n")
    (tmp_path / "notes.txt").write_text("hello")
    paths = ["a.png"]
    rig = RIG_FLAGS
    if extra and extra[0] == "--PATH":
        paths, extra = [extra[1]], []
    elif extra == ["--NORIG"]:
        rig, extra = [], []
    calls: list[str] = []
    spy = lambda images, rig, names: calls.extend(names) or fake_soft(images, rig, names)
    with mock.patch.dict(_pipeline._LOADERS, {"soft": lambda *_: spy}):
        code, err = run_cli(["estimate", *paths, *rig, *extra])
    assert code == 2 and needle in err, err
    errors = [line for line in err.splitlines() if "error:" in line]
    assert len(errors) == 1 and errors[0].startswith("sinkjax estimate: error: "), err
    assert "Traceback" not in err
    assert not (tmp_path / "results.csv").exists() and not calls


# --- the real soft estimator on awkward frames (subprocess: float32, compiled once) ------------


def _soft_cases() -> list[tuple[str, bytes, set[str]]]:
    """~20 awkward inputs; every readable, big-enough frame is 48x64 so one compile serves all."""
    h, w = 48, 64
    rgb = scene(h, w, "wheel", 3)
    measured = {"ok", "no_contact", "no_wheel", "fit_failed", "implausible"}
    cases: list[tuple[str, bytes, set[str]]] = [
        ("zero.png", b"", {"unreadable"}),
        ("text.jpg", b"hello, not a jpeg", {"unreadable"}),
        ("trunc.png", encode(rgb, ".png")[:100], {"unreadable"}),
        ("tiny_1x1.png", encode(rgb[:1, :1], ".png"), {"bad_image"}),
        ("tiny_5x3.png", encode(rgb[:3, :5], ".png"), {"bad_image"}),
        ("tiny_15x40.png", encode(rgb[:40, :15], ".png"), {"bad_image"}),
        ("rect_off_20x20.png", encode(rgb[:20, :20], ".png"), {"bad_rect"}),
        ("grey8.png", encode(rgb.mean(axis=2).astype(np.uint8), ".png"), measured),
        ("grey16.png", encode(rgb.mean(axis=2).astype(np.uint16) * 257, ".png"), measured),
        ("rgb16.png", encode(rgb.astype(np.uint16) * 257, ".png"), measured),
        ("rgba.png", encode(np.dstack([rgb, np.full((h, w), 128, np.uint8)]), ".png"), measured),
        ("wheel.jpg", encode(rgb, ".jpg"), measured),
    ]
    for content in ("noise", "black", "white", "soil", "wheel_elsewhere"):
        for seed in (1, 2) if content in ("noise", "soil") else (1,):
            cases.append(
                (f"{content}_{seed}.png", encode(scene(h, w, content, seed), ".png"), measured)
            )
    cases.append(("video.mp4", small_video(".mp4")[:600], {"unreadable"} | measured))
    return cases


SOFT_CASES = _soft_cases()


@pytest.mark.heavy
@pytest.mark.slow
def test_real_soft_estimator_on_awkward_frames(tmp_path):
    paths = []
    for name, data, _ in SOFT_CASES:
        (tmp_path / name).write_bytes(data)
        paths.append(str(tmp_path / name))
    out = tmp_path / "results.csv"
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "sinkjax.app.cli",
            "estimate",
            *paths,
            *RIG_FLAGS,
            "--method",
            "soft",
            "--batch-size",
            "1",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    with open(out, newline="") as f:
        rows = list(csv.DictReader(f))
    by_path: dict[str, list[dict[str, str]]] = {}
    for row in rows:
        by_path.setdefault(row["image"].split("#")[0], []).append(row)
    assert list(by_path) == paths  # every input, in order
    for (name, _, allowed), path in zip(SOFT_CASES, paths, strict=True):
        for row in by_path[path]:
            assert row["status"] in allowed, (name, row)
            assert row["status"] == "ok" or row["message"].strip(), (name, row)
            for col in ("sinkage_mm", "sinkage_std_mm", "theta1_deg", "theta2_deg"):
                assert row[col] == "" or math.isfinite(float(row[col])), (name, row)
    assert len(SOFT_CASES) >= 18
