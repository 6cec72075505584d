"""The review page's web server (Starlette, served by uvicorn on 127.0.0.1 only).

Routes: ``/`` the page and ``/static/*`` its files (package data, no build step); ``/files/R/P``
frame P of recording R (only frame files under the recordings' folders, checked after resolving
``..`` and symlinks); ``/api/*`` JSON: the frame table, label starts, label values computed from a
geometry, saving labels, and the measure / calibrate jobs. A bad request gets a 4xx with
``{"error": message}``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException
from starlette.middleware import Middleware
from starlette.middleware.trustedhost import TrustedHostMiddleware
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from ..app.frames import read_image
from .jobs import JobBusy, Jobs
from .labels import LabelFileError, LabelGeometry, label_values
from .session import ReviewSession

STATIC = Path(__file__).parent / "static"
ALLOWED_HOSTS = ("127.0.0.1", "localhost")
_BROWSER_FORMATS = {".png", ".jpg", ".jpeg", ".bmp"}
_MAX_BODY_BYTES = 1 << 20


def _plain(value: Any) -> Any:
    """JSON-safe copy: NumPy scalars/arrays to Python, NaN and infinities to null."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _json(content: Any, status_code: int = 200) -> JSONResponse:
    return JSONResponse(_plain(content), status_code=status_code)


async def _body(request: Request) -> dict[str, Any]:
    # JSON only: a cross-site form or text/plain POST cannot carry it without a CORS preflight,
    # which this server never grants, so other web pages cannot write labels through it.
    kind = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if kind != "application/json":
        raise HTTPException(415, f"send JSON (Content-Type: application/json), not {kind!r}")
    raw = await request.body()
    if len(raw) > _MAX_BODY_BYTES:
        raise HTTPException(413, f"request body over {_MAX_BODY_BYTES} bytes")
    try:
        data = json.loads(raw or b"{}")
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise HTTPException(400, f"the body is not JSON: {e}") from e
    if not isinstance(data, dict):
        raise HTTPException(400, "the body must be a JSON object")
    return data


def _frame_index(data: dict[str, Any], session: ReviewSession) -> int:
    index = data.get("frame")
    if isinstance(index, bool) or not isinstance(index, int):
        raise HTTPException(400, f"'frame' must be a frame number, got {index!r}")
    try:
        session.frame(index)
    except LookupError as e:
        raise HTTPException(404, str(e)) from e
    return index


def create_app(session: ReviewSession) -> Starlette:
    """The review application for ``session`` (mount it in uvicorn, or in a TestClient)."""
    jobs = Jobs(session)

    async def index(request: Request) -> Response:
        return FileResponse(STATIC / "index.html")

    async def info(request: Request) -> Response:
        return _json(
            {
                "frames": [
                    {"index": f.index, "name": f.name, "url": f.url, "recording": f.recording}
                    for f in session.frames
                ],
                "recordings": [
                    {
                        "root": str(r.root),
                        "travel": r.rig.travel,
                        "wheel_radius_mm": r.rig.wheel_radius_mm,
                        "confidence_rect": list(r.rig.confidence_rect),
                    }
                    for r in session.recordings
                ],
                "labels": str(session.labels.path),
                "results": str(session.results_path) if session.results_path else None,
                "method": session.method,
            }
        )

    def table(request: Request) -> Response:
        rows = session.labels.rows()
        entries = session.table()
        for entry, frame in zip(entries, session.frames, strict=True):
            entry["label"] = rows.get(session.labels.relative(frame.path))
        return _json(entries)

    def files(request: Request) -> Response:
        recording = request.path_params["recording"]
        try:
            path = session.file_for(recording, request.path_params["path"])
        except PermissionError as e:
            raise HTTPException(403, str(e)) from e
        except LookupError as e:
            raise HTTPException(404, str(e)) from e
        if path.suffix.lower() in _BROWSER_FORMATS:
            return FileResponse(path)
        # TIFF and the like: browsers cannot show them, so send the pixels as PNG.
        try:
            ok, png = cv2.imencode(".png", read_image(path)[:, :, ::-1])
        except (OSError, ValueError) as e:
            raise HTTPException(415, f"cannot show {path.name}: {e}") from e
        if not ok:
            raise HTTPException(415, f"cannot show {path.name} in a browser")
        return Response(png.tobytes(), media_type="image/png")

    def start(request: Request) -> Response:
        try:
            return _json(session.label_start(request.path_params["index"]))
        except LookupError as e:
            raise HTTPException(404, str(e)) from e

    async def geometry(request: Request) -> Response:
        data = await _body(request)
        index = _frame_index(data, session)
        values = await run_in_threadpool(_values, data, session, index)
        return _json(values.__dict__)

    async def save(request: Request) -> Response:
        data = await _body(request)
        index = _frame_index(data, session)
        values = await run_in_threadpool(_values, data, session, index)
        try:
            row = await run_in_threadpool(
                session.labels.save, session.frame(index).path, values.cells()
            )
        except LabelFileError as e:
            raise HTTPException(409, str(e)) from e
        return _json({"row": row, "values": values.__dict__, "labels": str(session.labels.path)})

    def labels(request: Request) -> Response:
        try:
            return _json(session.labels.rows())
        except LabelFileError as e:
            raise HTTPException(409, str(e)) from e

    async def measure(request: Request) -> Response:
        data = await _body(request)
        frames = data.get("frames")
        if frames is not None:
            frames = [_frame_index({"frame": i}, session) for i in frames]
        try:
            jobs.measure(frames)
        except JobBusy as e:
            raise HTTPException(409, str(e)) from e
        return _json(jobs.status(), 202)

    async def calibrate(request: Request) -> Response:
        data = await _body(request)
        steps = data.get("steps", 50)
        if isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= 1000:
            raise HTTPException(400, f"'steps' must be a whole number 1-1000, got {steps!r}")
        try:
            jobs.calibrate(steps)
        except JobBusy as e:
            raise HTTPException(409, str(e)) from e
        except (ValueError, LabelFileError) as e:
            raise HTTPException(400, str(e)) from e
        return _json(jobs.status(), 202)

    def job(request: Request) -> Response:
        return _json(jobs.status())

    async def error(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, HTTPException)
        return _json({"error": exc.detail}, exc.status_code)

    app = Starlette(
        routes=[
            Route("/", index),
            Route("/api/session", info),
            Route("/api/table", table),
            Route("/api/frames/{index:int}/start", start),
            Route("/api/geometry", geometry, methods=["POST"]),
            Route("/api/labels", labels),
            Route("/api/labels", save, methods=["POST"]),
            Route("/api/measure", measure, methods=["POST"]),
            Route("/api/calibrate", calibrate, methods=["POST"]),
            Route("/api/job", job),
            Route("/files/{recording:int}/{path:path}", files),
            Mount("/static", StaticFiles(directory=STATIC), name="static"),
        ],
        exception_handlers={HTTPException: error},
        # Only the loopback names: a DNS-rebinding page cannot reach the API under its own name.
        middleware=[Middleware(TrustedHostMiddleware, allowed_hosts=list(ALLOWED_HOSTS))],
    )
    app.state.session, app.state.jobs = session, jobs
    return app


def _values(data: dict[str, Any], session: ReviewSession, index: int) -> Any:
    try:
        geometry = LabelGeometry.from_json(data)
    except ValueError as e:
        raise HTTPException(400, str(e)) from e
    return label_values(geometry, session.rig_of(index))
