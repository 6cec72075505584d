"""PATH arguments -> recordings, each with its own rig (docs/conventions.md §2, §3).

A PATH is an image file, a directory of images (sorted by name, not recursive) or a video file.
A :class:`Recording` is one camera set-up: a directory, a video, or the image files given one by
one from the same folder (consecutive on the command line). Each recording is measured with its
own rig: the ``rig.toml`` in its directory (beside the video, beside the images), else ``--rig``,
else the command-line fields alone; command-line fields then override single fields everywhere.
So one command over N recordings gives exactly the rows of N separate commands.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..rig import Rig, RigError, read_rig_toml, rig_from_dict
from .image_file import (
    IMAGE_EXTENSIONS as IMAGE_EXTENSIONS,
    VIDEO_EXTENSIONS as VIDEO_EXTENSIONS,
    is_image_path as is_image_path,
    is_video_path as is_video_path,
)

log = logging.getLogger("sinkjax")

RIG_FILENAME = "rig.toml"


class InputError(ValueError):
    """A PATH argument is unusable (missing, unsupported, empty); the message says what to do."""


@dataclass(frozen=True)
class Source:
    """One input file. ``name`` is its ``image`` column: the PATH as given joined with the file."""

    kind: str  # "image" or "video"
    path: Path
    name: str


@dataclass(frozen=True)
class RigOverrides:
    """Rig fields given on the command line; each that is not None overrides every recording's."""

    wheel_radius_mm: float | None = None
    confidence_rect: tuple[int, int, int, int] | None = None
    travel: str | None = None
    encoding: str | None = None

    def as_dict(self) -> dict[str, Any]:
        flags: dict[str, Any] = {}
        if self.wheel_radius_mm is not None:
            flags["wheel_radius_mm"] = float(self.wheel_radius_mm)
        if self.confidence_rect is not None:
            flags["confidence_rect"] = list(self.confidence_rect)
        if self.travel is not None:
            flags["travel"] = self.travel
        if self.encoding is not None:
            flags["encoding"] = self.encoding
        return flags


@dataclass(frozen=True)
class Recording:
    """One camera set-up: its files in order, the folder its rig is looked up in, and its rig.

    ``rig`` is None until :func:`assign_rigs` (or :func:`open_recordings`) fills it;
    ``rig_source`` says where it came from (a file, ``--rig``, the command line).
    """

    name: str
    folder: Path
    sources: tuple[Source, ...]
    rig: Rig | None = field(default=None, compare=False)
    rig_source: str = ""

    @property
    def own_rig_file(self) -> Path | None:
        """The ``rig.toml`` of this recording's folder, if there is one."""
        path = self.folder / RIG_FILENAME
        return path if path.is_file() else None


@dataclass(frozen=True)
class Inputs:
    """Expanded PATH arguments: the recordings in input order (their files in order)."""

    recordings: tuple[Recording, ...]

    @property
    def sources(self) -> tuple[Source, ...]:
        return tuple(s for rec in self.recordings for s in rec.sources)

    @property
    def directory_rigs(self) -> tuple[Path, ...]:
        """The rig files the recordings would use, in input order (duplicates kept)."""
        return tuple(p for rec in self.recordings if (p := rec.own_rig_file) is not None)


def expand_paths(paths: Sequence[str | Path]) -> Inputs:
    """Expand PATH arguments in order into recordings of image and video sources.

    Directories contribute their images sorted by file name (hidden files skipped, not
    recursive). Consecutive image files from one folder form one recording. Raises InputError
    for a PATH that does not exist, a file that is neither an image nor a video, or when no
    frames at all are left.
    """
    if not paths:
        raise InputError("no PATH given; pass image files, directories of images or videos")
    recordings: list[Recording] = []
    loose: list[Source] = []  # image files given one by one, from the same folder

    def close_loose() -> None:
        if loose:
            folder = loose[0].path.parent
            recordings.append(Recording(str(folder), folder, tuple(loose)))
            loose.clear()

    for arg in paths:
        given = str(arg)
        p = Path(given)
        if p.is_dir():
            close_loose()
            found = _images_in(p, given)
            if not found:
                log.warning(
                    "directory %r contains no images (%s); nothing taken from it",
                    given,
                    ", ".join(IMAGE_EXTENSIONS),
                )
                continue
            recordings.append(Recording(given, p, tuple(found)))
        elif p.is_file():
            if is_image_path(p):
                if loose and loose[0].path.parent != p.parent:
                    close_loose()
                loose.append(Source("image", p, given))
            elif is_video_path(p):
                close_loose()
                recordings.append(Recording(given, p.parent, (Source("video", p, given),)))
            else:
                hint = ""
                if p.name == RIG_FILENAME:
                    hint = f"; to use it pass --rig {given} (or pass its directory as PATH)"
                raise InputError(
                    f"{given!r} is neither an image ({', '.join(IMAGE_EXTENSIONS)}) nor a video "
                    f"({', '.join(VIDEO_EXTENSIONS)}){hint}"
                )
        elif p.exists():
            raise InputError(f"{given!r} is not a regular file or directory")
        elif p.is_symlink():
            raise InputError(f"{given!r} is a broken symbolic link (to {os.readlink(p)!r})")
        else:
            raise InputError(f"{given!r} does not exist; check the path")
    close_loose()
    if not recordings:
        raise InputError(
            "no images or videos found in the given PATHs; a directory must contain image files "
            f"({', '.join(IMAGE_EXTENSIONS)}) directly (subdirectories are not searched)"
        )
    return Inputs(tuple(recordings))


