"""``--resume``: make an existing results CSV ready to be appended to, or refuse it untouched."""

from __future__ import annotations

import csv
import os
from pathlib import Path

from .results import COLUMNS
from .smoothing import SMOOTH_COLUMNS


class ResumeError(ValueError):
    """``resume`` was asked for, but the output file is not a results CSV this run can extend."""


def _truncate_partial_row(path: Path) -> None:
    """Cut a row that a killed run left half-written (no final newline); it is measured again."""
    with open(path, "rb+") as f:
        f.seek(0, os.SEEK_END)
        size = f.tell()
        if size == 0:
            return
        f.seek(size - 1)
        if f.read(1) == b"\n":
            return
        # Rows are short: look back a block at a time for the last newline.
        end = size
        while end > 0:
            start = max(0, end - 65536)
            f.seek(start)
            block = f.read(end - start)
            cut = block.rfind(b"\n")
            if cut != -1:
                f.truncate(start + cut + 1)
                return
            end = start
        f.truncate(0)


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


def prepare_resume(out_csv: str | Path) -> set[str]:
    """Make ``out_csv`` ready to be appended to; return the image names it already has.

    A missing or empty file is a fresh start (empty set; the caller writes the header). A row
    left half-written is removed; smoothed columns from an earlier ``smooth`` are dropped (they
    are recomputed over the whole file). Raises ResumeError for a file with another header.
    """
    path = Path(out_csv)
    if not path.is_file():
        return set()
    _truncate_partial_row(path)
    with open(path, newline="", encoding="utf-8", errors="surrogateescape") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header is None:
            return set()
        if tuple(header) not in (COLUMNS, (*COLUMNS, *SMOOTH_COLUMNS)):
            raise ResumeError(
                f"cannot resume into {path}: it is not a sinkjax results CSV (its header is "
                f"{','.join(header)[:80]!r}); pass another --out, or drop --resume to overwrite it"
            )
        done = {row[0] for row in reader if row}
    if len(header) != len(COLUMNS):
        _strip_columns(path, len(COLUMNS))
    return done
