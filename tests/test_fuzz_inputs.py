"""Bad input, crafted: lying headers, corrupt JPEGs, odd names, broken rigs, labels, resume files,
outputs that would overwrite something, garbage for every subcommand (issue 17).

Every file is made by the tests (no committed binaries). The CLI runs use a fast fake method
(its number is the frame's mean pixel) or the classic one, so they take seconds; what is checked
is the contract: one row per input, in order, with the status and the words that say why; good
rows the same as in a run without the bad files; exit codes; files refused are left byte for
byte as they were. Property-based tests (hypothesis) drive the parsers with random and mutated
bytes.
"""

from __future__ import annotations

import csv
import io
import math
import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path
from unittest import mock

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from sinkjax.app import image_file, pipeline as _pipeline
from sinkjax.app.cli import main
from sinkjax.app.image_file import BadImageError, read_image
from sinkjax.app.results import COLUMNS, ResultsWriter
from sinkjax.app.resume import ResumeError, prepare_resume
from sinkjax.app.smoothing import NotAResultsCsv, read_results
from sinkjax.calibration.labels import LabelError, read_labels
from sinkjax.result import FrameResult
from sinkjax.rig import RigError, rig_from_dict, rig_to_toml

FUZZ = settings(
    derandomize=True,
    database=None,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
RIG = ["--wheel-radius-mm", "100", "--confidence-rect", "20,10,8,8"]


# --- crafted files -----------------------------------------------------------------------------


def encode(rgb: np.ndarray, ext: str) -> bytes:
    ok, buf = cv2.imencode(ext, np.ascontiguousarray(rgb[..., ::-1]) if rgb.ndim == 3 else rgb)
    assert ok
    return buf.tobytes()


def picture(h: int = 40, w: int = 60, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rgb = np.clip(np.array([150, 120, 70]) + rng.normal(0, 6, (h, w, 3)), 0, 255).astype(np.uint8)
    cv2.circle(rgb, (24, 14), 12, (60, 60, 200), -1)
    return rgb


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def png_bomb(width: int = 12000, height: int = 12000) -> bytes:
    """A small, valid PNG whose picture is huge: all-zero rows compress ~1000:1."""
    rows = zlib.compressobj(9)
    body = b"".join(rows.compress(b"\x00" * (1 + 3 * width)) for _ in range(height // 8))
    body += rows.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", body) + _chunk(b"IEND", b"")
    )


def jpeg_claiming(width: int, height: int) -> bytes:
    """A real JPEG whose frame header (SOF0) is rewritten to claim ``width`` x ``height``."""
    data = bytearray(encode(picture(), ".jpg"))
    sof = data.find(b"\xff\xc0")
    data[sof + 5 : sof + 9] = struct.pack(">HH", height, width)
    return bytes(data)


def bmp_claiming(width: int, height: int) -> bytes:
    data = bytearray(encode(picture(), ".bmp"))
    data[18:26] = struct.pack("<ii", width, height)
    return bytes(data)


def tiff_claiming(width: int, height: int, order: str = "<") -> bytes:
    """A minimal TIFF header: one IFD with ImageWidth and ImageLength (LONG), nothing else."""
    magic = b"II*\x00" if order == "<" else b"MM\x00*"
    entries = struct.pack(order + "HHII", 256, 4, 1, width) + struct.pack(
        order + "HHII", 257, 4, 1, height
    )
    return magic + struct.pack(order + "I", 8) + struct.pack(order + "H", 2) + entries + b"\0" * 64


def corrupt_jpeg_scan() -> bytes:
    """Scan data cut in half, then an end marker: libjpeg decodes it, saying "Corrupt JPEG"."""
    data = encode(picture(), ".jpg")
    sos = data.find(b"\xff\xda")
    return data[: sos + (len(data) - sos) // 2] + b"\xff\xd9"


def corrupt_jpeg_extraneous() -> bytes:
    """Junk before the end marker: "Corrupt JPEG data: N extraneous bytes before marker 0xd9"."""
    data = encode(np.full((120, 160, 3), 100, np.uint8), ".jpg")
    return data[:-2] + b"\x00\x11\x22\xff\xd9"


# (name, bytes, exception, words in its message): read_image refuses each, from the header where
# the header lies (the decoder is never called for those: see the test).
REFUSED = [
    ("bomb.png", png_bomb(), BadImageError, "claims 12000x12000 px"),
    ("wide_bomb.png", png_bomb(200000, 800), BadImageError, "claims 200000x800 px"),
    ("bomb.jpg", jpeg_claiming(12000, 12000), BadImageError, "JPEG header claims 12000x12000"),
    ("bomb.bmp", bmp_claiming(20000, 20000), BadImageError, "BMP header claims 20000x20000"),
    ("topdown_bomb.bmp", bmp_claiming(20000, -20000), BadImageError, "20000x20000"),
    ("bomb_le.tif", tiff_claiming(30000, 30000), BadImageError, "TIFF header claims 30000x30000"),
    ("bomb_be.tif", tiff_claiming(30000, 30000, ">"), BadImageError, "30000x30000"),
    ("corrupt_scan.jpg", corrupt_jpeg_scan(), ValueError, "Corrupt JPEG data"),
    ("extraneous.jpg", corrupt_jpeg_extraneous(), ValueError, "extraneous bytes"),
    ("no_ihdr.png", b"\x89PNG\r\n\x1a\n" + b"\0" * 40, ValueError, "header gives no image size"),
    ("sos_first.jpg", b"\xff\xd8\xff\xda\x00\x02" + b"\0" * 50, ValueError, "no image size"),
    ("ifd_past_end.tif", b"II*\x00" + struct.pack("<I", 99999), ValueError, "no image size"),
    ("bmp_header_only.bmp", b"BM" + b"\0" * 10, ValueError, "no image size"),
    ("empty.png", b"", ValueError, "empty file"),
    ("text.jpg", b"just some text\n", ValueError, "not an image"),
    ("cut.png", encode(picture(), ".png")[:200], ValueError, "truncated PNG"),
    ("cut.jpg", encode(picture(), ".jpg")[:300], ValueError, "truncated JPEG"),
]


@pytest.mark.parametrize("name, data, error, words", REFUSED, ids=[r[0] for r in REFUSED])
def test_read_image_refuses_from_the_header(tmp_path, name, data, error, words):
    path = tmp_path / name
    path.write_bytes(data)
    lying = error is BadImageError
    real = cv2.imdecode
    with mock.patch.object(
        image_file.cv2, "imdecode", side_effect=AssertionError("decoded") if lying else real
    ):
        with pytest.raises(error, match=words):
            read_image(path)
        if lying:
            with pytest.raises(error, match="megapixels"):
                read_image(path)


def test_bomb_is_small_and_its_limits_are_pillows(tmp_path):
    assert len(png_bomb()) < 64_000  # the "48 KB file claiming 12000x12000 px"
    assert image_file.MAX_PIXELS == 89_478_485 and image_file.MAX_FILE_BYTES == 1 << 30
    # At the limit it is read; one pixel over, refused.
    path = tmp_path / "edge.png"
    path.write_bytes(encode(picture(10, 30), ".png"))
    with mock.patch.object(image_file, "MAX_PIXELS", 300):
        assert read_image(path).shape == (10, 30, 3)
    with mock.patch.object(image_file, "MAX_PIXELS", 299), pytest.raises(BadImageError):
        read_image(path)


def test_file_over_the_size_limit_is_not_read(tmp_path):
    path = tmp_path / "huge.png"
    with open(path, "wb") as f:  # sparse: 1 GiB + 1 byte on disk costs nothing
        f.write(encode(picture(), ".png")[:64])
        f.truncate(image_file.MAX_FILE_BYTES + 1)
    with mock.patch.object(Path, "read_bytes", side_effect=AssertionError("read it all")):
        with pytest.raises(BadImageError, match=r"file too large: 1073741825 bytes"):
            read_image(path)


def test_good_images_still_read_exactly(tmp_path):
    rgb = picture(33, 47, seed=3)
    for ext in (".png", ".bmp", ".tif"):
        (tmp_path / f"a{ext}").write_bytes(encode(rgb, ext))
        np.testing.assert_array_equal(read_image(tmp_path / f"a{ext}"), rgb)
    data = encode(rgb, ".jpg")
    (tmp_path / "a.jpg").write_bytes(data)
    reference = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    np.testing.assert_array_equal(read_image(tmp_path / "a.jpg"), reference)


# --- the image reader on random and mutated bytes ----------------------------------------------

SEEDS = {ext: encode(picture(24, 32, seed=1), ext) for ext in (".png", ".jpg", ".bmp", ".tif")}


@st.composite
def mutated(draw) -> tuple[str, bytes]:
    ext = draw(st.sampled_from(sorted(SEEDS)))
    data = bytearray(SEEDS[ext])
    for _ in range(draw(st.integers(1, 4))):
        how = draw(st.sampled_from(["flip", "cut", "insert", "delete", "header"]))
        i = draw(st.integers(0, max(0, len(data) - 1)))
        if how == "flip" and data:
            data[i] ^= draw(st.integers(1, 255))
        elif how == "cut":
            del data[i:]
        elif how == "insert":
            data[i:i] = draw(st.binary(min_size=1, max_size=16))
        elif how == "delete":
            del data[i : i + draw(st.integers(1, 16))]
        else:  # a lie in the first 32 bytes, where the sizes are
            j = draw(st.integers(0, 31))
            data[j : j + 4] = draw(st.binary(min_size=4, max_size=4))
    return ext, bytes(data)


random_files = st.one_of(
    mutated(), st.tuples(st.sampled_from(sorted(SEEDS)), st.binary(max_size=400))
)


@settings(FUZZ, max_examples=150)
@given(case=random_files)
def test_read_image_on_random_and_mutated_bytes(tmp_path, case):
    ext, data = case
    path = tmp_path / f"x{ext}"
    path.write_bytes(data)
    try:
        image = read_image(path)
    except ValueError as e:  # BadImageError included
        assert str(e).strip()
        return
    assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
    assert image.shape[0] * image.shape[1] <= image_file.MAX_PIXELS


# --- the rig parser --------------------------------------------------------------------------

toml_values = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**6), 10**6),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    st.lists(st.integers(-5, 500), max_size=5),
    st.lists(st.floats(allow_nan=True), max_size=4),
)
keys = st.sampled_from(
    ["wheel_radius_mm", "confidence_rect", "travel", "rim_radius_px", "segmentation", "travle"]
)


@settings(FUZZ, max_examples=200)
@given(data=st.dictionaries(keys, toml_values, max_size=6))
def test_rig_parser_raises_only_rig_errors(data):
    data = {k: v for k, v in data.items() if v is not None}
    try:
        rig = rig_from_dict(data, source="fuzz.toml")
    except RigError as e:
        assert str(e).startswith("fuzz.toml: ")
        return
    # Accepted: every field usable, and it round-trips through the file format.
    assert 0 < rig.wheel_radius_mm <= 1e5 and rig.travel in ("right", "left")
    assert rig.rim_radius_px is None or 4 <= rig.rim_radius_px <= 1e5
    import tomllib

    again = rig_from_dict(tomllib.loads(rig_to_toml(rig)))
    assert again.rim_radius_px == rig.rim_radius_px and again.confidence_rect == rig.confidence_rect


VALID_RIG = 'wheel_radius_mm = 140.0\nconfidence_rect = [20, 10, 8, 8]\ntravel = "right"\n'
BAD_RIGS = [
    ("wheel_radius_mm = 1.7e308", "wheel_radius_mm = 1.7e+308 is more than 100000 mm"),
    ("wheel_radius_mm = 100001.0", "more than 100000 mm"),
    ("rim_radius_px = 0", "rim_radius_px must be a number of pixels"),
    ("rim_radius_px = -50", "rim_radius_px must be"),
    ("rim_radius_px = nan", "rim_radius_px must be"),
    ("rim_radius_px = inf", "rim_radius_px must be"),
    ("rim_radius_px = true", "rim_radius_px must be"),
    ('rim_radius_px = "60"', "rim_radius_px must be"),
    ("rim_radius_px = [50, 70]", "rim_radius_px must be"),
    ("rim_radius_px = 3.5", "from 4 to"),
    ("rim_radius_px = 1e9", "from 4 to 100000"),
    ("rim_radius = 60", "did you mean 'rim_radius_px'"),
    ("wheel_radius = 60", "did you mean 'wheel_radius_mm'"),
]


@pytest.mark.parametrize("line, words", BAD_RIGS)
def test_bad_rig_lines_stop_the_run_before_work(tmp_path, line, words):
    key = line.split(" = ")[0]
    text = "".join(row + "\n" for row in VALID_RIG.splitlines() if not row.startswith(key + " "))
    (tmp_path / "rig.toml").write_text(text + line + "\n")
    (tmp_path / "a.png").write_bytes(encode(picture(), ".png"))
    out = tmp_path / "r.csv"
    code, err, calls = run(["estimate", str(tmp_path), "--out", str(out)])
    assert code == 2 and words in err and "Traceback" not in err, err
    assert not out.exists() and not calls


# --- the CLI on a corpus of crafted bad files ----------------------------------------------------


def fake(calls: list[str]):
    def method(images, rig, names):
        calls.extend(names)
        return [
            FrameResult(image=n, status="ok", sinkage_mm=float(im.mean()) / 10, theta1_deg=1.0)
            for im, n in zip(images, names, strict=True)
        ]

    return method


def run(args: list[str], method=None) -> tuple[int, str, list[str]]:
    calls: list[str] = []
    err = io.StringIO()
    loader = (lambda *_: method) if method is not None else (lambda *_: fake(calls))
    with (
        mock.patch.dict(_pipeline._LOADERS, {"soft": loader}),
        mock.patch("sys.stderr", err),
        mock.patch("sys.stdout", io.StringIO()),
    ):
        code = main(args)
    return code, err.getvalue(), calls


def rows_of(path: Path) -> list[list[bytes]]:
    return [line.split(b",") for line in path.read_bytes().splitlines()[1:]]


def dict_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="", encoding="utf-8", errors="surrogateescape") as f:
        return list(csv.DictReader(f))


