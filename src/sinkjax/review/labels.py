"""Labels drawn in the review page: geometry -> z0, theta1, theta2, and the LABELS.csv store.

The page sends the geometry a person placed on a frame (rim circle, entry point A, exit point B
and the soil: two points of a line or any number of clicked soil points, all in image pixels).
The numbers are computed here, once, with :mod:`sinkjax.geometry` (conventions §1), so the page
shows exactly what ``save`` writes and what ``calibrate`` later compares against.
"""

from __future__ import annotations

import contextlib
import csv
import io
import math
import os
import tempfile
import threading
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..geometry import from_wheel_frame, geometry_from_boundary, to_wheel_frame
from ..rig import Rig

LABEL_COLUMNS = ("image", "sinkage_mm", "theta1_deg", "theta2_deg")


class LabelFileError(ValueError):
    """LABELS.csv exists but cannot be kept (not UTF-8 CSV, or it lacks the label columns)."""


@dataclass(frozen=True)
class LabelGeometry:
    """What a person placed on one frame, in image pixels (x right, y down).

    ``soil_px`` (n >= 2, 2): points of the soil surface inside the rim; the equivalent line is
    their least-squares line (two points: the line through them).
    """

    centre_px: tuple[float, float]
    radius_px: float
    a_px: tuple[float, float]
    b_px: tuple[float, float]
    soil_px: np.ndarray

    @classmethod
    def from_json(cls, data: Mapping[str, object]) -> LabelGeometry:
        """Parse the page's JSON; raises ValueError saying which field is wrong."""
        centre = _point(data, "centre_px")
        radius = _number(data.get("radius_px"), "radius_px")
        if not radius > 0:
            raise ValueError(f"radius_px must be positive, got {radius}")
        soil = data.get("soil_px")
        if not isinstance(soil, list) or len(soil) < 2:
            raise ValueError("soil_px must be a list of at least two [x, y] points")
        points = np.array([_pair(p, "soil_px") for p in soil], dtype=np.float64)
        if np.ptp(points[:, 0]) < 1e-6:
            raise ValueError("soil_px points must not all have the same x (a vertical line)")
        return cls(centre, radius, _point(data, "a_px"), _point(data, "b_px"), points)


