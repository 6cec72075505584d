"""`sinkjax review`'s server: label geometry against the renderer's truth, LABELS.csv writes
(atomic, rows kept, concurrent saves), which frames are suspicious, and safety (traversal,
symlinks, bad requests). The page itself is driven in a browser in test_review_browser.py."""

from __future__ import annotations

import csv
import json
import math
import os
import shutil
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("starlette", reason="needs the review extra: pip install 'sinkjax[review]'")
pytest.importorskip("uvicorn", reason="needs the review extra: pip install 'sinkjax[review]'")

import sinkjax
from sinkjax.app.results import COLUMNS, FrameResult
from sinkjax.review import LabelGeometry, LabelStore, label_values, suspicion
from sinkjax.review.command import Server, bind
from sinkjax.review.jobs import Jobs
from sinkjax.review.server import create_app
from sinkjax.review.session import ReviewSession


def _client(session: ReviewSession):
    from starlette.testclient import TestClient

    return TestClient(create_app(session), base_url="http://127.0.0.1")


def _truth(folder: Path) -> list[dict[str, str]]:
    with (folder / "truth.csv").open(newline="") as fh:
        return list(csv.DictReader(fh))


def true_geometry_px(row: dict[str, str], travel: str) -> dict[str, object]:
    """Rim, A, B and two soil points in image px from a truth row (straight-surface frames):
    A and B are where the true line v = k u + b meets the true rim (wheel frame)."""
    cx, cy, r = (float(row[c]) for c in ("center_x_px", "center_y_px", "radius_px"))
    k, b = float(row["k"]), float(row["b_px"])
    s = 1.0 if travel == "right" else -1.0
    u = np.roots([1 + k * k, 2 * k * b, b * b - r * r]).real
    ua, ub = u.max(), u.min()

    def image(uu: float) -> list[float]:
        return [cx + s * uu, cy + k * uu + b]

    return {
        "centre_px": [cx, cy],
        "radius_px": r,
        "a_px": image(ua),
        "b_px": image(ub),
        "soil_px": [image(0.5 * ua), image(0.5 * ub)],
    }


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return sinkjax.write_recording(
        tmp_path_factory.mktemp("rec") / "rec", n_frames=3, seed=1, preset="clean", progress=False
    )


@pytest.fixture
def session(recording: Path, tmp_path: Path) -> ReviewSession:
    return ReviewSession([recording], labels=tmp_path / "LABELS.csv", method="classic")


# ------------------------------------------------------------------------ label geometry


@pytest.mark.parametrize("travel", ["right", "left"])
def test_label_values_reproduce_the_renderers_truth(tmp_path: Path, travel: str) -> None:
    folder = sinkjax.write_recording(
        tmp_path, n_frames=3, seed=1, preset="clean", travel=travel, progress=False
    )
    rig = sinkjax.load_rig(folder / "rig.toml")
    flat = [row for row in _truth(folder) if row["terrain"] == "flat"]
    assert flat, "seed 1 renders a flat frame"
    for row in flat:
        g = LabelGeometry.from_json(true_geometry_px(row, travel))
        v = label_values(g, rig)
        assert v.contact
        assert v.sinkage_mm == pytest.approx(float(row["sinkage_mm"]), abs=1e-6)
        assert v.theta1_deg == pytest.approx(float(row["theta1_deg"]), abs=1e-6)
        assert v.theta2_deg == pytest.approx(float(row["theta2_deg"]), abs=1e-6)
        # flat ground: theta1 = theta2 = acos(1 - z0/r)
        flat_deg = math.degrees(math.acos(1 - v.sinkage_px / g.radius_px))
        assert v.theta1_deg == pytest.approx(flat_deg, abs=1e-6)


def test_soil_points_use_their_least_squares_line() -> None:
    rig = sinkjax.Rig(wheel_radius_mm=100.0, confidence_rect=(0, 0, 4, 4), travel="right")
    rng = np.random.default_rng(3)
    cx, cy, r = 200.0, 150.0, 80.0
    x = rng.uniform(150, 250, 40)
    y = 200.0 + 0.1 * (x - cx) + rng.normal(0, 2.0, 40)
    g = LabelGeometry((cx, cy), r, (260.0, 190.0), (140.0, 195.0), np.stack([x, y], 1))
    v = label_values(g, rig)
    k, b = np.polyfit(x - cx, y - cy, 1)  # independent least squares in the O-centred frame
    z0_px = r - abs(b) / math.sqrt(k * k + 1)
    assert v.sinkage_px == pytest.approx(z0_px, abs=1e-6)
    assert v.sinkage_mm == pytest.approx(z0_px * 100.0 / r, abs=1e-6)
    assert v.theta1_deg == pytest.approx(math.degrees(math.atan2(60.0, 40.0)), abs=1e-6)
    assert v.theta2_deg == pytest.approx(math.degrees(math.atan2(60.0, 45.0)), abs=1e-6)


