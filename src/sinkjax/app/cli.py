"""The ``sinkjax`` command (docs/conventions.md §3). Thin: parse, validate, call the API, report.

Subcommands live in :data:`COMMANDS` (name -> :class:`Command`); add one by adding an entry.
User errors (bad arguments, unusable rig, nothing readable) print one message and exit 2, never a
traceback.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence

from ..rig import RigError
from .cli_base import (
    EXIT_INTERNAL,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_USAGE,
    Command,
    UsageError,
)
from .cli_estimate import _add_estimate, _run_estimate
from .cli_tools import (
    _add_demo,
    _add_plot,
    _add_smooth,
    _add_synth,
    _run_demo,
    _run_plot,
    _run_smooth,
    _run_synth,
)
from .sources import InputError

__all__ = ["COMMANDS", "EXIT_OK", "EXIT_USAGE", "UsageError", "build_parser", "main"]

# --------------------------------------------------------------------------------------------
# registry and entry point

COMMANDS: dict[str, Command] = {
    "estimate": Command(
        "measure sinkage and angles in images or videos", _add_estimate, _run_estimate
    ),
    "synth": Command("write a synthetic recording with ground truth", _add_synth, _run_synth),
    # calibrate lives in sinkjax.calibration.cli (parse + run), imported when it is used.
    "calibrate": Command(
        "tune the segmentation thresholds to a few labelled frames; writes a rig file",
        lambda p: __import__("sinkjax.calibration.cli", fromlist=["_"]).add_cli_arguments(p),
        lambda a: __import__("sinkjax.calibration.cli", fromlist=["_"]).run_cli(a),
    ),
    # train lives in sinkjax.learn.cli, imported when it is used.
    "train": Command(
        "train a learned wheel segmenter from labelled frames, through the fit",
        lambda p: __import__("sinkjax.learn.cli", fromlist=["_"]).add_cli_arguments(p),
        lambda a: __import__("sinkjax.learn.cli", fromlist=["_"]).run_cli(a),
    ),
    "demo": Command("run the whole job on a built-in synthetic recording", _add_demo, _run_demo),
    "smooth": Command("add Kalman/RTS-smoothed columns to a results CSV", _add_smooth, _run_smooth),
    "plot": Command("plot sinkage and angles over the frames", _add_plot, _run_plot),
    "review": Command(
        "review a run and label frames for calibration in a local web page",
        lambda p: __import__("sinkjax.review.command", fromlist=["_"]).add_cli_arguments(p),
        lambda a: __import__("sinkjax.review.command", fromlist=["_"]).run_cli(a),
    ),
}


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__

    parser = argparse.ArgumentParser(
        prog="sinkjax",
        description="Wheel sinkage and entry/exit angles from images of a rover wheel.",
    )
    parser.add_argument("--version", action="version", version=f"sinkjax {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, command in COMMANDS.items():
        command.add_arguments(sub.add_parser(name, help=command.help, description=command.help))
    return parser


class _TqdmHandler(logging.Handler):
    """Warnings on stderr without tearing a progress bar apart."""

    def emit(self, record: logging.LogRecord) -> None:
        from tqdm import tqdm

        try:
            tqdm.write(f"sinkjax: warning: {record.getMessage()}", file=sys.stderr)
        except Exception:
            self.handleError(record)


def _setup_logging() -> None:
    logger = logging.getLogger("sinkjax")
    if not any(isinstance(h, _TqdmHandler) for h in logger.handlers):
        logger.addHandler(_TqdmHandler(level=logging.WARNING))
    logger.setLevel(logging.WARNING)
    logger.propagate = False


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``sinkjax``; returns the exit code (0 done, 2 unusable arguments or inputs, 1 a bug,
    130 interrupted). No traceback reaches the user unless ``SINKJAX_TRACEBACK`` is set."""
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging()
    try:
        return COMMANDS[args.command].run(args)
    except (UsageError, InputError, RigError) as e:
        print(f"sinkjax {args.command}: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as e:  # a file the command was pointed at (permissions, a full disk, ...)
        where = f"{e.filename}: " if e.filename else ""
        print(f"sinkjax {args.command}: error: {where}{e.strerror or e}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        kept = ""
        if args.command == "estimate":
            kept = f"; the rows finished so far are in {args.out} (finish with --resume)"
        print(f"sinkjax {args.command}: interrupted{kept}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as e:
        # A bug, not the user's input: one line, and the traceback only when asked for.
        if os.environ.get("SINKJAX_TRACEBACK"):
            raise
        print(
            f"sinkjax {args.command}: internal error (please report it): "
            f"{type(e).__name__}: {e}; set SINKJAX_TRACEBACK=1 to see where",
            file=sys.stderr,
        )
        return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(main())