# In one folder with good frames: (file name, bytes or None for a dangling link, status, words).
CORPUS = [
    *[(name, data, "bad_image", "megapixels") for name, data, err, _ in REFUSED[:7]],
    ("corrupt_scan.jpg", corrupt_jpeg_scan(), "unreadable", "Corrupt JPEG data"),
    ("extraneous.jpg", corrupt_jpeg_extraneous(), "unreadable", "extraneous bytes"),
    ("dangling.png", None, "unreadable", "broken symbolic link"),
    ("no_ihdr.png", REFUSED[9][1], "unreadable", "no image size"),
    ("zero.bmp", b"", "unreadable", "empty file"),
    ("text.tif", b"II*\x00 not really", "unreadable", ""),
    ("tiny.png", encode(picture(5, 7), ".png"), "bad_image", "at least 16x16"),
]
NAMES = ["plain.png", "with space.png", "comma,name.png", 'quote"s.png', "ünïcode.png", "nl\nx.png"]


def test_cli_corpus_one_row_each_good_rows_unchanged(tmp_path):
    good_dir, mixed = tmp_path / "good", tmp_path / "mixed"
    good_dir.mkdir()
    mixed.mkdir()
    for k, name in enumerate(NAMES):
        for d in (good_dir, mixed):
            (d / f"g{k}_{name}").write_bytes(encode(picture(seed=k), ".png"))
    raw = os.fsencode(mixed) + b"/g9_\xff\xfe.png"  # not UTF-8: written with surrogate escapes
    for target in (raw, os.fsencode(good_dir) + b"/g9_\xff\xfe.png"):
        with open(target, "wb") as f:
            f.write(encode(picture(seed=9), ".png"))
    for name, data, _, _ in CORPUS:
        if data is None:
            os.symlink(mixed / "gone.png", mixed / f"b_{name}")
        else:
            (mixed / f"b_{name}").write_bytes(data)
    code, err, _ = run(["estimate", str(good_dir), *RIG, "--out", str(tmp_path / "g.csv")])
    assert code == 0, err
    code, err, calls = run(["estimate", str(mixed), *RIG, "--out", str(tmp_path / "m.csv")])
    assert code == 0 and "Traceback" not in err, err
    rows = dict_rows(tmp_path / "m.csv")
    files = sorted(os.listdir(mixed))
    assert [Path(r["image"]).name for r in rows] == files  # one row each, in name order
    by_name = {Path(r["image"]).name: r for r in rows}
    for name, _, status, words in CORPUS:
        row = by_name[f"b_{name}"]
        assert row["status"] == status and words in row["message"], row
        assert row["sinkage_mm"] == "" and f"b_{name}" not in " ".join(calls)
    good = {Path(r["image"]).name: r for r in dict_rows(tmp_path / "g.csv")}
    assert len(good) == len(NAMES) + 1
    for name, row in good.items():
        mine = dict(by_name[name])
        assert mine.pop("image") != row.pop("image") and mine == row  # same numbers


