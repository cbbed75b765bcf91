"""Shared console output for the command line."""

from __future__ import annotations

import sys
from typing import NoReturn

from rich.console import Console

# A pipe or file gets 120 columns: rich's 80 would fold the study's tables in two.
stdout = Console(soft_wrap=True, width=None if sys.stdout.isatty() else 120)
stderr = Console(stderr=True)

EXIT_INPUT_ERROR = 2


def fail(message: str) -> NoReturn:
    stderr.print(f"[bold red]error:[/bold red] {message}", highlight=False, soft_wrap=True)
    raise SystemExit(EXIT_INPUT_ERROR)
