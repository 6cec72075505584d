"""The review page in a real browser (Playwright driving Debian's chromium): measure a synthetic
recording, look at it (screenshot for the README), then label a flat-ground frame by dragging the
rim, A, B and the soil line onto the renderer's truth and save; LABELS.csv must match the truth.

Skipped, saying how to install, where playwright or /usr/bin/chromium is missing.
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path

import pytest

pytest.importorskip("starlette", reason="needs the review extra: pip install 'sinkjax[review]'")
CHROMIUM = Path("/usr/bin/chromium")
INSTALL = "pip install 'sinkjax[review,dev]' (playwright) and apt-get install -y chromium"
try:
    from playwright.sync_api import Page, sync_playwright
except ImportError:
    pytest.skip(f"playwright is not installed: {INSTALL}", allow_module_level=True)
if not CHROMIUM.exists():
    pytest.skip(f"{CHROMIUM} is missing: {INSTALL}", allow_module_level=True)

from test_review import true_geometry_px  # noqa: E402

import sinkjax  # noqa: E402
from sinkjax.app.demo import DEMO_PRESET, DEMO_SEED  # noqa: E402
from sinkjax.review.command import Server, bind  # noqa: E402
from sinkjax.review.server import create_app  # noqa: E402
from sinkjax.review.session import ReviewSession  # noqa: E402

ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
# The README's screenshot: rewritten only where SINKJAX_UPDATE_SCREENSHOT=1 asks (a test run
# leaves the working tree as it was); otherwise the page is shot into the test's own folder.
SCREENSHOT = Path(__file__).resolve().parents[1] / "docs" / "review.png"


def _client_xy(page: Page, x: float, y: float) -> tuple[float, float]:
    """Image pixels -> the page's CSS pixels, through the SVG's own transform."""
    return tuple(
        page.evaluate(
            """([x, y]) => { const s = document.getElementById('view');
               const p = s.createSVGPoint(); p.x = x; p.y = y;
               const q = p.matrixTransform(s.getScreenCTM()); return [q.x, q.y]; }""",
            [x, y],
        )
    )


def _handle(page: Page, role: str) -> tuple[float, float]:
    h = page.locator(f"[data-role={role}]")
    return float(h.get_attribute("data-x")), float(h.get_attribute("data-y"))


def _drag(page: Page, role: str, to_px: tuple[float, float]) -> None:
    x0, y0 = _client_xy(page, *_handle(page, role))
    x1, y1 = _client_xy(page, *to_px)
    page.mouse.move(x0, y0)
    page.mouse.down()
    page.mouse.move((x0 + x1) / 2, (y0 + y1) / 2)
    page.mouse.move(x1, y1)
    page.mouse.up()


def test_review_page_measure_look_and_label_a_frame(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # frames are named as given: rec/frame_0000.png
    # The demo's recording (its seed and preset; its first 6 frames): the README's screenshot.
    folder = sinkjax.write_recording(
        "rec", n_frames=6, seed=DEMO_SEED, preset=DEMO_PRESET, progress=False
    )
    truth = list(csv.DictReader((folder / "truth.csv").open()))
    flat = next(i for i, row in enumerate(truth) if row["terrain"] == "flat")
    session = ReviewSession([folder], labels=tmp_path / "labels" / "LABELS.csv")
    server = Server(create_app(session), bind(0)).start()
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
            page = browser.new_page(viewport={"width": 1400, "height": 860})
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(server.url)
            page.wait_for_selector("body[data-ready='1']")
            assert page.locator("#frames tbody tr").count() == 6

            # Review: measure on demand, then the list, the overlay and the series fill in.
            page.click("#measure")
            page.wait_for_function("document.body.dataset.job === 'done'", timeout=240_000)
            page.wait_for_selector("#estimate circle")
            assert page.locator("#series svg").count() == 3
            statuses = page.locator("#frames td.st").all_inner_texts()
            assert statuses.count("ok") >= 4, statuses
            update = os.environ.get("SINKJAX_UPDATE_SCREENSHOT") == "1"
            shot = SCREENSHOT if update else tmp_path / "review.png"
            shot.parent.mkdir(exist_ok=True)
            page.screenshot(path=str(shot))
            assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
            # a click on a point of the series opens its frame; arrow keys step through the list
            page.locator(f"#series svg >> nth=0 >> circle[data-index='{flat}']").click()
            assert page.inner_text("#framename").startswith(f"#{flat} ")
            order = [
                int(i)
                for i in page.locator("#frames tbody tr").evaluate_all(
                    "rows => rows.map(r => r.dataset.index)"
                )
            ]
            page.keyboard.press("ArrowRight")
            following = order[min(order.index(flat) + 1, len(order) - 1)]
            assert page.inner_text("#framename").startswith(f"#{following} ")
            page.keyboard.press("ArrowLeft")
            assert page.inner_text("#framename").startswith(f"#{flat} ")

            # Label: start from the estimate, drag everything onto the truth, save.
            page.keyboard.press("l")
            page.wait_for_selector("[data-role=A]")
            assert "estimate" in page.inner_text("#labelsource")
            true = true_geometry_px(truth[flat], session.rig_of(flat).travel)
            centre = tuple(true["centre_px"])
            _drag(page, "L1", true["soil_px"][0])
            _drag(page, "L2", true["soil_px"][1])
            _drag(page, "O", centre)
            hx, hy = _handle(page, "R")
            phi = math.atan2(hy - centre[1], hx - centre[0])
            r = true["radius_px"]
            _drag(page, "R", (centre[0] + r * math.cos(phi), centre[1] + r * math.sin(phi)))
            _drag(page, "A", true["a_px"])
            _drag(page, "B", true["b_px"])
            page.wait_for_function("!document.body.dataset.pending")
            shown = float(page.inner_text("#lz0"))
            page.click("#save")
            page.wait_for_selector("#saved:has-text('saved')")
            browser.close()
    finally:
        server.stop()
    assert not errors
    rows = list(csv.DictReader(session.labels.path.open()))
    assert [r["image"] for r in rows] == [
        os.path.relpath(folder / truth[flat]["image"], session.labels.path.parent)
    ]
    assert float(rows[0]["sinkage_mm"]) == pytest.approx(float(truth[flat]["sinkage_mm"]), abs=0.3)
    assert float(rows[0]["theta1_deg"]) == pytest.approx(float(truth[flat]["theta1_deg"]), abs=0.3)
    assert float(rows[0]["theta2_deg"]) == pytest.approx(float(truth[flat]["theta2_deg"]), abs=0.3)
    assert shown == pytest.approx(float(rows[0]["sinkage_mm"]), abs=0.01)