def test_broken_link_given_directly_is_a_clear_error(tmp_path):
    os.symlink(tmp_path / "nowhere.png", tmp_path / "a.png")
    code, err, _ = run(["estimate", str(tmp_path / "a.png"), *RIG, "--out", str(tmp_path / "r")])
    assert code == 2 and "broken symbolic link" in err


def test_broken_video_rows(tmp_path):
    (tmp_path / "v.mp4").write_bytes(b"\0\0\0\x18ftypmp42" + os.urandom(200))
    (tmp_path / "a.png").write_bytes(encode(picture(), ".png"))
    out = tmp_path / "r.csv"
    code, err, _ = run(["estimate", str(tmp_path / "v.mp4"), str(tmp_path / "a.png"), *RIG,
                        "--out", str(out)])  # fmt: skip
    assert code == 0, err
    rows = dict_rows(out)
    assert [r["status"] for r in rows] == ["unreadable", "ok"] and "video" in rows[0]["message"]


# --- non-finite results ------------------------------------------------------------------------


@pytest.mark.parametrize(
    "values",
    [
        {"sinkage_mm": math.inf},
        {"sinkage_mm": -math.inf},
        {"sinkage_mm": math.nan},
        {"theta1_deg": math.nan},
        {"theta2_deg": math.inf},
        {"sinkage_mm": np.float32("inf")},
    ],
)
def test_non_finite_results_become_fit_failed(tmp_path, values):
    def method(images, rig, names):
        base = {"sinkage_mm": 1.0, "theta1_deg": 2.0, "theta2_deg": 3.0}
        return [FrameResult(image=n, status="ok", **(base | values)) for n in names]

    (tmp_path / "a.png").write_bytes(encode(picture(), ".png"))
    (tmp_path / "b.png").write_bytes(encode(picture(seed=2), ".png"))
    out = tmp_path / "r.csv"
    code, err, _ = run(["estimate", str(tmp_path), *RIG, "--out", str(out)], method=method)
    assert code == 0, err
    for row in dict_rows(out):
        assert row["status"] == "fit_failed" and "non-finite result" in row["message"], row
        assert next(iter(values)) in row["message"]


