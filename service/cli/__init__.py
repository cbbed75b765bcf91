"""The ``narxwatch`` command line."""

from __future__ import annotations

import atexit
import gc
import sys
from importlib import import_module

import typer

from models.blas import one_blas_thread
from models.errors import InputError
from service.cli.console import fail
from service.errors import DatabaseNotReadyError, SettingsError

# Each command's module and attribute: a command (a function) or a group of them (a Typer app).
# Only the module of the command being run is imported — `narxwatch refine` does not load the
# server's stack, nor `narxwatch serve` the refinement's — which takes about a second off every
# invocation; `--help` and an unknown command load them all, to list them.
COMMANDS = {
    "simulate": ("service.cli.simulate", "simulate"),
    "train": ("service.cli.train", "app"),
    "select": ("service.cli.select", "select"),
    "inspect": ("service.cli.inspect", "inspect"),
    "refine": ("service.cli.refine", "refine_command"),
    "reproduce": ("service.cli.reproduce", "reproduce"),
    "serve": ("service.cli.server", "serve"),
    "worker": ("service.cli.server", "worker"),
    "db": ("service.cli.server", "db_app"),
    "keys": ("service.cli.server", "keys_app"),
    "demo-seed": ("service.cli.server", "demo_seed"),
}


def build_app(command: str | None = None) -> typer.Typer:
    """The ``narxwatch`` application with ``command`` alone, or every command when it names none."""
    app = typer.Typer(
        name="narxwatch",
        help="Condition monitoring of vibrating structures with NARX and functional NARX models.",
        no_args_is_help=True,
        pretty_exceptions_enable=False,
        add_completion=False,
        rich_markup_mode=None,  # help texts hold units like [m], which rich markup would swallow
    )

    @app.callback()
    def narxwatch() -> None:
        """Condition monitoring of vibrating structures with NARX and functional NARX models."""

    for name, (module, attribute) in COMMANDS.items():
        if command in (None, name):
            target = getattr(import_module(module), attribute)
            if isinstance(target, typer.Typer):
                app.add_typer(target, name=name)
            else:
                app.command(name)(target)
    return app


def main() -> None:
    """Console-script entry point: input errors, invalid settings and a database not ready end
    with their message, not a traceback."""
    # Before a command's module loads numpy, which neither this module nor what it imports does
    # (tests/test_layers.py); `narxwatch serve`'s workers inherit the environment.
    one_blas_thread()
    # At exit, before the interpreter's last collections: they need not walk every object the
    # command loaded (numpy, scipy, numba, SQLAlchemy) to free memory the process gives back as
    # it ends. A stopped worker or server spent seconds on them before it exited.
    atexit.register(gc.freeze)
    try:
        args = files_after_options(sys.argv[1:])
        build_app(args[0] if args and args[0] in COMMANDS else None)(args=args)
    except (InputError, DatabaseNotReadyError, SettingsError) as exc:
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
