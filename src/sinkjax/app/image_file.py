"""One image file -> RGB uint8 pixels, header first (docs/conventions.md §3, limits).

:func:`read_image` never reads more of a file than it has decided to decode: it looks at the
file's size, then at its header (PNG IHDR, JPEG SOF, BMP info header, TIFF first IFD), and
refuses a file over :data:`MAX_FILE_BYTES` or a picture over :data:`MAX_PIXELS` before the body
is read, as Pillow's decompression-bomb limit does. A JPEG that the decoder reports as corrupt
("Corrupt JPEG data", "Premature end of JPEG file") is refused too, with the decoder's words:
libjpeg decodes such files to a damaged picture and only prints a warning on stderr, which is
captured around the decode (a frame measured on it would look fine and be wrong).
"""

from __future__ import annotations

import logging
import os
import struct
import tempfile
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np

log = logging.getLogger("sinkjax")

# A file larger than this is refused unread (1 GiB: far above any camera frame, well below the
# memory of a machine that runs sinkjax).
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".m4v")
MAX_FILE_BYTES = 1 << 30
# A picture with more pixels than this is refused from its header, undecoded (Pillow's
# MAX_IMAGE_PIXELS: about 0.27 GB as RGB; a 12000 x 12000 px claim is refused).
MAX_PIXELS = 89_478_485
# Bytes read for the header; JPEGs may need more (large EXIF blocks), read segment by segment.
_HEAD_BYTES = 64 * 1024


class BadImageError(ValueError):
    """The file is an image, but one sinkjax will not measure (too large, odd pixel type)."""


_SIGNATURES = (
    (b"\x89PNG\r\n\x1a\n", "PNG"),
    (b"\xff\xd8", "JPEG"),
    (b"BM", "BMP"),
    (b"II*\x00", "TIFF"),
    (b"MM\x00*", "TIFF"),
)


def format_of(data: bytes) -> str | None:
    """ "PNG", "JPEG", "BMP" or "TIFF" from a file's first bytes; None for anything else."""
    for magic, name in _SIGNATURES:
        if data.startswith(magic):
            return name
    return None


def _png_size(head: bytes) -> tuple[int, int] | None:
    if len(head) < 24 or head[12:16] != b"IHDR":
        return None
    return struct.unpack(">II", head[16:24])


def _bmp_size(head: bytes) -> tuple[int, int] | None:
    if len(head) < 26:
        return None
    if struct.unpack("<I", head[14:18])[0] == 12:  # OS/2 BITMAPCOREHEADER: 16-bit sides
        return struct.unpack("<HH", head[18:22])
    width, height = struct.unpack("<ii", head[18:26])
    return abs(width), abs(height)  # a negative height is a top-down bitmap