def test_no_contact_with_finite_numbers_stays(tmp_path):
    def method(images, rig, names):
        return [FrameResult(image=n, status="no_contact", sinkage_mm=0.0) for n in names]

    (tmp_path / "a.png").write_bytes(encode(picture(), ".png"))
    out = tmp_path / "r.csv"
    assert run(["estimate", str(tmp_path), *RIG, "--out", str(out)], method=method)[0] == 0
    assert dict_rows(out)[0]["status"] == "no_contact"


# --- labels ----------------------------------------------------------------------------------

BAD_LABEL_CELLS = ["inf", "-inf", "nan", "NaN", "1e999", "Infinity", "-181", "181", "12 mm", "1,5"]


@pytest.mark.parametrize("cell", BAD_LABEL_CELLS)
def test_label_cells_that_are_not_finite_in_range_are_refused(tmp_path, cell):
    (tmp_path / "a.png").write_bytes(encode(picture(), ".png"))
    path = tmp_path / "LABELS.csv"
    path.write_text(f'image,sinkage_mm,theta1_deg,theta2_deg\na.png,1.0,"{cell}",3\n')
    with pytest.raises(LabelError, match=r"row 2, column theta1_deg"):
        read_labels(path)


@settings(FUZZ, max_examples=120)
@given(text=st.text(max_size=200), raw=st.binary(max_size=200))
def test_labels_parser_raises_only_label_errors(tmp_path, text, raw):
    (tmp_path / "a.png").write_bytes(encode(picture(), ".png"))
    for content in (
        ("image,sinkage_mm,theta1_deg,theta2_deg\n" + text).encode("utf-8", "surrogatepass"),
        raw,
    ):
        path = tmp_path / "LABELS.csv"
        path.write_bytes(content)
        try:
            frames = read_labels(path)
        except LabelError as e:
            assert str(e).strip()
            continue
        assert np.isfinite(frames.targets).any()
        assert not np.isinf(frames.targets).any()


