"""A throwaway PostgreSQL server for the test session.

``postgres_server()`` runs ``initdb`` into a fresh temporary directory (in memory where the machine
has a tmpfs, ``MEMORY``), starts the server on a free port of 127.0.0.1 (durability switched off:
nothing here needs to survive a crash), creates an empty database and yields its SQLAlchemy URL. On
exit the server is stopped and the directory deleted; a watchdog does both if the test process dies
without exiting (killed, or out of memory). It uses the server binaries of Debian's
``postgresql`` package (``/usr/lib/postgresql/<version>/bin``, newest version), falling back to
``initdb``/``pg_ctl`` on ``PATH``; ``bash scripts/ensure-postgres.sh`` installs them.

PostgreSQL refuses to run as root, so under root (as in CI) the directory is handed to the
``postgres`` system user and the server runs as that user through ``runuser``.

When the binaries (or the ``psycopg`` driver) are missing, ``postgres_server()`` yields
``None`` with the reason in ``missing_reason()``, so the caller can skip; when the environment
variable ``CI`` is true it raises ``PostgresUnavailableError`` instead: in CI a missing PostgreSQL is
a failure, not a skip.
"""

from __future__ import annotations

import contextlib
import os
import re
import shlex
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

USER = "narxwatch"
DATABASE = "narxwatch_test"
HOST = "127.0.0.1"
SYSTEM_USER = "postgres"  # the account the server runs as when the tests run as root
DEBIAN_ROOT = Path("/usr/lib/postgresql")
INSTALL_HINT = "install it with `bash scripts/ensure-postgres.sh` (as root) or `apt-get install postgresql`"

# A throwaway server: durability off, which makes initdb, DDL and commits much faster.
SERVER_SETTINGS = {
    "listen_addresses": f"'{HOST}'",
    "max_connections": "100",
    "fsync": "off",
    "synchronous_commit": "off",
    "full_page_writes": "off",
    "shared_buffers": "'32MB'",
    "log_min_messages": "warning",
    "logging_collector": "off",
}


# Where a server that need not survive a crash keeps its files, when the machine has it: a tmpfs.
# The session's server holds a copy of the migrated template for each test that needs a database
# of its own (harness/migrated.py): on a disk, writing them back and deleting them at the end
# (thousands of files) cost seconds of each pytest process's last moments; in memory, nothing
# waits on a disk, and the durable server of the tests that stop PostgreSQL stays on one. Only
# where the tmpfs has room for both pytest processes' servers: a container's is 64 MB by default.
MEMORY = Path("/dev/shm")
MEMORY_ROOM = 2 * 2**30  # bytes free on it at least


# A server started with pg_ctl is detached: nothing stops it when the test process that started it
# is killed, and it would keep its port, its memory and its tmpfs files until the machine restarts.
# The watchdog waits on the test process's pidfd (no polling) and then stops the server and removes
# its directory; a test process that exits normally has done both and ends the watchdog first.
WATCHDOG = """
import os, select, shutil, subprocess, sys
parent, workdir, *stop = sys.argv[1:]
select.select([os.pidfd_open(int(parent))], [], [])
subprocess.run(stop, cwd=workdir, capture_output=True, timeout=60, check=False)
shutil.rmtree(workdir, ignore_errors=True)
"""


class PostgresUnavailableError(RuntimeError):
    """PostgreSQL cannot be started here (binaries or driver missing, or the server failed)."""


@dataclass(frozen=True)
class Binaries:
    initdb: Path
    pg_ctl: Path


def in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() in {"true", "1", "yes"}


def _version_key(path: Path) -> tuple[int, ...]:
    return tuple(int(part) for part in re.findall(r"\d+", path.name)) or (0,)


