"""MkDocs hook: the reference pages that are read off the code at every build.

- ``reference/openapi.json``: the HTTP API's OpenAPI document, from the app factory itself;
- ``<!-- generated:settings -->``: every ``NARXWATCH_`` setting of :class:`service.config.Settings`,
  with the comment written above it in ``service/config.py`` (or its ``Field`` description);
- ``<!-- generated:cli -->``: the ``--help`` of every ``narxwatch`` and ``narxwatch-sim`` command;
- ``<!-- generated:paths -->``: a table of the API's paths and what each does.

Generated, not written by hand, so that a setting, a command or a route added to the code appears
here by itself, and a stale page cannot be built.
"""

from __future__ import annotations

import inspect
import json
import re
import sys
import tempfile
from functools import cache
from pathlib import Path
from typing import Literal, get_args, get_origin

from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

OPENAPI = "reference/openapi.json"


@cache
def openapi() -> dict:
    from service.api.app import create_app
    from service.config import Settings

    # The schema does not depend on the database; the app never opens this one.
    with tempfile.TemporaryDirectory() as folder:
        return create_app(Settings(database_url=f"sqlite:///{folder}/unused.db")).openapi()


def on_files(files, config):
    files.append(File.generated(config, OPENAPI, content=json.dumps(openapi(), indent=1)))
    return files


def on_page_markdown(markdown: str, page, config, files) -> str:
    for name, render in (("settings", settings_markdown), ("cli", cli_markdown), ("paths", paths_markdown)):
        marker = f"<!-- generated:{name} -->"
        if marker in markdown:
            markdown = markdown.replace(marker, render())
    return markdown


# Settings ------------------------------------------------------------------------------------------

FIELD_LINE = re.compile(r"^    (\w+): ")
COMMENT_LINE = re.compile(r"^    # ?(.*)$")


GENERIC_WORDS = {"max", "seconds", "bytes", "hours"}


def shares_subject(first: str, name: str, comment: str) -> bool:
    """Whether a field written right under ``first`` without a comment of its own is what
    ``first``'s comment speaks of too: their names share a word, or the comment names it."""
    words = set(first.split("_")) - GENERIC_WORDS
    return bool(words & set(name.split("_"))) or name in comment


def setting_groups() -> list[tuple[str, list[str]]]:
    """The fields of ``Settings`` in source order, grouped under the comment written above them."""
    from service.config import Settings

    groups: list[tuple[str, list[str]]] = []
    comment: list[str] = []
    for line in inspect.getsource(Settings).splitlines():
        if match := COMMENT_LINE.match(line):
            comment.append(match.group(1))
        elif (match := FIELD_LINE.match(line)) and match.group(1) in Settings.model_fields:
            name = match.group(1)
            if not comment and groups and shares_subject(groups[-1][1][0], name, groups[-1][0]):
                groups[-1][1].append(name)
            else:
                groups.append((" ".join(comment), [name]))
            comment = []
        elif not line.strip():
            comment = []
    return groups


def constraint_text(field) -> str:
    words = {"gt": ">", "ge": "≥", "lt": "<", "le": "≤", "min_length": "length ≥", "max_length": "length ≤"}
    parts = []
    for item in field.metadata:
        for attribute, symbol in words.items():
            value = getattr(item, attribute, None)
            if value is not None:
                shown = f"{value:_}".replace("_", " ") if isinstance(value, int) else value
                parts.append(f"{symbol} {shown}")
    return ", ".join(parts)


def default_text(field) -> str:
    from service.config import _data_home

    default = field.default
    if default is None:
        return "unset"
    if isinstance(default, bool):
        return str(default).lower()
    text = json.dumps(default) if isinstance(default, list) else str(default)
    if isinstance(default, int) and not isinstance(default, bool) and default >= 10_000:
        text = f"{default:_}".replace("_", " ")
    # The default paths hold the builder's home: write the rule instead.
    return text.replace(str(_data_home()), "$XDG_DATA_HOME")


def type_text(annotation) -> str:
    if get_origin(annotation) is Literal:
        return " or ".join(f"`{choice}`" for choice in get_args(annotation))
    text = getattr(annotation, "__name__", None) if not getattr(annotation, "__args__", None) else None
    text = text or str(annotation).replace("typing.", "")
    for long, short in (("pydantic.types.", ""), ("pathlib.", ""), ("ipaddress.", ""), ("NoneType", "None")):
        text = text.replace(long, short)
    return text


# For the settings ``service/config.py`` has no comment on: a comment or a ``Field(description=…)``
# written there takes precedence over these.
UNCOMMENTED = {
    "database_url": "The database: a SQLite file in the user's data directory by default, "
    "`postgresql+psycopg://user:password@host/db` in production.",
    "alpha": "α, the significance level of an inspection: its overall false-alarm rate.",
    "lags": "h, the lags of the residuals' Ljung–Box test.",
    "upgrade_on_start": "`narxwatch serve` upgrades the schema as it starts; off, it stops with one line "
    "when the database is missing or not upgraded.",
    "history_page_size": "The page size of a structure's verdict history when the request gives no `limit`.",
}


def settings_markdown() -> str:
    from service.config import Settings

    rows = ["| variable | default | allowed | what it sets |", "|---|---|---|---|"]
    for comment, names in setting_groups():
        for position, name in enumerate(names):
            field = Settings.model_fields[name]
            text = field.description or (comment if position == 0 else "with the setting above")
            text = (text or UNCOMMENTED.get(name, "")).replace("<", "&lt;")
            allowed = ", ".join(filter(None, [type_text(field.annotation), constraint_text(field)]))
            rows.append(
                f"| `NARXWATCH_{name.upper()}` | `{default_text(field)}` | {allowed.replace('|', '&#124;')} "
                f"| {text.replace('|', '&#124;')} |"
            )
    return "\n".join(rows)


# Command line --------------------------------------------------------------------------------------


def commands(command, path: list[str]):
    """Every command under ``command`` (a click command, which Typer may carry a copy of), with its
    path of names."""
    yield path, command
    if hasattr(command, "list_commands"):
        context = command.context_class(command, info_name=" ".join(path))
        for name in command.list_commands(context):
            yield from commands(command.get_command(context, name), [*path, name])


def cli_markdown() -> str:
    import typer

    from service.cli import build_app
    from simulator.client.commands import app as sim_app

    out = []
    for root, app in (("narxwatch", build_app()), ("narxwatch-sim", sim_app)):
        for path, command in commands(typer.main.get_command(app), [root]):
            context = command.context_class(
                command, info_name=" ".join(path), terminal_width=100, max_content_width=100
            )
            level = "#" * min(len(path) + 1, 4)
            out.append(f"{level} `{' '.join(path)}`\n\n```text\n{command.get_help(context)}\n```")
    return "\n\n".join(out)


# HTTP paths ----------------------------------------------------------------------------------------


def operation_text(operation: dict) -> str:
    """The first sentence of the route's docstring, else the name FastAPI made of its function."""
    description = " ".join((operation.get("description") or "").split())
    first = re.split(r"(?<=[.;:])\s", description, maxsplit=1)[0].rstrip(";:")
    return (first or operation.get("summary", "")).replace("|", "&#124;")


def paths_markdown() -> str:
    rows = ["| route | what it does |", "|---|---|"]
    for path, operations in openapi()["paths"].items():
        for method, operation in operations.items():
            rows.append(f"| `{method.upper()} {path}` | {operation_text(operation)} |")
    return "\n".join(rows)