def test_a_soil_line_outside_the_rim_is_no_contact() -> None:
    rig = sinkjax.Rig(wheel_radius_mm=100.0, confidence_rect=(0, 0, 4, 4))
    soil = np.array([[0.0, 300.0], [400.0, 300.0]])  # 150 px below O, rim radius 80 px
    v = label_values(LabelGeometry((200.0, 150.0), 80.0, (250, 200), (150, 200), soil), rig)
    assert (v.contact, v.sinkage_mm, v.theta1_deg, v.theta2_deg) == (False, 0.0, 0.0, 0.0)


# ------------------------------------------------------------------------ LABELS.csv


def test_store_replaces_one_row_and_keeps_the_others_and_extra_columns(tmp_path: Path) -> None:
    path = tmp_path / "LABELS.csv"
    path.write_text(
        "image,sinkage_mm,theta1_deg,theta2_deg,note\n"
        "a.png,1,2,3,keep me\n./b.png,4,5,6,and me\nc.png,7,,9,\n"
    )
    store = LabelStore(path)
    store.save(tmp_path / "b.png", {"sinkage_mm": "40", "theta1_deg": "50", "theta2_deg": "60"})
    store.save(tmp_path / "sub" / "d.png", {"sinkage_mm": "1", "theta1_deg": "", "theta2_deg": ""})
    rows = list(csv.DictReader(path.open()))
    assert [r["image"] for r in rows] == ["a.png", "b.png", "c.png", "sub/d.png"]
    assert rows[0] == {
        "image": "a.png",
        "sinkage_mm": "1",
        "theta1_deg": "2",
        "theta2_deg": "3",
        "note": "keep me",
    }
    assert (rows[1]["sinkage_mm"], rows[1]["theta2_deg"], rows[1]["note"]) == ("40", "60", "and me")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["LABELS.csv"]  # no temp file left


def test_store_refuses_a_file_that_is_not_a_labels_file(tmp_path: Path) -> None:
    from sinkjax.review.labels import LabelFileError

    path = tmp_path / "results.csv"
    path.write_text("image,status\nx.png,ok\n")
    with pytest.raises(LabelFileError, match="missing column"):
        LabelStore(path).save(tmp_path / "x.png", {"sinkage_mm": "1"})
    assert path.read_text() == "image,status\nx.png,ok\n"