def find_binaries() -> Binaries | None:
    """initdb and pg_ctl: Debian's newest versioned bin directory first, then ``PATH``.

    ``/usr/local/bin/pg_ctl`` and friends may be wrappers or links on a developer machine, so the
    versioned directory wins; both programs always come from the same directory.
    """
    if DEBIAN_ROOT.is_dir():
        for version_dir in sorted(DEBIAN_ROOT.iterdir(), key=_version_key, reverse=True):
            bin_dir = version_dir / "bin"
            initdb, pg_ctl = bin_dir / "initdb", bin_dir / "pg_ctl"
            if os.access(initdb, os.X_OK) and os.access(pg_ctl, os.X_OK):
                return Binaries(initdb, pg_ctl)
    found = shutil.which("pg_ctl")
    if found:
        bin_dir = Path(found).resolve().parent
        initdb, pg_ctl = bin_dir / "initdb", bin_dir / "pg_ctl"
        if os.access(initdb, os.X_OK):
            return Binaries(initdb, pg_ctl)
    return None


def missing_reason() -> str | None:
    """Why no server can be started here, or None when everything needed is installed."""
    if find_binaries() is None:
        return f"PostgreSQL server binaries (initdb, pg_ctl) not found; {INSTALL_HINT}"
    try:
        import psycopg  # noqa: F401
    except ImportError:
        return "the psycopg driver is not installed; install the test extras: pip install -e '.[test]'"
    return None


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((HOST, 0))
        return sock.getsockname()[1]


def _running_as_root() -> bool:
    return hasattr(os, "geteuid") and os.geteuid() == 0


class _Runner:
    """Runs the server programs as the current user, or as ``postgres`` when we are root."""

    def __init__(self, workdir: Path) -> None:
        self.workdir = workdir
        self.as_root = _running_as_root()
        if self.as_root:
            import pwd

            try:
                self.account = pwd.getpwnam(SYSTEM_USER)
            except KeyError:
                raise PostgresUnavailableError(
                    f"running as root, but there is no {SYSTEM_USER!r} system user to run PostgreSQL as "
                    f"(PostgreSQL refuses to run as root); {INSTALL_HINT}"
                ) from None
            self.runuser = shutil.which("runuser") or shutil.which("su")
            if self.runuser is None:
                raise PostgresUnavailableError("running as root, but neither runuser nor su is available")

    def command(self, argv: list[str]) -> list[str]:
        if not self.as_root:
            return argv
        if Path(self.runuser).name == "runuser":
            return [self.runuser, "-u", SYSTEM_USER, "--", *argv]
        return [self.runuser, SYSTEM_USER, "-s", "/bin/sh", "-c", shlex.join(argv)]

    def run(self, argv: list[str], timeout: float = 120) -> subprocess.CompletedProcess[str]:
        env = {**os.environ, "LC_ALL": "C", "LANG": "C"}
        env.pop("PGDATA", None)
        return subprocess.run(
            self.command(argv),
            cwd=self.workdir,  # the postgres user may not be allowed into the caller's directory
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )

    def give(self, path: Path) -> None:
        if self.as_root:
            os.chown(path, self.account.pw_uid, self.account.pw_gid)


def in_memory_room() -> bool:
    """Whether a throwaway server's files can go to ``MEMORY``: there, writable, with room."""
    usable = MEMORY.is_dir() and os.access(MEMORY, os.W_OK | os.X_OK)
    return usable and shutil.disk_usage(MEMORY).free >= MEMORY_ROOM


def _make_workdir(as_root: bool, durable: bool) -> Path:
    """A private temporary directory; in memory (``MEMORY``) unless the server is ``durable``;
    under root one the ``postgres`` user can reach (/tmp)."""
    base = str(MEMORY) if not durable and in_memory_room() else tempfile.gettempdir()
    if as_root:
        # Every parent must be traversable by the postgres user; /tmp always is.
        parents = Path(base).resolve().parents
        if not all(os.stat(p).st_mode & 0o001 for p in [Path(base).resolve(), *parents]):
            base = "/tmp"
    # Short name: the unix socket path (workdir/.s.PGSQL.<port>) must stay under 107 bytes.
    return Path(tempfile.mkdtemp(prefix="nxpg-", dir=base))


def _fail(message: str, result: subprocess.CompletedProcess[str] | None, log: Path | None) -> None:
    details = []
    if result is not None:
        details.append(f"exit status {result.returncode}\n{result.stdout}\n{result.stderr}".strip())
    if log is not None and log.exists():
        tail = log.read_text(errors="replace").splitlines()[-30:]
        details.append("server log (last lines):\n" + "\n".join(tail))
    raise PostgresUnavailableError("\n".join([message, *details]))


