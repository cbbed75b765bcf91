"""The ``narxwatch`` and ``narxwatch-sim`` console scripts as a user runs them, and their entry points in
the caller's process."""

from __future__ import annotations

import contextlib
import io
import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path

from service.cli import main
from service.config import get_settings
from simulator.client import main as simulator_main

BIN = Path(sys.executable).parent
NARXWATCH = shutil.which("narxwatch", path=str(BIN))
ENTRY_POINTS = {"narxwatch": main, "narxwatch-sim": simulator_main}
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def run(*args: str, cwd: Path, check: bool = True) -> subprocess.CompletedProcess[str]:
    assert NARXWATCH, "the narxwatch console script is not installed next to this Python"
    result = subprocess.run([NARXWATCH, *args], cwd=cwd, capture_output=True, text=True, timeout=300)
    if check:
        assert result.returncode == 0, result.stderr
    return result


def invoke(
    *args: str,
    cwd: Path,
    check: bool = True,
    script: str = "narxwatch",
    environ: Mapping[str, str] | None = None,
) -> subprocess.CompletedProcess[str]:
    """:func:`run` in this process: the console script's entry point with ``args`` in ``cwd``, its
    exit code and what it wrote. An exception it lets through fails the test, as a traceback
    would. ``script`` names the console script (``narxwatch`` or ``narxwatch-sim``); ``environ`` is
    the environment it runs in instead of this process's (restored after it), as is the handler of
    SIGTERM, which a stream takes to stop as on Ctrl-C. The service's settings, cached for the
    process, are read afresh from the environment before the command and after it."""
    stdout, stderr = io.StringIO(), io.StringIO()
    argv, saved, on_sigterm = sys.argv, dict(os.environ), signal.getsignal(signal.SIGTERM)
    sys.argv = [shutil.which(script, path=str(BIN)) or script, *args]
    if environ is not None:
        os.environ.clear()
        os.environ.update(environ)
    get_settings.cache_clear()
    try:
        with contextlib.chdir(cwd), contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            ENTRY_POINTS[script]()
        code = 0
    except SystemExit as stopped:
        code = stopped.code if isinstance(stopped.code, int) else int(stopped.code is not None)
    finally:
        sys.argv = argv
        signal.signal(signal.SIGTERM, on_sigterm)
        if environ is not None:
            os.environ.clear()
            os.environ.update(saved)
        get_settings.cache_clear()
    result = subprocess.CompletedProcess(list(args), code, stdout.getvalue(), stderr.getvalue())
    if check:
        assert result.returncode == 0, result.stderr
    return result
