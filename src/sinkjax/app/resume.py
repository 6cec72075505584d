"""``--resume``: make an existing results CSV ready to be appended to, or refuse it untouched."""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path

from .results import COLUMNS
from .smoothing import SMOOTH_COLUMNS


class ResumeError(ValueError):
    """``resume`` was asked for, but the output file is not a results CSV this run can extend."""


def _strip_columns(path: Path, n_columns: int) -> None:
    """Rewrite ``path`` keeping its first ``n_columns`` columns (atomically)."""
    tmp = path.with_name(f".{path.name}.resume.tmp")
    with (
        open(path, newline="", encoding="utf-8", errors="surrogateescape") as src,
        open(tmp, "w", newline="", encoding="utf-8", errors="surrogateescape") as dst,
    ):
        writer = csv.writer(dst, lineterminator="\n")
        for row in csv.reader(src):
            writer.writerow(row[:n_columns])
    os.replace(tmp, path)


def _read_header(path: Path) -> tuple[list[str], int] | None:
    """The first line of ``path`` parsed as CSV and the byte offset after it; None for an empty
    file. Raises ResumeError if that line is not complete (no newline within 64 KiB)."""
    with open(path, "rb") as f:
        head = f.read(65536)
    if not head:
        return None
    end = head.find(b"\n")
    if end == -1:
        raise ResumeError(
            f"cannot resume into {path}: it is not a sinkjax results CSV (its first line is "
            f"{head[:80].decode('utf-8', 'replace')!r}...); pass another --out, or drop --resume "
            "to overwrite it"
        )
    try:
        line = head[: end + 1].decode("utf-8", "surrogateescape")
        header = next(csv.reader(io.StringIO(line, newline="")), [])
    except csv.Error:
        header = []
    return header, end + 1


def prepare_resume(out_csv: str | Path) -> set[str]:
    """Make ``out_csv`` ready to be appended to; return the image names it already has.

    A missing or empty file is a fresh start (empty set; the caller writes the header). The
    file is checked whole before it is touched: ResumeError leaves it byte for byte as it was
    (another header, a first line that is not complete, rows that are not CSV). Only then is a
    row left half-written (no final newline) cut off, to be measured again, and smoothed columns
    from an earlier ``smooth`` dropped (they are recomputed over the whole file).
    """
    path = Path(out_csv)
    if not path.is_file():
        return set()
    parsed = _read_header(path)
    if parsed is None:
        return set()
    header, start = parsed
    if tuple(header) not in (COLUMNS, (*COLUMNS, *SMOOTH_COLUMNS)):
        raise ResumeError(
            f"cannot resume into {path}: it is not a sinkjax results CSV (its header is "
            f"{','.join(header)[:80]!r}); pass another --out, or drop --resume to overwrite it"
        )
    data = path.read_bytes()
    cut = data.rfind(b"\n") + 1  # after the last complete row; a partial row follows it
    try:
        rows = list(csv.reader(io.StringIO(data[start:cut].decode("utf-8", "surrogateescape"))))
    except csv.Error as e:
        raise ResumeError(
            f"cannot resume into {path}: its rows are not valid CSV ({e}); pass another --out"
        ) from e
    # Checked: from here on the file is continued, never refused.
    if cut < len(data):
        with open(path, "rb+") as f:
            f.truncate(cut)
    if len(header) != len(COLUMNS):
        _strip_columns(path, len(COLUMNS))
    return {row[0] for row in rows if row}