def _start(binaries: Binaries, runner: _Runner, data: Path, log: Path, durable: bool = False) -> int:
    """initdb into ``data``, configure, start; returns the port the server listens on."""
    workdir = data.parent
    result = runner.run(
        [
            str(binaries.initdb),
            "-D",
            str(data),
            "-A",
            "trust",
            "-U",
            USER,
            "--encoding=UTF8",
            "--no-locale",
            "--no-sync",
        ]
    )
    if result.returncode != 0:
        _fail("initdb failed", result, None)
    settings = {**SERVER_SETTINGS, "unix_socket_directories": f"'{workdir}'"}
    if durable:  # a server that is to be stopped under load keeps what it acknowledged
        settings.update(fsync="on", synchronous_commit="on", full_page_writes="on")
        # A fast shutdown waits for the connections accepted while it runs to send their startup
        # packet or time out: a client that connected then and never spoke (a narxwatch worker's
        # connection attempt abandoned as it lost the database) held the stop for the default
        # minute, past pg_ctl's wait (its backends cannot be signalled before they know their
        # database). A client on loopback sends its packet as its connection opens.
        settings["authentication_timeout"] = "'2s'"
    with (data / "postgresql.conf").open("a") as conf:
        conf.write("\n# throwaway test server (harness/postgres.py)\n")
        conf.writelines(f"{name} = {value}\n" for name, value in settings.items())

    # The port is free when picked but another process could take it before the server binds
    # it; try a few.
    attempts = 5
    for attempt in range(1, attempts + 1):
        port = _free_port()
        if log.exists():
            log.write_text("")
        result = _pg_ctl_start(binaries, runner, data, log, port)
        if result.returncode == 0:
            return port
        text = log.read_text(errors="replace") if log.exists() else ""
        port_taken = "could not bind" in text or "already in use" in text
        if not port_taken or attempt == attempts:
            _fail("pg_ctl start failed", result, log)
    raise AssertionError("unreachable")


def _pg_ctl_start(
    binaries: Binaries, runner: _Runner, data: Path, log: Path, port: int
) -> subprocess.CompletedProcess[str]:
    command = [str(binaries.pg_ctl), "-D", str(data), "-l", str(log), "-w", "-t", "60", "-o", f"-p {port}"]
    return runner.run([*command, "start"])


def _stop_command(binaries: Binaries, data: Path, mode: str = "immediate") -> list[str]:
    return [str(binaries.pg_ctl), "-D", str(data), "-m", mode, "-w", "-t", "30", "stop"]


def _stop(
    binaries: Binaries, runner: _Runner, data: Path, mode: str = "immediate"
) -> subprocess.CompletedProcess[str]:
    return runner.run(_stop_command(binaries, data, mode), timeout=60)


def _watchdog(binaries: Binaries, runner: _Runner, data: Path) -> subprocess.Popen[bytes] | None:
    """The process that stops the server at ``data`` and removes its directory if this process
    dies first (``WATCHDOG``); None where the system has no pidfds."""
    if not hasattr(os, "pidfd_open"):
        return None
    stop = runner.command(_stop_command(binaries, data))
    argv = [sys.executable, "-I", "-S", "-c", WATCHDOG, str(os.getpid()), str(data.parent), *stop]
    # A session of its own: a signal to the test run's process group does not reach it.
    return subprocess.Popen(argv, start_new_session=True, stdin=subprocess.DEVNULL)


def conninfo(url: str) -> str:
    """A libpq connection string for a ``postgresql+psycopg://user@host:port/db`` URL."""
    match = re.fullmatch(r"postgresql(?:\+psycopg)?://([^@/:]+)(?::[^@/]*)?@([^:/]+):(\d+)/(\w+)", url)
    if match is None:
        raise ValueError(f"not a URL made by harness/postgres.py: {url}")
    user, host, port, dbname = match.groups()
    return f"host={host} port={port} user={user} dbname={dbname}"


