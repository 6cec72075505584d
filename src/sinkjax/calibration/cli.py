"""``sinkjax calibrate``: parse, validate everything, calibrate, write the rig, print a summary.

Thin by design (no science here): labels and rig are checked before any work starts, so a bad
cell or a missing file stops the command at once with the row, column or path to fix.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..rig import RigError, load_rig, save_rig
from .labels import read_labels
from .optimise import calibrate

CLI_HELP = "tune the segmentation thresholds to a few labelled frames; writes a rig file"


def add_cli_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of ``sinkjax calibrate`` (conventions §3)."""
    p.add_argument(
        "labels",
        metavar="LABELS.csv",
        help="columns image,sinkage_mm,theta1_deg,theta2_deg; image paths relative to its "
        "folder; empty cell = not measured",
    )
    p.add_argument(
        "--rig", metavar="RIG.toml", help="rig to start from (default: rig.toml beside LABELS.csv)"
    )
    p.add_argument("--out", required=True, metavar="CALIBRATED.toml", help="rig file to write")
    p.add_argument(
        "--steps",
        type=_steps,
        default=50,
        metavar="N",
        help="Adam steps after the grid search (default: 50; 0: the grid search alone, which "
        "compiles no gradient and is faster)",
    )
    p.add_argument(
        "--augment",
        action="store_true",
        help="also calibrate under random lighting changes (slower; thresholds that survive "
        "the lamp moving)",
    )
    p.add_argument("--seed", type=int, default=0, metavar="S", help="augmentation seed (0)")
    from ..app.cli_estimate import add_cache_option

    add_cache_option(p)


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _steps(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 (the grid search alone) or more, got {value}")
    return value


def _check_out(out: Path, inputs: list[Path]) -> None:
    """Raise RigError if the calibrated rig cannot be written to ``out`` or would replace one of
    ``inputs``: checked before any work, not after minutes of it."""
    from ..app.run import check_writable_folder

    if not out.parent.is_dir():
        raise RigError(f"cannot write {str(out)!r}: folder {str(out.parent)!r} does not exist")
    if out.is_dir():
        raise RigError(f"--out {str(out)!r} is a folder; name the rig file to write")
    for path in inputs:
        if path.exists() and out.resolve() == path.resolve():
            raise RigError(
                f"--out {str(out)!r} is one of the inputs ({path}); write the calibrated rig to "
                "another file"
            )
    try:
        check_writable_folder(out.parent, "--out")
    except ValueError as e:
        raise RigError(str(e)) from e


def run_cli(args: argparse.Namespace) -> int:
    """``sinkjax calibrate``: validate everything, calibrate, write the rig, print a summary."""
    labels = Path(args.labels)
    rig_path = Path(args.rig) if args.rig else labels.parent / "rig.toml"
    out = Path(args.out)
    _check_out(out, [labels, rig_path])
    if not rig_path.is_file():
        raise RigError(
            f"rig file {str(rig_path)!r} does not exist; pass --rig RIG.toml or put the rig.toml "
            "of these frames next to the labels file"
        )
    rig = load_rig(rig_path)
    frames = read_labels(labels, rig)
    _check_out(out, [labels.parent / name for name in frames.names])
    from ..app.cli_estimate import setup_compile_cache

    # A second calibration of a size already seen (any rig) loads its compiled loss from disk.
    setup_compile_cache(args)
    n_cells = int(np.isfinite(frames.targets).sum())
    print(f"calibrating {rig_path} on {len(frames.names)} frames ({n_cells} measured values)")
    if frames.rim_images is not None:
        print(
            f"rim circle found from the first {len(frames.rim_images)} frames of the recording in "
            f"{labels.parent}, as `sinkjax estimate {labels.parent}` will find it"
        )
    result = calibrate(
        frames, rig, steps=args.steps, augment=args.augment, seed=args.seed, progress=True
    )
    comment = (
        f"calibrated by `sinkjax calibrate {labels.name}` from {rig_path.name}: "
        f"{len(frames.names)} frames, loss {result.loss_before:.4g} -> "
        f"{result.loss_after:.4g}{', augmented' if args.augment else ''}"
    )
    try:
        save_rig(result.rig, out, comment=comment)
    except OSError as e:
        raise RigError(f"cannot write {str(out)!r}: {e.strerror or e}") from e
    print(result.summary())
    print(
        f"wrote {out}; measure with it: save it as the rig.toml beside the recording's images "
        f"(a recording's own rig.toml wins over --rig), or, for recordings without one, "
        f"sinkjax estimate IMAGES --rig {out}"
    )
    return 0