def _tiff_size(f: BinaryIO, head: bytes) -> tuple[int, int] | None:
    order = "<" if head[:2] == b"II" else ">"
    f.seek(struct.unpack(order + "I", head[4:8])[0])
    count_bytes = f.read(2)
    if len(count_bytes) < 2:
        return None
    n = struct.unpack(order + "H", count_bytes)[0]
    entries = f.read(12 * n)
    sides: dict[int, int] = {}
    for i in range(len(entries) // 12):
        tag, kind = struct.unpack(order + "HH", entries[12 * i : 12 * i + 4])
        if tag in (256, 257) and kind in (3, 4):  # ImageWidth, ImageLength as SHORT or LONG
            fmt = "H" if kind == 3 else "I"
            sides[tag] = struct.unpack(
                order + fmt, entries[12 * i + 8 : 12 * i + 8 + (2 if kind == 3 else 4)]
            )[0]
    if 256 not in sides or 257 not in sides:
        return None
    return sides[256], sides[257]


# Start-of-frame markers (baseline, progressive, lossless, arithmetic): they carry the size.
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _jpeg_size(f: BinaryIO) -> tuple[int, int] | None:
    pos = 2
    while True:
        f.seek(pos)
        marker = f.read(4)
        if len(marker) < 4 or marker[0] != 0xFF:
            return None
        if marker[1] == 0xFF:  # fill byte
            pos += 1
            continue
        if 0xD0 <= marker[1] <= 0xD9 or marker[1] == 0x01:
            pos += 2
            continue
        if marker[1] == 0xDA:  # scan data before any frame header
            return None
        length = struct.unpack(">H", marker[2:4])[0]
        if marker[1] in _SOF:
            frame = f.read(5)
            if len(frame) < 5:
                return None
            height, width = struct.unpack(">HH", frame[1:5])
            return width, height
        pos += 2 + length


def image_size(f: BinaryIO, fmt: str, head: bytes) -> tuple[int, int] | None:
    """(width, height) px from the header of an open image file of format ``fmt``; None if the
    header does not say (damaged or truncated)."""
    if fmt == "PNG":
        return _png_size(head)
    if fmt == "BMP":
        return _bmp_size(head)
    if fmt == "TIFF":
        return _tiff_size(f, head)
    return _jpeg_size(f)


def is_image_path(path: str | Path) -> bool:
    """Whether ``path``'s extension is an image's (:data:`IMAGE_EXTENSIONS`)."""
    return os.path.splitext(str(path))[1].lower() in IMAGE_EXTENSIONS


def is_video_path(path: str | Path) -> bool:
    """Whether ``path``'s extension is a video's (:data:`VIDEO_EXTENSIONS`)."""
    return os.path.splitext(str(path))[1].lower() in VIDEO_EXTENSIONS


def header_size(path: str | Path) -> tuple[int, int] | None:
    """(width, height) px of the image file at ``path`` from its header alone; None if it cannot
    be read or is not a PNG, JPEG, BMP or TIFF with a size in its header."""
    try:
        with open(path, "rb") as f:
            head = f.read(_HEAD_BYTES)
            fmt = format_of(head)
            return None if fmt is None else image_size(f, fmt, head)
    except (OSError, struct.error):
        return None


def check_header(f: BinaryIO) -> tuple[str, int]:
    """The format and size (bytes) of the open image file ``f``, from its header alone.

    Raises OSError if it cannot be read, BadImageError if it is over :data:`MAX_FILE_BYTES` or
    claims more than :data:`MAX_PIXELS`, and ValueError if it is empty, not a PNG, JPEG, BMP or
    TIFF, or its header gives no size.
    """
    size = os.fstat(f.fileno()).st_size
    if size == 0:
        raise ValueError("empty file (0 bytes)")
    head = f.read(_HEAD_BYTES)
    fmt = format_of(head)
    if fmt is None:
        raise ValueError("not an image: the content is not PNG, JPEG, BMP or TIFF")
    if size > MAX_FILE_BYTES:
        raise BadImageError(
            f"file too large: {size} bytes, over the limit of {MAX_FILE_BYTES} bytes "
            "(MAX_FILE_BYTES); not read"
        )
    try:
        sides = image_size(f, fmt, head)
    except struct.error:
        sides = None
    if sides is None:
        raise ValueError(f"corrupt {fmt}: its header gives no image size ({size} bytes)")
    width, height = sides
    if width * height > MAX_PIXELS:
        raise BadImageError(
            f"image too large: the {fmt} header claims {width}x{height} px "
            f"({width * height / 1e6:.1f} megapixels), over the limit of "
            f"{MAX_PIXELS / 1e6:.1f} megapixels (MAX_PIXELS); not decoded"
        )
    return fmt, size


def to_rgb8(array: np.ndarray, *, bgr: bool = True) -> np.ndarray:
    """Any decoded image -> RGB uint8 (H, W, 3).

    Grey (H, W) or (H, W, 1) is repeated over 3 channels; grey+alpha keeps the grey; a 4th
    (alpha) channel is dropped, not composited; uint16 is scaled by 255/65535 over the FULL
    16-bit range (no per-frame stretch, which would shift colours between frames). ``bgr``: the
    input is in OpenCV's BGR(A) order. Raises BadImageError for other shapes or pixel types.
    """
    a = np.asarray(array)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 2, 3, 4) or a.shape[0] < 1 or a.shape[1] < 1:
        raise BadImageError(f"unsupported image shape {a.shape}; expected (H, W) or (H, W, 1-4)")
    if a.dtype == np.uint16:
        a = ((a.astype(np.uint32) * 255 + 32767) // 65535).astype(np.uint8)
    elif a.dtype != np.uint8:
        raise BadImageError(f"unsupported pixel type {a.dtype}; convert the image to 8 or 16 bit")
    channels = a.shape[2]
    if channels <= 2:
        rgb = np.repeat(a[:, :, :1], 3, axis=2)
    else:
        rgb = a[:, :, :3]
        if bgr:
            rgb = rgb[:, :, ::-1]
    return np.ascontiguousarray(rgb)


def _jpeg_complete(data: bytes) -> bool:
    """True if the JPEG's first scan is followed by an end-of-image marker.

    Walks the marker segments up to the first SOS so that an EXIF thumbnail (inside APP1, with
    its own EOI) cannot make a truncated main image look complete. Inside scan data 0xFF is
    byte-stuffed, so an FF D9 after the SOS is a real end marker.
    """
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return False
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker == 0xDA:
            return data.find(b"\xff\xd9", i) != -1
        if 0xD0 <= marker <= 0xD9 or marker == 0x01:
            i += 2
            continue
        i += 2 + int.from_bytes(data[i + 2 : i + 4], "big")
    return False


def read_image(path: str | Path) -> np.ndarray:
    """Read one image file as RGB uint8 (H, W, 3) (see :func:`to_rgb8` for the conversions).

    The header is checked before the body is read (:func:`check_header`). Raises OSError if the
    file cannot be read, BadImageError if it is over a limit or of an unsupported pixel type, and
    ValueError (message in words) if it is empty, truncated, corrupt or not an image.
    """
    with open(path, "rb") as f:
        fmt, size = check_header(f)
        f.seek(0)
        data = f.read(size)  # not more: the file may be growing
    if fmt == "PNG" and b"IEND" not in data[-16:]:
        raise ValueError(f"truncated PNG ({len(data)} bytes, no end chunk)")
    if fmt == "JPEG" and not _jpeg_complete(data):
        raise ValueError(f"truncated JPEG ({len(data)} bytes, no end-of-image marker)")
    decoded, warning = _decode(data)
    if decoded is None:
        raise ValueError(f"corrupt {fmt}: OpenCV could not decode it")
    if fmt == "JPEG" and warning:
        # libjpeg still returns a picture, with grey or shifted blocks where the data was bad.
        raise ValueError(f"corrupt JPEG: the decoder reports {warning!r}")
    if warning:
        log.debug("%s: decoder said %r", path, warning)
    return to_rgb8(decoded, bgr=True)


def _decode(data: bytes) -> tuple[np.ndarray | None, str]:
    """cv2.imdecode, and what the codec library printed on stderr meanwhile (one line).

    The codec libraries report damage they decode through (libjpeg's "Corrupt JPEG data") only
    on file descriptor 2, so it is pointed at a temporary file for the call. OpenCV's own log is
    held at errors: per-frame failures are reported by the caller.
    """
    logging_api = getattr(getattr(cv2, "utils", None), "logging", None)
    previous = None
    if logging_api is not None:
        previous = logging_api.getLogLevel()
        logging_api.setLogLevel(logging_api.LOG_LEVEL_ERROR)
    saved = os.dup(2)
    try:
        with tempfile.TemporaryFile() as capture:
            os.dup2(capture.fileno(), 2)
            try:
                decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
            except cv2.error:
                decoded = None
            finally:
                os.dup2(saved, 2)
            capture.seek(0)
            said = capture.read(4096).decode("utf-8", "replace")
    finally:
        os.close(saved)
        if logging_api is not None and previous is not None:
            logging_api.setLogLevel(previous)
    lines = [line.strip() for line in said.splitlines() if line.strip()]
    return decoded, "; ".join(lines)[:300]