def reset_database(url: str) -> None:
    """Drop everything in the database (schema ``public`` recreated empty), e.g. between modules."""
    import psycopg

    with psycopg.connect(conninfo(url), autocommit=True) as conn:
        conn.execute("DROP SCHEMA IF EXISTS public CASCADE")
        conn.execute("CREATE SCHEMA public")


def create_database(url: str, name: str) -> str:
    """A new empty database on the same server; returns its URL (for tests needing isolation)."""
    import psycopg
    from psycopg import sql

    if not re.fullmatch(r"[a-z_][a-z0-9_]*", name):
        raise ValueError(f"database name must be a lowercase identifier: {name!r}")
    with psycopg.connect(conninfo(url), autocommit=True) as conn:
        conn.execute(sql.SQL("CREATE DATABASE {}").format(sql.Identifier(name)))
    return url.rsplit("/", 1)[0] + "/" + name


@dataclass
class Server:
    """A running throwaway server; ``stop`` and ``start`` take it down and up on the same port."""

    url: str
    binaries: Binaries
    runner: _Runner
    data: Path
    log: Path
    port: int

    def stop(self, mode: str = "fast") -> None:
        """``fast``: an operator's stop (sessions cut, work in flight rolled back); ``immediate``: a crash.

        Raises when the server is still running after pg_ctl's wait: a test goes on only on a
        server that is down."""
        result = _stop(self.binaries, self.runner, self.data, mode)
        if result.returncode != 0:
            _fail(f"pg_ctl stop -m {mode} failed", result, self.log)

    def start(self) -> None:
        result = _pg_ctl_start(self.binaries, self.runner, self.data, self.log, self.port)
        if result.returncode != 0:
            _fail("pg_ctl start (restart) failed", result, self.log)


@contextlib.contextmanager
def postgres_instance(database: str = DATABASE, durable: bool = False) -> Iterator[Server | None]:
    """Start a throwaway server with an empty ``database``; yield it (see ``postgres_server``).

    ``durable``: with fsync and synchronous commits, as a production server, for tests that stop
    it and count what survived; the default trades that for speed."""
    reason = missing_reason()
    if reason is not None:
        if in_ci():
            raise PostgresUnavailableError(f"CI=true and {reason}")
        yield None
        return
    if not re.fullmatch(r"[a-z_][a-z0-9_]*", database):
        raise ValueError(f"database name must be a lowercase identifier: {database!r}")
    binaries = find_binaries()
    assert binaries is not None
    import psycopg

    workdir = _make_workdir(_running_as_root(), durable)
    data, log = workdir / "data", workdir / "server.log"
    watchdog = None
    try:
        runner = _Runner(workdir)
        runner.give(workdir)
        watchdog = _watchdog(binaries, runner, data)
        try:
            port = _start(binaries, runner, data, log, durable)
            admin = f"host={HOST} port={port} user={USER} dbname=postgres"
            with psycopg.connect(admin, autocommit=True) as conn:
                conn.execute(f'CREATE DATABASE "{database}"')
            url = f"postgresql+psycopg://{USER}@{HOST}:{port}/{database}"
            yield Server(url, binaries, runner, data, log, port)
        finally:
            if (data / "postmaster.pid").exists():
                _stop(binaries, runner, data)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
        if watchdog is not None:
            watchdog.kill()
            watchdog.wait()


@contextlib.contextmanager
def postgres_server(database: str = DATABASE) -> Iterator[str | None]:
    """Start a throwaway server and yield ``postgresql+psycopg://narxwatch@127.0.0.1:PORT/DB``.

    Yields None when PostgreSQL or psycopg is missing outside CI (see ``missing_reason()``);
    raises ``PostgresUnavailableError`` when they are missing in CI or the server fails to start.
    """
    with postgres_instance(database) as server:
        yield None if server is None else server.url


if __name__ == "__main__":  # manual check: python -m harness.postgres
    started = time.perf_counter()
    with postgres_server() as server_url:
        print(f"{server_url} up in {time.perf_counter() - started:.2f} s")
    print(f"stopped and removed after {time.perf_counter() - started:.2f} s")
