"""What every ``sinkjax`` subcommand shares: exit codes, the usage error, the command record."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass

EXIT_OK = 0
EXIT_INTERNAL = 1  # a bug: reported in one line, see sinkjax.app.cli.main
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


class UsageError(Exception):
    """An unusable argument or input; printed as ``sinkjax CMD: error: ...``, exit code 2."""


@dataclass(frozen=True)
class Command:
    """A subcommand: its one-line help, how it adds its arguments, and how it runs."""

    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