# --- resume: continue exactly, or leave the file as it was ---------------------------------------

HEADER = ",".join(COLUMNS)
NOT_RESULTS = [
    b"just one line without a newline",
    b"image,status",
    b"a,b,c\n1,2,3\n4,5",
    b"\x89PNG\r\n\x1a\n\x00\x00binary",
    os.urandom(300).replace(b"\n", b"\r"),
    b"image;status;sinkage_mm\nx;ok;1\n",
    HEADER.encode()[:-8] + b"\nrow,ok\n",
    b"\xef\xbb\xbf" + HEADER.encode() + b"\nx,ok\n",  # a BOM: not what sinkjax writes
    b"\n" + HEADER.encode() + b"\n",
]


@pytest.mark.parametrize("content", NOT_RESULTS)
def test_resume_onto_a_file_that_is_not_results_leaves_it_unchanged(tmp_path, content):
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "a.png").write_bytes(encode(picture(), ".png"))
    out = tmp_path / "notes.csv"
    out.write_bytes(content)
    code, err, calls = run(["estimate", str(tmp_path / "in"), *RIG, "--out", str(out), "--resume"])
    assert code == 2 and "cannot resume into" in err and not calls, err
    assert out.read_bytes() == content


def test_resume_continues_a_killed_run_exactly(tmp_path):
    (tmp_path / "in").mkdir()
    for k in range(3):
        (tmp_path / "in" / f"f{k}.png").write_bytes(encode(picture(seed=k), ".png"))
    full = tmp_path / "full.csv"
    assert run(["estimate", str(tmp_path / "in"), *RIG, "--out", str(full)])[0] == 0
    lines = full.read_bytes().splitlines(keepends=True)
    for keep, partial in ((1, b""), (2, b"/x/f1.p"), (3, b""), (2, lines[2][:5])):
        out = tmp_path / "part.csv"
        out.write_bytes(b"".join(lines[:keep]) + partial)
        code, err, calls = run(
            ["estimate", str(tmp_path / "in"), *RIG, "--out", str(out), "--resume"]
        )
        assert code == 0, err
        assert out.read_bytes() == full.read_bytes()
        assert len(calls) == len(lines) - keep