def _number(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    return float(value)


def _pair(value: object, name: str) -> tuple[float, float]:
    if not isinstance(value, list | tuple) or len(value) != 2:
        raise ValueError(f"{name} must be an [x, y] pair of pixels, got {value!r}")
    return _number(value[0], name), _number(value[1], name)


def _point(data: Mapping[str, object], name: str) -> tuple[float, float]:
    return _pair(data.get(name), name)


@dataclass(frozen=True)
class LabelValues:
    """z0 (mm and px) and the angles (degrees) of a :class:`LabelGeometry`, plus its line.

    ``line_px`` is the equivalent line's chord of the rim circle in image pixels (for drawing;
    where the line misses the rim, the segment under the circle's horizontal extent).
    """

    sinkage_mm: float
    sinkage_px: float
    theta1_deg: float
    theta2_deg: float
    contact: bool
    line_px: tuple[tuple[float, float], tuple[float, float]]

    def cells(self) -> dict[str, str]:
        return {
            "sinkage_mm": f"{self.sinkage_mm:.4f}",
            "theta1_deg": f"{self.theta1_deg:.4f}",
            "theta2_deg": f"{self.theta2_deg:.4f}",
        }


def label_values(geometry: LabelGeometry, rig: Rig) -> LabelValues:
    """Conventions §1 on the placed geometry: z0 = r - |b| / sqrt(k^2 + 1) of the soil points'
    least-squares line in the O-centred wheel frame, times R / r mm; theta1 at A, theta2 at B.

    A soil line that does not reach inside the rim is no contact: sinkage 0, both angles 0.
    """
    (cx, cy), r = geometry.centre_px, geometry.radius_px
    (ax, ay), (bx, by) = (tuple(map(float, p)) for p in (geometry.a_px, geometry.b_px))
    a_u, a_v = to_wheel_frame(ax, ay, cx, cy, rig.travel)
    b_u, b_v = to_wheel_frame(bx, by, cx, cy, rig.travel)
    g = geometry_from_boundary(
        geometry.soil_px[:, 0],
        geometry.soil_px[:, 1],
        cx,
        cy,
        r,
        travel=rig.travel,
        a_px=np.array([float(a_u), float(a_v)]),
        b_end_px=np.array([float(b_u), float(b_v)]),
    )
    z0_px = float(g.sinkage_px)
    line = rim_chord(float(g.k), float(g.b_px), r, (cx, cy), rig.travel)
    if not z0_px > 0:
        return LabelValues(0.0, 0.0, 0.0, 0.0, False, line)
    return LabelValues(
        sinkage_mm=z0_px * rig.wheel_radius_mm / r,
        sinkage_px=z0_px,
        theta1_deg=math.degrees(float(g.theta1_rad)),
        theta2_deg=math.degrees(float(g.theta2_rad)),
        contact=True,
        line_px=line,
    )


def rim_chord(
    k: float, b: float, r: float, centre: tuple[float, float], travel: str
) -> tuple[tuple[float, float], tuple[float, float]]:
    """Image-px ends of the wheel-frame line v = k u + b inside the rim circle of radius ``r``
    (where it misses the rim: its stretch under the circle, u from -r to r)."""
    # v = k u + b meets u^2 + v^2 = r^2 where (1 + k^2) u^2 + 2 k b u + b^2 - r^2 = 0.
    qa, qb, qc = 1.0 + k * k, 2.0 * k * b, b * b - r * r
    disc = qb * qb - 4.0 * qa * qc
    half = math.sqrt(disc) / (2.0 * qa) if disc > 0 else r
    mid = -qb / (2.0 * qa) if disc > 0 else 0.0
    us = np.array([mid - half, mid + half])
    x, y = from_wheel_frame(us, k * us + b, centre[0], centre[1], travel)
    return (float(x[0]), float(y[0])), (float(x[1]), float(y[1]))


class LabelStore:
    """LABELS.csv (conventions §3): one row per image, written atomically, existing rows kept.

    Image cells are paths relative to the CSV's folder. Saves are serialised by a lock in this
    process and, where the platform has ``fcntl``, by an advisory lock on the folder, so two
    tabs (or two review servers) saving at once lose nothing. Extra columns are kept.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()

    def relative(self, image: str | Path) -> str:
        """The ``image`` cell for an image file: its path relative to the CSV's folder."""
        return Path(os.path.relpath(Path(image).absolute(), self.path.parent.absolute())).as_posix()

    def rows(self) -> dict[str, dict[str, str]]:
        """The rows by (normalised) ``image`` cell; empty if the file does not exist yet."""
        return self._read()[1]

    def save(self, image: str | Path, cells: Mapping[str, str]) -> dict[str, str]:
        """Set the row of ``image`` (a file path) to ``cells``; returns the row written."""
        key = self.relative(image)
        with self._lock, _folder_lock(self.path.parent):
            header, rows = self._read()
            row = dict(rows.get(key, {}))
            row.update(cells, image=key)
            rows[key] = row
            self._write(header, rows.values())
        return row

    def _read(self) -> tuple[list[str], dict[str, dict[str, str]]]:
        if not self.path.exists():
            return list(LABEL_COLUMNS), {}
        try:
            text = self.path.read_text(encoding="utf-8-sig")
        except (OSError, UnicodeDecodeError) as e:
            raise LabelFileError(f"{self.path}: cannot read it as UTF-8 text ({e})") from e
        reader = csv.DictReader(io.StringIO(text))
        header = [h.strip() for h in reader.fieldnames or []]
        missing = [c for c in LABEL_COLUMNS if c not in header]
        if missing:
            raise LabelFileError(
                f"{self.path}: not a labels file (missing column(s) {', '.join(missing)}); "
                "pass another --labels file"
            )
        reader.fieldnames = header
        rows: dict[str, dict[str, str]] = {}
        for row in reader:
            image = (row.get("image") or "").strip()
            if image:
                key = Path(os.path.normpath(image)).as_posix()
                rows[key] = {k: v or "" for k, v in row.items() if k is not None}
        return header, rows

    def _write(self, header: Sequence[str], rows: Iterable[dict[str, str]]) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(
            dir=self.path.parent, prefix=f".{self.path.name}.", suffix=".tmp"
        )
        try:
            with os.fdopen(fd, "w", newline="", encoding="utf-8") as fh:
                writer = csv.DictWriter(fh, header, lineterminator="\n", extrasaction="ignore")
                writer.writeheader()
                for row in rows:
                    writer.writerow(row)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, self.path)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise


@contextlib.contextmanager
def _folder_lock(folder: Path) -> Iterator[None]:
    try:
        import fcntl
    except ImportError:  # not POSIX: the in-process lock is all there is
        yield
        return
    folder.mkdir(parents=True, exist_ok=True)
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)
