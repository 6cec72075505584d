"""Saving and loading learned segmenters: one JSON header line, then equinox's serialised leaves.

The file is ``{"format": "sinkjax-segmenter", "version": 1, "kind": "cnn", "hyper": {...},
...}\\n`` followed by :func:`equinox.tree_serialise_leaves` of the model (NumPy ``.npy`` records,
float32). The header names what rebuilds the skeleton (:func:`sinkjax.learn.segmenters.build`)
and may carry a ``report`` of how the model was trained. Anything else, a truncated or edited
file, a newer version, gives :class:`SegmenterFileError` saying what is wrong with which file.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..rig import RigError
from .segmenters import KINDS, LearnedSegmenter, build

FORMAT = "sinkjax-segmenter"
VERSION = 1
# A header longer than this is not ours (and reading it whole would be a waste).
MAX_HEADER_BYTES = 1 << 20


class SegmenterFileError(RigError):
    """A segmenter file that cannot be used; the message names the file and what is wrong."""


def save_segmenter(
    path: str | Path, segmenter: LearnedSegmenter, *, report: dict[str, Any] | None = None
) -> Path:
    """Write ``segmenter`` to ``path`` (header + leaves, see the module docstring); ``report``
    (JSON-able) is kept in the header for whoever reads the file later. Returns the path."""
    header = {
        "format": FORMAT,
        "version": VERSION,
        "kind": segmenter.kind,
        "hyper": dict(segmenter.hyper),
        "n_parameters": segmenter.n_parameters,
        "report": report or {},
    }
    as_f32 = jax.tree_util.tree_map(
        lambda x: jnp.asarray(x, jnp.float32) if eqx.is_array(x) else x, segmenter
    )
    buffer = io.BytesIO()
    eqx.tree_serialise_leaves(buffer, as_f32)
    out = Path(path)
    out.write_bytes(json.dumps(header).encode("utf-8") + b"\n" + buffer.getvalue())
    return out


def read_header(path: str | Path) -> tuple[dict[str, Any], bytes]:
    """The checked header of a segmenter file and the bytes after it. Raises
    :class:`SegmenterFileError` if the file is missing, not a segmenter file, or of an
    unsupported version or kind."""
    p = Path(path)
    if not p.is_file():
        raise SegmenterFileError(f"segmenter file {str(p)!r} does not exist")
    data = p.read_bytes()
    end = data.find(b"\n", 0, MAX_HEADER_BYTES)
    what = f"{p}: not a sinkjax segmenter file (write one with 'sinkjax train')"
    if end < 0:
        raise SegmenterFileError(f"{what}: no header line")
    try:
        header = json.loads(data[:end].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise SegmenterFileError(f"{what}: the first line is not a JSON header") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise SegmenterFileError(f"{what}: its header does not say format {FORMAT!r}")
    if header.get("version") != VERSION:
        raise SegmenterFileError(
            f"{p}: segmenter file version {header.get('version')!r}; this sinkjax reads "
            f"version {VERSION} (upgrade sinkjax, or train the model again)"
        )
    if header.get("kind") not in KINDS or not isinstance(header.get("hyper"), dict):
        raise SegmenterFileError(
            f"{p}: unknown segmenter kind {header.get('kind')!r} (known: {', '.join(KINDS)})"
        )
    return header, data[end + 1 :]


def load_segmenter(path: str | Path) -> LearnedSegmenter:
    """The segmenter saved at ``path`` by :func:`save_segmenter`. Raises
    :class:`SegmenterFileError` for a missing, foreign, truncated or corrupt file."""
    header, payload = read_header(path)
    try:
        skeleton = build(header["kind"], key=0, **header["hyper"])
    except ValueError as e:
        raise SegmenterFileError(f"{path}: header cannot rebuild the model: {e}") from None
    try:
        model = eqx.tree_deserialise_leaves(io.BytesIO(payload), skeleton)
        leaves = jax.tree_util.tree_leaves(eqx.filter(model, eqx.is_array))
        finite = all(bool(np.all(np.isfinite(np.asarray(x)))) for x in leaves)
    except (ValueError, EOFError, OSError, RuntimeError) as e:
        raise SegmenterFileError(
            f"{path}: the parameters are truncated or corrupt ({type(e).__name__}: {e}); "
            "train or copy the file again"
        ) from None
    if not finite:
        raise SegmenterFileError(f"{path}: the parameters hold NaN or infinite values")
    if len(payload) != _payload_size(skeleton):
        raise SegmenterFileError(
            f"{path}: {len(payload)} bytes of parameters where a {header['kind']!r} model with "
            f"{header['hyper']} has {_payload_size(skeleton)}; the file is corrupt"
        )
    return model


def _payload_size(skeleton: LearnedSegmenter) -> int:
    buffer = io.BytesIO()
    eqx.tree_serialise_leaves(buffer, skeleton)
    return len(buffer.getvalue())
