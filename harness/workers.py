"""`narxwatch worker` processes for the tests: real processes, started and killed like in production."""

from __future__ import annotations

import os
import signal
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from harness.cli import NARXWATCH


class Worker:
    """A `narxwatch worker` process on ``database_url``; its output goes to ``log``."""

    def __init__(self, database_url: str, log: Path, **settings: str) -> None:
        env = {**os.environ, "NARXWATCH_DATABASE_URL": database_url, "PYTHONUNBUFFERED": "1"}
        env.update({f"NARXWATCH_{name.upper()}": value for name, value in settings.items()})
        self.log = log
        with log.open("ab") as out:
            self.process = subprocess.Popen(
                [NARXWATCH, "worker"], env=env, stdout=out, stderr=subprocess.STDOUT
            )

    def alive(self) -> bool:
        return self.process.poll() is None

    def kill(self) -> None:
        """SIGKILL: no chance to finish or hand back its job."""
        self.process.send_signal(signal.SIGKILL)
        self.process.wait(30)

    def stop(self) -> None:
        if self.alive():
            self.process.terminate()
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:
                self.kill()

    def output(self) -> str:
        return self.log.read_text(errors="replace")


@contextmanager
def workers(database_url: str, count: int, folder: Path, **settings: str) -> Iterator[list[Worker]]:
    started = [Worker(database_url, folder / f"worker-{i}.log", **settings) for i in range(count)]
    try:
        yield started
    finally:
        for worker in started:
            worker.stop()