@settings(FUZZ, max_examples=60)
@given(content=st.binary(max_size=300))
def test_resume_parser_on_random_bytes(tmp_path, content):
    path = tmp_path / "x.csv"
    path.write_bytes(content)
    try:
        done = prepare_resume(path)
    except ResumeError:
        assert path.read_bytes() == content  # refused: untouched
        return
    assert not content or content.startswith(HEADER.encode()), content
    assert isinstance(done, set)


@settings(FUZZ, max_examples=60)
@given(names=st.lists(st.text(min_size=1, max_size=12), min_size=1, max_size=5))
def test_results_round_trip_any_name(tmp_path, names):
    # Names from the file system may hold lone surrogates (undecodable bytes): written losslessly.
    names = [n.replace("\x00", "") or "x" for n in names] + ["bad\udcff.png"]
    path = tmp_path / "r.csv"
    with open(path, "w", newline="", encoding="utf-8", errors="surrogateescape") as f:
        writer = ResultsWriter(f)
        for n in names:
            writer.write(FrameResult(image=n, status="ok", sinkage_mm=1.5))
    header, rows = read_results(path)
    assert tuple(header) == COLUMNS
    assert [r["image"] for r in rows] == names
    assert prepare_resume(path) == set(names)


# --- outputs are checked before any work ---------------------------------------------------------

