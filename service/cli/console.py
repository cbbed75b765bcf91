"""Shared console output for the command line."""

from __future__ import annotations

import sys
from typing import NoReturn

from rich.console import Console
from rich.progress import Progress, ProgressColumn

# A pipe or file gets 120 columns: rich's 80 would fold the study's tables in two.
stdout = Console(soft_wrap=True, width=None if sys.stdout.isatty() else 120)
stderr = Console(stderr=True)

EXIT_INPUT_ERROR = 2


def transient_progress(*columns: ProgressColumn) -> Progress:
    """A progress display of these ``columns`` on the terminal's stderr, gone once done: on a pipe
    or a file (a script, a log) it shows nothing, so that only the command's result is written."""
    return Progress(*columns, console=stderr, transient=True, disable=not stderr.is_terminal)


def fail(message: str) -> NoReturn:
    stderr.print(f"[bold red]error:[/bold red] {message}", highlight=False, soft_wrap=True)
    raise SystemExit(EXIT_INPUT_ERROR)
