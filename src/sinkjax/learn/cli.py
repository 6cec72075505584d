"""``sinkjax train``: parse, validate everything, train a segmenter, write it, print a report.

Thin by design (no science here): every labels file, rig and the output path are checked before
any compiling starts, so a bad cell or a missing file stops the command at once.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..calibration.cli import _check_out, _positive_int
from .data import frame_batches, load_labelled, split
from .io import save_segmenter
from .segmenters import KINDS, build
from .train import imitate, train

CLI_HELP = "train a learned wheel segmenter from labelled frames, through the fit; writes FILE"


def add_cli_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of ``sinkjax train`` (conventions §3)."""
    p.add_argument(
        "labels",
        nargs="+",
        metavar="LABELS.csv",
        help="one labels file per recording (columns image,sinkage_mm,theta1_deg,theta2_deg), "
        "each with its recording's rig.toml beside it",
    )
    p.add_argument("--segmenter", choices=KINDS, default="mlp", help="model kind (default: mlp)")
    p.add_argument("--out", required=True, metavar="FILE", help="segmenter file to write")
    p.add_argument(
        "--scratch",
        action="store_true",
        help="the network alone, started by imitating the rigs' default masks (default: a "
        "network that corrects the default segmenter, started where it is)",
    )
    p.add_argument(
        "--rig", metavar="RIG.toml", help="rig for the labels files that have no rig.toml beside"
    )
    p.add_argument("--steps", type=_positive_int, default=100, metavar="N", help="Adam steps (100)")
    p.add_argument(
        "--learning-rate", type=float, default=1e-3, metavar="LR", help="Adam step size (1e-3)"
    )
    p.add_argument(
        "--batch-size", type=_positive_int, default=8, metavar="N", help="frames per step (8)"
    )
    p.add_argument(
        "--held-out",
        type=float,
        default=0.25,
        metavar="F",
        help="fraction of each recording's labelled frames kept out of training to stop early "
        "on (0.25; 0 trains on all and stops on the training loss)",
    )
    p.add_argument(
        "--patience",
        type=_positive_int,
        default=3,
        metavar="N",
        help="stop after N scorings (every --eval-every steps) without improvement (3)",
    )
    p.add_argument(
        "--eval-every", type=_positive_int, default=10, metavar="N", help="score every N steps"
    )
    p.add_argument(
        "--width",
        type=_positive_int,
        metavar="N",
        help="hidden units (mlp) or channels (cnn): default 8, or 16 with --scratch",
    )
    p.add_argument("--seed", type=int, default=0, metavar="S", help="initialisation seed (0)")
    from ..app.cli_estimate import add_cache_option

    add_cache_option(p)


def run_cli(args: argparse.Namespace) -> int:
    """``sinkjax train``: validate everything, start from the default masks, train, save,
    report."""
    from ..app.cli_estimate import setup_compile_cache
    from ..rig import RigError

    if not 0.0 <= args.held_out < 1.0:
        raise RigError(f"--held-out must be in [0, 1), got {args.held_out}")
    out = Path(args.out)
    labels = [Path(p) for p in args.labels]
    _check_out(out, labels)
    recordings = load_labelled(labels, args.rig)
    for rec in recordings:
        _check_out(out, [Path(rec.name).parent / n for n in rec.frames.names])
    training, held = split(recordings, args.held_out, seed=args.seed)
    n_train = sum(len(r) for r in training)
    n_held = sum(len(r) for r in held)
    n_cells = int(sum(np.isfinite(r.frames.targets).sum() for r in training))
    print(
        f"training a {args.segmenter} segmenter on {n_train} frames ({n_cells} measured values) "
        f"from {len(recordings)} recording(s); {n_held} held out to stop early on"
    )
    hyper = (
        {}
        if args.width is None
        else {"hidden" if args.segmenter == "mlp" else "channels": args.width}
    )
    batches, held_batches = frame_batches(training), frame_batches(held)
    setup_compile_cache(args)
    start = build(args.segmenter, key=args.seed, residual=int(not args.scratch), **hyper)
    if args.scratch:
        seg, ce = imitate(start, batches, seed=args.seed)
        print(f"start: imitated the rigs' default masks (pixel cross-entropy {ce:.3f})")
    else:
        seg = start
        print("start: the default segmenter's mask, corrected by a network that starts at zero")
    result = train(
        seg,
        batches,
        held_batches,
        steps=args.steps,
        learning_rate=args.learning_rate,
        batch_size=args.batch_size,
        eval_every=args.eval_every,
        patience=args.patience,
        seed=args.seed,
        progress=True,
    )
    report = result.report() | {"labels": [str(p) for p in labels]}
    try:
        save_segmenter(out, result.segmenter, report=report)
    except OSError as e:
        raise RigError(f"cannot write {str(out)!r}: {e.strerror or e}") from e
    print(result.summary())
    print(f"wrote {out}; measure with: sinkjax estimate IMAGES --segmenter {out}")
    return 0