OUTPUTS = [
    (["--out", "{in}/a.png"], "is one of the inputs"),
    (["--out", "{in}"], "is a folder"),
    (["--out", "{file}/r.csv"], "is not a folder"),
    (["--out", "{tmp}/r.mp4", "--overlay-video", "{tmp}/r.mp4"], "both name"),
    (["--out", "{tmp}/r.csv", "--overlay-video", "{tmp}/dir.mp4"], "is a folder"),
    (["--out", "{tmp}/r.csv", "--overlay-video", "{file}/v.mp4"], "is not a folder"),
    (["--out", "{tmp}/r.csv", "--overlay", "{file}"], "is a file, not a folder"),
    (["--out", "{tmp}/r.csv", "--overlay", "{in}"], "holds input images"),
    (["--out", "{tmp}/r.csv", "--overlay", "{file}/o"], "is not a folder"),
    (["--out", "{tmp}/link/r.csv"], "broken symbolic link"),
]


@pytest.mark.parametrize("flags, words", OUTPUTS)
def test_unusable_outputs_fail_before_any_work(tmp_path, flags, words):
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "a.png").write_bytes(encode(picture(), ".png"))
    (tmp_path / "file").write_text("x")
    os.symlink(tmp_path / "missing", tmp_path / "link")
    (tmp_path / "dir.mp4").mkdir()
    before = sorted(p.name for p in tmp_path.rglob("*"))
    given = [
        f.format(tmp=tmp_path, file=tmp_path / "file", **{"in": tmp_path / "in"}) for f in flags
    ]
    code, err, calls = run(["estimate", str(tmp_path / "in"), *RIG, *given])
    assert code == 2 and words in err and not calls, err
    assert sorted(p.name for p in tmp_path.rglob("*")) == before


