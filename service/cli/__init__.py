"""The ``narxwatch`` command line."""

from __future__ import annotations

import sys

import typer

from models.errors import InputError
from service.cli import inspect, refine, reproduce, select, server, simulate, train
from service.cli.console import fail
from service.migrate import DatabaseNotReadyError

app = typer.Typer(
    name="narxwatch",
    help="Condition monitoring of vibrating structures with NARX and functional NARX models.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    rich_markup_mode=None,  # help texts hold units like [m], which rich markup would swallow
)
app.command("simulate")(simulate.simulate)
app.add_typer(train.app, name="train")
app.command("select")(select.select)
app.command("inspect")(inspect.inspect)
app.command("refine")(refine.refine_command)
app.command("reproduce")(reproduce.reproduce)
app.command("serve")(server.serve)
app.command("worker")(server.worker)
app.add_typer(server.db_app, name="db")
app.add_typer(server.keys_app, name="keys")
app.command("demo-seed")(server.demo_seed)


def main() -> None:
    """Console-script entry point: input errors and a database not ready end with their message,
    not a traceback."""
    try:
        app(args=files_after_options(sys.argv[1:]))
    except (InputError, DatabaseNotReadyError) as exc:
        fail(str(exc))


# Options that take every file after them, up to the next option: click gives an option one
# value, so `refine EST… --validate V1 V2` would otherwise fit on V2 as silently as on EST.
MANY_FILES = {"refine": "--validate"}


def files_after_options(args: list[str]) -> list[str]:
    """``args`` with ``--validate V1 V2`` of ``refine`` written as ``--validate V1 --validate V2``."""
    option = MANY_FILES.get(args[0]) if args else None
    if option is None:
        return args
    written: list[str] = []
    taking = False
    for arg in args:
        if arg == "--":
            taking = False
        elif arg.startswith("-"):
            taking = arg.split("=", 1)[0] == option
        elif taking and written[-1] != option:
            written.append(option)
        written.append(arg)
    return written
