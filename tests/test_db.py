"""The SQLite writer gate: one writer at a time across threads and processes."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import threading
from pathlib import Path

from service.db import WriterGate, make_engine, writer_gate

ROOT = Path(__file__).resolve().parents[1]
HOLDER = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    from service.db import WriterGate

    with WriterGate(Path(sys.argv[1])).held():
        print("held", flush=True)
        sys.stdin.readline()
    """
)


def test_a_gate_held_by_another_process_blocks_until_released(tmp_path: Path) -> None:
    database = tmp_path / "narxwatch.db"
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLDER, str(database)],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdin is not None
        assert holder.stdout.readline().strip() == "held"
        acquired = threading.Event()

        def acquire() -> None:
            with WriterGate(database).held():
                acquired.set()

        waiter = threading.Thread(target=acquire)
        waiter.start()
        assert not acquired.wait(0.5), "the gate was entered while another process held it"
        holder.stdin.write("release\n")
        holder.stdin.flush()
        assert acquired.wait(10), "the gate stayed closed after the other process let go"
        waiter.join()
    finally:
        holder.kill()
        holder.wait()


def test_threads_of_one_process_take_the_gate_in_turn(tmp_path: Path) -> None:
    gate = WriterGate(tmp_path / "narxwatch.db")
    inside, most_inside = 0, 0
    counter = threading.Lock()

    def write() -> None:
        nonlocal inside, most_inside
        for _ in range(50):
            with gate.held():
                with counter:
                    inside += 1
                    most_inside = max(most_inside, inside)
                threading.Event().wait(0.0005)  # let the others try to get in meanwhile
                with counter:
                    inside -= 1

    threads = [threading.Thread(target=write) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert most_inside == 1


def test_only_a_sqlite_file_has_a_gate(tmp_path: Path) -> None:
    gate = writer_gate(f"sqlite:///{tmp_path / 'a.db'}")
    assert gate is not None
    assert writer_gate(f"sqlite:///{tmp_path / 'a.db'}") is gate  # one per database file in a process
    engine = make_engine(f"sqlite:///{tmp_path / 'a.db'}")
    with engine.connect() as connection:
        assert connection.connection.driver_connection.gate is gate  # the engine's connections take it
    for url in ("sqlite://", "sqlite:///:memory:", "postgresql+psycopg://monitor@localhost/narxwatch"):
        assert writer_gate(url) is None, url