@pytest.mark.parametrize(
    "out, words",
    [
        ("{tmp}", "is a folder"),
        ("{tmp}/LABELS.csv", "is one of the inputs"),
        ("{tmp}/rig.toml", "is one of the inputs"),
        ("{tmp}/a.png", "is one of the inputs"),
        ("{tmp}/missing/o.toml", "does not exist"),
    ],
)
def test_calibrate_checks_out_before_work(tmp_path, out, words):
    (tmp_path / "a.png").write_bytes(encode(picture(), ".png"))
    (tmp_path / "rig.toml").write_text(VALID_RIG)
    (tmp_path / "LABELS.csv").write_text("image,sinkage_mm,theta1_deg,theta2_deg\na.png,1,2,3\n")
    before = {p: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    with mock.patch("sinkjax.calibration.cli.calibrate", side_effect=AssertionError("work")):
        code, err, _ = run(
            ["calibrate", str(tmp_path / "LABELS.csv"), "--out", out.format(tmp=tmp_path)]
        )
    assert code == 2 and words in err, err
    assert {p: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == before


# --- smooth and plot on garbage; every subcommand on garbage, in a real process -----------------

GARBAGE = [
    os.urandom(2000),
    b"\x00" * 100,
    b"image,status\n\xff\xfe,\x00ok\n",
    HEADER.encode() + b"\n" + b'"' + b"x" * 200_000 + b"\n",  # a field over csv's limit
    encode(picture(), ".png"),
]


@pytest.mark.parametrize("command", ["smooth", "plot"])
@pytest.mark.parametrize("content", GARBAGE, ids=["random", "nul", "short", "huge", "png"])
def test_smooth_and_plot_refuse_garbage_in_one_line(tmp_path, command, content):
    path = tmp_path / "r.csv"
    path.write_bytes(content)
    code, err, _ = run([command, str(path), "--out", str(tmp_path / "o.x")])
    assert code == 2 and "not a sinkjax results CSV" in err, err
    assert len(err.strip().splitlines()) == 1 and len(err) < 300
    assert path.read_bytes() == content and not (tmp_path / "o.x").exists()
    with pytest.raises(NotAResultsCsv):
        read_results(path)


def test_every_subcommand_on_garbage_prints_no_traceback(tmp_path):
    junk = tmp_path / "junk.png"
    junk.write_bytes(os.urandom(3000))
    (tmp_path / "junk.csv").write_bytes(os.urandom(3000))
    (tmp_path / "rig.toml").write_bytes(os.urandom(200))
    j, c = str(junk), str(tmp_path / "junk.csv")
    commands = [
        ["estimate", j, *RIG, "--method", "classic", "--out", str(tmp_path / "r.csv")],
        ["estimate", j, "--method", "classic"],  # the garbage rig.toml beside it
        ["calibrate", c, "--out", str(tmp_path / "o.toml")],
        ["synth", j, "--frames", "1"],
        ["synth", str(tmp_path / "junk.png" / "sub"), "--frames", "1"],
        ["demo", "--help"],
        ["smooth", c],
        ["plot", c],
        ["review", j, "--no-browser"],
        ["review", c, "--no-browser"],
        ["estimate", "--no-such-flag"],
    ]
    script = (
        "import sys, json\nfrom sinkjax.app.cli import main\n"
        "codes = []\n"
        "for argv in json.loads(sys.argv[1]):\n"
        "    try:\n        codes.append(main(argv))\n"
        "    except SystemExit as e:\n        codes.append(e.code)\n"
        "print(json.dumps(codes))\n"
    )
    import json

    proc = subprocess.run(
        [sys.executable, "-c", script, json.dumps(commands)],
        capture_output=True,
        text=True,
        timeout=240,
        cwd=tmp_path,
    )
    assert "Traceback" not in proc.stderr, proc.stderr
    codes = json.loads(proc.stdout.strip().splitlines()[-1])
    assert codes == [2, 2, 2, 2, 2, 0, 2, 2, 2, 2, 2], (codes, proc.stderr)
    errors = [line for line in proc.stderr.splitlines() if ": error: " in line]
    assert len(errors) == 10, proc.stderr


# --- the rim search follows the rig: a small wheel in a large frame -----------------------------


@pytest.fixture(scope="module")
def small_wheel_in_large_frame():
    """A 320x240 synthetic scene (rim ~72 px) drawn on a 960x720 canvas: below 0.12 of 720."""
    import dataclasses

    from sinkjax.synth.presets import random_scene
    from sinkjax.synth.raster import render
    from sinkjax.synth.recording import rig_for

    scene = random_scene(np.random.default_rng(3), width=320, height=240)
    small_image, _ = render(scene, 0)
    big = dataclasses.replace(scene, width=960, height=720)
    image, truth = render(big, 0)
    return image, rig_for(big), truth, small_image, rig_for(scene)


def test_classic_rim_search_follows_the_hint(small_wheel_in_large_frame):
    import dataclasses

    from sinkjax.classic.estimator import estimate_classic

    image, rig, truth, small_image, small_rig = small_wheel_in_large_frame
    plain = estimate_classic(image, rig, "x")
    assert plain.status == "fit_failed" and "rim radii searched: 86-540 px" in plain.message
    assert "rim_radius_px" in plain.message
    hinted = estimate_classic(image, dataclasses.replace(rig, rim_radius_px=70.0), "x")
    assert hinted.status == "ok" and abs(hinted.radius_px - truth.radius_px) < 1.0
    # The same wheel measured in its own small frame (no hint needed there) agrees.
    alone = estimate_classic(small_image, small_rig, "x")
    assert abs(hinted.sinkage_mm - alone.sinkage_mm) < 0.5
    assert abs(hinted.sinkage_mm - truth.sinkage_mm) < 2.0
    wrong = estimate_classic(image, dataclasses.replace(rig, rim_radius_px=300.0), "x")
    assert wrong.status != "ok" and "225-375 px, from the rig's rim_radius_px" in wrong.message


@pytest.mark.slow
def test_soft_rim_search_follows_the_hint_with_one_compile(small_wheel_in_large_frame):
    import dataclasses

    from sinkjax.soft import batch as soft

    image, rig, truth, _, _ = small_wheel_in_large_frame
    (plain,) = soft.estimate_batch([image], rig, ["x"])
    assert plain.status == "no_wheel" and "rim radii searched: 86-540 px" in plain.message
    before = soft._prepare_one._cache_size()
    radii = []
    for hint in (70.0, 78.0):
        (hinted,) = soft.estimate_batch(
            [image], dataclasses.replace(rig, rim_radius_px=hint), ["x"]
        )
        # The rim is found (radius below). The boundary of a small wheel high in a tall frame is
        # the documented limit (conventions §2): the plausibility check flags it, never ``ok``.
        assert hinted.status in ("ok", "no_contact", "implausible"), hinted.message
        radii.append(hinted.radius_px)
    assert soft._prepare_one._cache_size() == before + 1  # the hint is traced, not static
    assert all(abs(r - truth.radius_px) < 1.0 for r in radii)
