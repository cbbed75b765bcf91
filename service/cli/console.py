"""Shared console output for the command line."""

from __future__ import annotations

from typing import NoReturn

from rich.console import Console

stdout = Console(soft_wrap=True)
stderr = Console(stderr=True)

EXIT_INPUT_ERROR = 2


def fail(message: str) -> NoReturn:
    stderr.print(f"[bold red]error:[/bold red] {message}", highlight=False, soft_wrap=True)
    raise SystemExit(EXIT_INPUT_ERROR)


def parse_assignments(items: list[str], what: str) -> dict[str, float]:
    """``NAME=VALUE`` strings to a dict of floats, refusing anything else with a clear message."""
    values: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            if not sep:
                raise ValueError
            values[name.strip()] = float(value)
        except ValueError:
            fail(f"cannot read {what} {item!r}: write NAME=NUMBER")
    return values
