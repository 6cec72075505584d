"""Careless or unlucky input: odd file names, rigs with a BOM or a misspelt key, --out on input."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from sinkjax.app.cli import main
from sinkjax.rig import RigError, load_rig

FLAGS = ["--wheel-radius-mm", "100", "--confidence-rect", "1,1,4,4", "--method", "classic"]


def _png(path: Path | bytes) -> None:
    ok, buf = cv2.imencode(".png", np.full((40, 60, 3), 90, np.uint8))
    assert ok
    with open(path, "wb") as f:
        f.write(buf.tobytes())


def test_non_utf8_file_name_is_written_losslessly(tmp_path, capsys):
    raw = os.fsencode(tmp_path) + b"/bad\xff\xfename.png"
    _png(raw)
    _png(tmp_path / "good.png")
    out = tmp_path / "r.csv"
    assert main(["estimate", str(tmp_path), "--out", str(out), *FLAGS]) == 0
    data = out.read_bytes().splitlines()
    # Both frames have a row; the undecodable name comes back as the same bytes.
    assert len(data) == 3
    assert data[1].startswith(raw + b",") and data[2].startswith(os.fsencode(tmp_path / "good.png"))
    # --resume reads it back and finds nothing left to do.
    assert main(["estimate", str(tmp_path), "--out", str(out), "--resume", *FLAGS]) == 0
    assert out.read_bytes().splitlines() == data
    assert "nothing left to measure" in capsys.readouterr().out


def test_out_naming_an_input_is_refused_and_the_input_kept(tmp_path, capsys):
    _png(tmp_path / "a.png")
    before = (tmp_path / "a.png").read_bytes()
    code = main(["estimate", str(tmp_path), "--out", str(tmp_path / "a.png"), *FLAGS])
    assert code == 2
    assert "is one of the inputs" in capsys.readouterr().err
    assert (tmp_path / "a.png").read_bytes() == before


def test_rig_with_bom_and_misspelt_key(tmp_path):
    good = 'wheel_radius_mm = 140.0\nconfidence_rect = [1, 2, 3, 4]\ntravel = "left"\n'
    (tmp_path / "bom.toml").write_bytes(b"\xef\xbb\xbf" + good.encode())
    assert load_rig(tmp_path / "bom.toml").travel == "left"
    (tmp_path / "typo.toml").write_text(good.replace("travel", "travle"))
    with pytest.raises(RigError, match=r"unknown key 'travle'; did you mean 'travel'\?"):
        load_rig(tmp_path / "typo.toml")
    (tmp_path / "seg.toml").write_text(good + "[segmentation]\np_a_hu = 1.2\n")
    with pytest.raises(RigError, match=r"unknown \[segmentation\] key 'p_a_hu'.*'p_a_hue'"):
        load_rig(tmp_path / "seg.toml")
    (tmp_path / "veto.toml").write_text(good + "[segmentation]\nveto_fraction = 0.8\n")
    assert float(load_rig(tmp_path / "veto.toml").segmentation.veto_fraction) == 0.8
    (tmp_path / "veto.toml").write_text(good + "[segmentation]\nveto_fraction = -0.1\n")
    with pytest.raises(RigError, match="veto_fraction must be >= 0"):
        load_rig(tmp_path / "veto.toml")


def test_overexposed_confidence_rectangle_is_named_in_the_message(tmp_path):
    """A rectangle over a blown-out glow: the frame's message says so (and what to do); the
    same frame with the rectangle on the wheel's face carries no such hint."""
    from sinkjax import synth
    from sinkjax.rig import rect_overexposed

    rng = np.random.default_rng(3)
    scene = synth.recording_scenes(rng, 1, width=320, height=240)[0]
    img, _ = synth.render(scene, 3)
    rig = synth.rig_for(scene)
    x, y, w, h = rig.confidence_rect
    assert rect_overexposed(img, rig.confidence_rect) is None
    blown = img.copy()
    blown[y : y + h, x : x + w] = 255
    # Just over half of the rectangle clipped is named; just under half is not.
    half = img.copy()
    half[y : y + h // 2, x : x + w] = 255
    assert rect_overexposed(half, rig.confidence_rect) is None
    half[y : y + h // 2 + 2, x : x + w] = 255
    assert "over-exposed" in (rect_overexposed(half, rig.confidence_rect) or "")
    # A saturated colour (one channel at the top) is not a glow; two channels at the top are.
    one = img.copy()
    one[y : y + h, x : x + w] = (255, 30, 20)
    assert rect_overexposed(one, rig.confidence_rect) is None
    one[y : y + h, x : x + w] = (255, 250, 20)
    assert "over-exposed" in (rect_overexposed(one, rig.confidence_rect) or "")

    for name, image in (("blown.png", blown), ("plain.png", img)):
        cv2.imwrite(str(tmp_path / name), image[..., ::-1])
    rect = ",".join(str(v) for v in rig.confidence_rect)
    out = tmp_path / "r.csv"
    args = ["estimate", str(tmp_path / "blown.png"), str(tmp_path / "plain.png"), "--out", str(out)]
    flags = ["--wheel-radius-mm", "140", "--confidence-rect", rect, "--method", "classic"]
    assert main([*args, *flags]) == 0
    rows = {r.split(",")[0]: r for r in out.read_text().splitlines()[1:]}
    blown_row = rows[str(tmp_path / "blown.png")]
    assert ",ok," not in blown_row and "confidence rectangle is over-exposed" in blown_row
    assert "over-exposed" not in rows[str(tmp_path / "plain.png")]