def test_concurrent_saves_from_threads_lose_nothing(recording: Path, tmp_path: Path) -> None:
    many = tmp_path / "many"
    many.mkdir()
    shutil.copy(recording / "rig.toml", many)
    frame = next(recording.glob("frame_*.png"))
    n = 24
    for i in range(n):
        os.link(frame, many / f"f{i:02d}.png")
    session = ReviewSession([many], labels=many / "LABELS.csv", method="classic")
    server = Server(create_app(session), bind(0)).start()
    base = {"centre_px": [300, 250], "a_px": [400, 330], "b_px": [200, 330]}
    errors: list[BaseException] = []

    def save(i: int) -> None:
        body = {**base, "frame": i, "radius_px": 150, "soil_px": [[200, 300 + i], [400, 300 + i]]}
        req = urllib.request.Request(
            server.url + "api/labels",
            json.dumps(body).encode(),
            {"Content-Type": "application/json"},
        )
        try:
            with urllib.request.urlopen(req, timeout=60) as resp:
                assert resp.status == 200
        except BaseException as e:  # collected: a thread's assert would be lost otherwise
            errors.append(e)

    try:
        threads = [threading.Thread(target=save, args=(i,)) for i in range(n)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        server.stop()
    assert not errors
    rows = {r["image"]: r for r in csv.DictReader((many / "LABELS.csv").open())}
    assert sorted(rows) == [f"f{i:02d}.png" for i in range(n)]
    for i in range(n):  # each row has its own line: z0 = r - (300 + i - 250) px, R/r = 140/150
        z0_mm = (150 - (50 + i)) * 140.0 / 150
        assert float(rows[f"f{i:02d}.png"]["sinkage_mm"]) == pytest.approx(z0_mm, abs=1e-3)


# ------------------------------------------------------------------------ the API


def test_save_through_the_api_writes_the_row_relative_to_the_csv(
    session: ReviewSession, recording: Path
) -> None:
    rig = sinkjax.load_rig(recording / "rig.toml")
    row = next(r for r in _truth(recording) if r["terrain"] == "flat")
    index = next(f.index for f in session.frames if f.path.name == row["image"])
    geometry = {"frame": index, **true_geometry_px(row, rig.travel)}
    client = _client(session)
    shown = client.post("/api/geometry", json=geometry).json()
    saved = client.post("/api/labels", json=geometry).json()
    assert saved["values"] == shown
    written = list(csv.DictReader(session.labels.path.open()))
    image = os.path.relpath(recording / row["image"], session.labels.path.parent)
    assert written == [saved["row"]] and saved["row"]["image"] == image
    for col in ("sinkage_mm", "theta1_deg", "theta2_deg"):
        assert float(written[0][col]) == pytest.approx(float(row[col]), abs=1e-4)
    assert client.get("/api/table").json()[index]["label"]["image"] == image
    # what calibrate reads back is what was saved
    labels = sinkjax.read_labels(session.labels.path, rig)
    assert labels.names == (image,)


def _bad(response, status: int, words: str) -> None:
    assert response.status_code == status, response.text
    assert words in response.json()["error"]


def test_bad_requests_get_a_4xx_with_a_message(session: ReviewSession) -> None:
    client = _client(session)
    good = {
        "frame": 0,
        "centre_px": [300, 250],
        "radius_px": 150,
        "a_px": [400, 330],
        "b_px": [200, 330],
        "soil_px": [[200, 330], [400, 330]],
    }
    post = client.post
    as_json = {"Content-Type": "application/json"}
    _bad(post("/api/geometry", content=b"{not json", headers=as_json), 400, "not JSON")
    _bad(post("/api/geometry", content=b"[1, 2]", headers=as_json), 400, "JSON object")
    # a cross-site form or text/plain POST (no CORS preflight) is refused
    plain = {"Content-Type": "text/plain"}
    _bad(post("/api/labels", content=json.dumps(good), headers=plain), 415, "application/json")
    _bad(post("/api/labels", json={**good, "frame": 99}), 404, "no frame 99")
    _bad(post("/api/labels", json={**good, "frame": "0"}), 400, "'frame' must be")
    _bad(post("/api/geometry", json={**good, "radius_px": -1}), 400, "radius_px")
    _bad(post("/api/geometry", json={k: v for k, v in good.items() if k != "a_px"}), 400, "a_px")
    _bad(post("/api/geometry", json={**good, "soil_px": [[1, 2]]}), 400, "at least two")
    _bad(post("/api/geometry", json={**good, "soil_px": [[1, 2], [1, 5]]}), 400, "vertical")
    nan = json.dumps(good).replace("150", "NaN").encode()
    _bad(post("/api/geometry", content=nan, headers=as_json), 400, "finite")
    _bad(client.get("/api/frames/99/start"), 404, "no frame 99")
    _bad(post("/api/calibrate", json={"steps": 0}), 400, "steps")
    _bad(post("/api/calibrate", json={"steps": 5}), 400, "no labels")
    assert not session.labels.path.exists()  # nothing bad was written
    # another host name (DNS rebinding) gets nothing
    from starlette.testclient import TestClient

    assert TestClient(create_app(session)).get("/api/session").status_code == 400


def test_only_frame_files_of_the_recordings_are_served(recording: Path, tmp_path: Path) -> None:
    root = tmp_path / "rec"
    shutil.copytree(recording, root)
    secret = tmp_path / "secret.png"
    shutil.copy(recording / "frame_0000.png", secret)
    (root / "zz_link.png").symlink_to(secret)  # a frame that is a symlink out of the tree
    session = ReviewSession([root], labels=tmp_path / "LABELS.csv")
    assert [f.path.name for f in session.frames][-1] == "zz_link.png"
    client = _client(session)
    ok = client.get("/files/0/frame_0001.png")
    assert ok.status_code == 200
    assert ok.content == (root / "frame_0001.png").read_bytes()
    for url, status in [
        ("/files/0/..%2Fsecret.png", 403),
        ("/files/0/%2e%2e%2fsecret.png", 403),
        ("/files/0/%2E%2E/secret.png", 403),
        ("/files/0/..%5csecret.png", 404),  # a backslash is a plain character on POSIX
        ("/files/0/%2Fetc%2Fpasswd", 403),
        ("/files/0/zz_link.png", 403),
        ("/files/0/truth.csv", 404),
        ("/files/0/rig.toml", 404),
        ("/files/0/nope.png", 404),
        ("/files/1/frame_0001.png", 404),
    ]:
        response = client.get(url)
        assert response.status_code == status, url
        assert response.content != secret.read_bytes()
        assert response.json()["error"]


def test_results_csv_rows_start_labelling_where_the_estimate_was(
    session: ReviewSession, recording: Path, tmp_path: Path
) -> None:
    rows = [
        ["frame_0000.png", "ok", 40.0, 0.5, 41.0, 0.3, 38.0, 0.4, 265.3, 265.2, 161.5, ""],
        ["frame_0001.png", "fit_failed", "", "", "", "", "", "", "", "", "", "did not converge"],
    ]
    results = tmp_path / "results.csv"
    with results.open("w", newline="") as fh:
        csv.writer(fh).writerows([COLUMNS, *rows])
    session.load_results(results)
    assert session.results[0].sinkage_mm == 40.0 and session.results[2] is None
    client = _client(session)
    start = client.get("/api/frames/0/start").json()
    assert start["source"] == "estimate"
    assert start["centre_px"] == [265.3, 265.2] and start["radius_px"] == 161.5
    # the start geometry, measured by the conventions, gives back the estimate's numbers
    back = client.post("/api/geometry", json={"frame": 0, **start}).json()
    assert back["sinkage_mm"] == pytest.approx(40.0, abs=1e-6)
    assert back["theta1_deg"] == pytest.approx(41.0, abs=1e-6)
    assert back["theta2_deg"] == pytest.approx(38.0, abs=1e-6)
    table = client.get("/api/table").json()
    assert table[1]["suspicion"] >= 100 and "did not converge" in table[1]["reasons"][0]


@pytest.mark.slow
def test_without_an_estimate_labelling_starts_from_the_hough_rim(
    session: ReviewSession, recording: Path
) -> None:
    start = _client(session).get("/api/frames/0/start").json()
    truth = _truth(recording)[0]
    assert start["source"] == "rim guess"
    assert start["centre_px"][0] == pytest.approx(float(truth["center_x_px"]), abs=1.0)
    assert start["centre_px"][1] == pytest.approx(float(truth["center_y_px"]), abs=1.0)
    assert start["radius_px"] == pytest.approx(float(truth["radius_px"]), abs=1.0)


def _wait(client, timeout_s: float = 120.0) -> dict:
    t0 = time.monotonic()
    while (job := client.get("/api/job").json())["state"] == "running":
        assert time.monotonic() - t0 < timeout_s, job
        time.sleep(0.05)
    return job


def test_measure_button_fills_the_table(session: ReviewSession, recording: Path) -> None:
    client = _client(session)
    assert client.post("/api/measure", json={}).status_code == 202
    job = _wait(client)
    assert (job["kind"], job["state"], job["progress"]) == ("measure", "done", 1.0)
    direct = list(sinkjax.estimate_paths([str(recording)], method="classic"))
    table = client.get("/api/table").json()
    for entry, expected in zip(table, direct, strict=True):
        assert entry["result"]["status"] == expected.status
        assert entry["result"]["sinkage_mm"] == pytest.approx(expected.sinkage_mm)


def test_calibrate_button_calibrates_saves_the_rig_and_remeasures(
    session: ReviewSession, recording: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The job's wiring around ``sinkjax.calibrate`` (itself tested in test_calibration): the
    saved labels go in, progress comes out, the new rig is written and the frames re-measured."""
    from sinkjax.calibration import CalibrationResult, Errors

    tuned = sinkjax.SegmentationParams(p_d_hue=0.8, p_a_hue=1.2)
    seen: dict[str, object] = {}

    def fake_calibrate(frames, rig, *, steps, callback, on_stage):
        seen.update(names=frames.names, steps=steps, rig=rig)
        for done, total in ((2, 6), (4, 6), (4, 4)):  # the grid's frames; its pruned total
            on_stage("grid", done, total)
        for i in range(steps + 1):
            callback(i, 10.0 - i)
        on_stage("polish", 1, 2)
        errors = Errors(1.0, 2.0, 3.0, 0.1, 3, 3)
        new = sinkjax.Rig(rig.wheel_radius_mm, rig.confidence_rect, rig.travel, tuned)
        return CalibrationResult(new, (10.0, 9.0, 8.0), 2, errors, errors, 0.1)

    monkeypatch.setattr(sinkjax, "calibrate", fake_calibrate)
    shown: list[tuple[float, str]] = []
    update = Jobs._update
    monkeypatch.setattr(Jobs, "_update", lambda self, *a: (shown.append(a), update(self, *a)))
    client = _client(session)
    rig = session.recordings[0].rig
    for row in _truth(recording)[:2]:
        index = next(f.index for f in session.frames if f.path.name == row["image"])
        geometry = true_geometry_px(row, rig.travel)
        assert client.post("/api/labels", json={"frame": index, **geometry}).status_code == 200
    assert client.post("/api/calibrate", json={"steps": 2}).status_code == 202
    job = _wait(client)
    assert job["state"] == "done", job
    folder = session.labels.path.parent
    expected = tuple(os.path.relpath(recording / f"frame_000{i}.png", folder) for i in (0, 1))
    assert seen["names"] == expected
    assert seen["steps"] == 2 and seen["rig"] == rig
    written = sinkjax.load_rig(Path(job["result"]["rig_path"]))
    assert written.segmentation.as_dict() == pytest.approx(tuned.as_dict())
    assert session.recordings[0].rig.segmentation.as_dict() == pytest.approx(tuned.as_dict())
    assert job["result"]["after"]["theta2_deg"] == 3.0
    # The bar moves through the grid, the steps and the polish, never back, then re-measures.
    calibrating = [(p, m) for p, m in shown if m.startswith("calibrating: ")]
    assert [m for _, m in calibrating[:3]] == [
        f"calibrating: frames measured on a grid of thresholds, {d}" for d in ("2/6", "4/6", "4/4")
    ]
    assert calibrating[-1][1] == "calibrating: polishing, 1/2"
    bar = [p for p, _ in calibrating]
    assert bar == sorted(bar) and bar[0] == pytest.approx(0.8 * 0.4 / 3)
    assert bar[-1] == pytest.approx(0.8 * 0.95) and shown[-1][0] > bar[-1]
    assert all(entry["result"] is not None for entry in client.get("/api/table").json())


# ------------------------------------------------------------------------ suspicion


def _ok(i: int, z: float, sigma: float = 0.5, rim=(300.0, 250.0, 150.0)) -> FrameResult:
    return FrameResult(
        f"f{i}", "ok", z, sigma, 40.0 + 0.1 * i, 0.3, 38.0, 0.3, rim[0], rim[1], rim[2]
    )


def test_suspicion_ranks_failures_sigma_rim_jumps_and_outliers() -> None:
    results: list[FrameResult | None] = [_ok(i, 30.0 + 0.2 * i) for i in range(12)]
    assert all(s.score == 0 for s in suspicion(results, [0] * 12))  # smooth: nothing to see
    results[2] = FrameResult("f2", "fit_failed", message="did not converge")
    results[5] = _ok(5, 31.0, sigma=3.0)
    results[7] = _ok(7, 31.4, rim=(306.0, 250.0, 150.0))
    results[9] = _ok(9, 48.0)
    results[10] = None
    flags = suspicion(results, [0] * 12)
    ranked = sorted(range(12), key=lambda i: -flags[i].score)
    assert ranked[0] == 2 and "fit_failed: did not converge" in flags[2].reasons
    assert set(ranked[1:4]) == {5, 7, 9}
    assert any("σ z0" in r for r in flags[5].reasons)
    assert any("rim jumps 6.0 px" in r for r in flags[7].reasons)
    assert any("z0 48.0 mm far from" in r for r in flags[9].reasons)
    assert all(flags[i].score == 0 for i in (0, 1, 3, 4, 6, 8, 10, 11))
    # recordings are judged separately: the same rims in another recording are not a jump
    other = [_ok(i, 30.0, rim=(100.0, 80.0, 60.0)) for i in range(4)]
    assert all(s.score == 0 for s in suspicion(results[:2] + other, [0, 0, 1, 1, 1, 1]))


# ------------------------------------------------------------------------ command line


def test_cli_names_the_extra_when_the_server_library_is_missing(
    recording: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from sinkjax.app.cli import main

    monkeypatch.setitem(sys.modules, "uvicorn", None)
    assert main(["review", str(recording), "--no-browser"]) == 2
    assert "pip install 'sinkjax[review]'" in capsys.readouterr().err


def test_cli_rejects_a_missing_path(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from sinkjax.app.cli import main

    assert main(["review", str(tmp_path / "nope"), "--no-browser"]) == 2
    assert "does not exist" in capsys.readouterr().err
