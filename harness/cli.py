"""The ``narxwatch`` console script as a user runs it, and its entry point in the caller's process."""

from __future__ import annotations

import contextlib
import io
import shutil
import subprocess
import sys
from pathlib import Path

from service.cli import main

NARXWATCH = shutil.which("narxwatch", path=str(Path(sys.executable).parent))
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def run(*args: str, cwd: Path, check: bool = True) -> subprocess.CompletedProcess[str]:
    assert NARXWATCH, "the narxwatch console script is not installed next to this Python"
    result = subprocess.run([NARXWATCH, *args], cwd=cwd, capture_output=True, text=True, timeout=300)
    if check:
        assert result.returncode == 0, result.stderr
    return result


def invoke(*args: str, cwd: Path, check: bool = True) -> subprocess.CompletedProcess[str]:
    """:func:`run` in this process: the console script's entry point with ``args`` in ``cwd``, its
    exit code and what it wrote. An exception it lets through fails the test, as a traceback
    would."""
    stdout, stderr = io.StringIO(), io.StringIO()
    argv = sys.argv
    sys.argv = [NARXWATCH or "narxwatch", *args]
    try:
        with contextlib.chdir(cwd), contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            main()
        code = 0
    except SystemExit as stopped:
        code = stopped.code if isinstance(stopped.code, int) else int(stopped.code is not None)
    finally:
        sys.argv = argv
    result = subprocess.CompletedProcess(list(args), code, stdout.getvalue(), stderr.getvalue())
    if check:
        assert result.returncode == 0, result.stderr
    return result