def _images_in(directory: Path, given: str) -> list[Source]:
    entries = sorted(os.listdir(directory))
    images = [
        Source("image", directory / n, os.path.join(given, n))
        for n in entries
        if not n.startswith(".") and is_image_path(n) and _file_or_dangling(directory / n)
    ]
    videos = [n for n in entries if is_video_path(n)]
    if videos:
        log.warning(
            "directory %r: ignored %d video file(s) (%s); pass videos as PATHs themselves",
            given,
            len(videos),
            videos[0] if len(videos) == 1 else f"{videos[0]}, ...",
        )
    return images


def _file_or_dangling(path: Path) -> bool:
    # A broken symbolic link is an input that went missing: it gets a row saying so, not silence.
    return path.is_file() or (path.is_symlink() and not path.exists())


def parse_rect(text: str) -> tuple[int, int, int, int]:
    """``"X,Y,W,H"`` -> four ints. Raises RigError with the expected form."""
    parts = [t.strip() for t in text.replace(" ", ",").split(",") if t.strip()]
    try:
        values = tuple(int(t) for t in parts)
    except ValueError:
        values = ()
    if len(values) != 4:
        raise RigError(
            f"--confidence-rect expects four integers X,Y,W,H (pixels), e.g. 300,120,40,30; "
            f"got {text!r}"
        )
    return values  # type: ignore[return-value]


_NO_RIG = (
    "pass --rig RIG.toml, or put a rig.toml in the recording's folder, or pass "
    "--wheel-radius-mm R and --confidence-rect X,Y,W,H (the rim radius in mm and a pixel "
    "rectangle that always shows the wheel face)"
)


def _build_rig(file: Path | None, overrides: RigOverrides) -> tuple[Rig, str]:
    """The rig from ``file`` (or none) with the overrides applied, and where it came from."""
    flags = overrides.as_dict()
    data: dict[str, Any] = read_rig_toml(file) if file is not None else {}
    source = str(file) if file is not None else "command line"
    if file is not None and flags:
        source += " with command-line overrides"
    data.update(flags)
    return rig_from_dict(data, source=source), source


def assign_rigs(
    inputs: Inputs,
    *,
    rig_path: str | Path | None = None,
    overrides: RigOverrides = RigOverrides(),
) -> Inputs:
    """``inputs`` with every recording's rig filled in (see the module docstring for the rule).

    Raises RigError (naming the recording and what to pass) before any frame is read.
    """
    default: Path | None = None
    if rig_path is not None:
        default = Path(rig_path)
        if not default.is_file():
            raise RigError(f"rig file {str(rig_path)!r} does not exist; check the --rig path")
    built: dict[Path | None, tuple[Rig, str]] = {}
    out: list[Recording] = []
    for rec in inputs.recordings:
        file = rec.own_rig_file or default
        if file is None and not overrides.as_dict():
            raise RigError(f"no rig for {rec.name!r}: {_NO_RIG}")
        if file not in built:
            built[file] = _build_rig(file, overrides)
        rig, source = built[file]
        if default is not None and file != default:
            log.warning(
                "%s uses its own %s; --rig %s serves only recordings without one",
                rec.name,
                file,
                rig_path,
            )
        out.append(Recording(rec.name, rec.folder, rec.sources, rig, source))
    return Inputs(tuple(out))


def with_rig(inputs: Inputs, rig: Rig, source: str = "given") -> Inputs:
    """``inputs`` with ``rig`` for every recording (an explicit rig overrides their own)."""
    recs = (Recording(r.name, r.folder, r.sources, rig, source) for r in inputs.recordings)
    return Inputs(tuple(recs))


def open_recordings(
    paths: Sequence[str | Path],
    *,
    rig_path: str | Path | None = None,
    overrides: RigOverrides = RigOverrides(),
) -> Inputs:
    """:func:`expand_paths` then :func:`assign_rigs`: the recordings of a run, each with its rig."""
    return assign_rigs(expand_paths(paths), rig_path=rig_path, overrides=overrides)


def resolve_rig(
    inputs: Inputs | None = None,
    *,
    rig_path: str | Path | None = None,
    wheel_radius_mm: float | None = None,
    confidence_rect: tuple[int, int, int, int] | None = None,
    travel: str | None = None,
) -> Rig:
    """ONE rig: ``rig_path``, else the first recording's own ``rig.toml``, then the flags.

    For callers that measure one recording (the demo, a review page). Runs over several
    recordings use :func:`assign_rigs`. Raises RigError saying what to pass.
    """
    overrides = RigOverrides(wheel_radius_mm, confidence_rect, travel)
    file: Path | None = None
    if rig_path is not None:
        file = Path(rig_path)
        if not file.is_file():
            raise RigError(f"rig file {str(rig_path)!r} does not exist; check the --rig path")
    elif inputs is not None and inputs.directory_rigs:
        file = inputs.directory_rigs[0]
    if file is None and not overrides.as_dict():
        raise RigError(f"no rig: {_NO_RIG}")
    return _build_rig(file, overrides)[0]
