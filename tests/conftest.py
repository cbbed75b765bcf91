"""Shared fixtures and independent reference computations for the science tests.

Everything expensive (simulated records, fitted fault-mode models) is built once per session.
Seeds are fixed once here and are not tuned to make any test pass: the tests assert properties
that hold with overwhelming probability for any seed.

The helpers below recompute, without the library, what the library computes: the exact NARX
coefficients from the equations of SPEC §1 (polynomial algebra in the forward shift q), a
hand-built regressor matrix, and column-scaled least squares via ``numpy.linalg.lstsq``.
"""

from __future__ import annotations

from models.blas import one_blas_thread

# One BLAS thread a process, as narxwatch's own processes run: set before numpy loads BLAS (no
# plugin has by now), so that `pytest` alone runs as `make test` does; xdist's workers and the
# servers the tests start inherit it. Two busy workers with two BLAS threads each spend several
# times the CPU in the refinement tests.
one_blas_thread()

import ipaddress
import socket
import sys
import uuid
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from harness.prerequisites import SILVERBOX_SHA256, benchmark_data
from models.fnarx import FNARX, fit_fnarx
from simulator.physics import PhysicalParameters
from simulator.simulate import Scenario, SimulatedRecord, simulate
from simulator.theory import EXACT_TERMS

P = np.polynomial.polynomial  # ascending coefficients: c[0] + c[1]·q + c[2]·q² + …

# Exact structure of SPEC §2 as (signal, lag, power) factors, independent of models.terms.
EXACT_STRUCTURE: list[list[tuple[str, int, int]]] = [
    [("y", 1, 1)],
    [("y", 2, 1)],
    [("y", 3, 1)],
    [("y", 4, 1)],
    [("y", 2, 3)],
    [("y", 3, 3)],
    [("y", 4, 3)],
    [("x", 4, 1)],
]

# SPEC §4 design: 17 experiments k = −32, −28, …, 32, N = 2000 each.
K2_MAGNITUDES = np.arange(-32.0, 33.0, 4.0)
EXPERIMENT_SAMPLES = 2000
# The verdict fields the issue names for ``narxwatch inspect --json`` and the service.
VERDICT_FIELDS = (
    "status",
    "fault_detected",
    "fault_mode",
    "k_hat",
    "sigma_k",
    "interval",
    "alpha",
    "lags",
    "n_samples",
    "modes",
)
MODE_FIELDS = ("name", "k_hat", "sigma_k", "q", "q_critical", "p_value", "accepted")
DISTURBANCE_STD = 800.0


# The files that take the most of a worker's time, longest first: each file's CPU, its tests'
# summed in one process, and the files whose tests wait on servers, timeouts and restarts more than
# they compute (the notifications' and schedules' workers, the browser, the database failures, the
# request lifecycle, the schema fuzz, the jobs) no later than files of like CPU. `make test` hands
# whole files to two pytest-xdist workers in this order (--no-loadscope-reorder), then the rest,
# each a few seconds, in collection order: no long file starts when the other worker is nearly
# done (the stateful fuzz run, last under xdist's own order, once left one worker idle for its
# last 100 s), and the short ones at the end even out when the two workers finish. A file that
# grows past the last here belongs in it.
LONGEST_FILES = (
    "test_refinement.py",
    "test_cli_refine.py",
    "test_free_run_inspection.py",
    "test_effects_output.py",
    "test_notifications.py",
    "test_dashboard_browser.py",
    "test_faults.py",
    "test_lifecycle.py",
    "test_fuzz_stateful.py",
    "test_schedules.py",
    "test_upload_memory.py",
    "test_api_refinements.py",
    "test_jobs.py",
    "test_api_errors.py",
    "test_novelty.py",
    "test_api_bounded.py",
    "test_readme.py",
    "test_service_cli.py",
    "test_api_novelty.py",
    "test_tenancy.py",
    "test_observability.py",
    "test_periodic.py",
    "test_migrations.py",
    "test_api_own_structure.py",
    "test_sim_scenarios.py",
    "test_cli.py",
    "test_sim_client.py",
    "test_api_sensor_noise.py",
    "test_localisation.py",
    "test_glitches.py",
    "test_fleet_scale.py",
    "test_cli_select.py",
    "test_compose.py",
    "test_upload_hardening.py",
    "test_sim_chain.py",
    "test_dashboard.py",
    "test_layers.py",
    "test_retention.py",
    "test_selection.py",
    "test_model_versions.py",
    "test_kinks.py",
    "test_api_alarms.py",
    "test_baseline_choice.py",
    "test_api_published.py",
    "test_api_channels.py",
    "test_recordfile.py",
    "test_output_error.py",
    "test_published_files.py",
    "test_diagnostics.py",
)


# --- Nothing leaves the machine ------------------------------------------------------------------
# Every test talks to servers it started on loopback (the app, receivers, SMTP, PostgreSQL): a
# connection anywhere else is a mistake, a webhook test whose allowance let a delivery out most
# of all. Python's socket calls in the test process (httpcore's, smtplib's, the tests' own) are
# refused one to any other address; libpq's and Chromium's connections are not Python's and are
# not seen, nor are those of the `narxwatch` processes a test starts. An audit hook stays for the
# life of the process, so it is installed once, here.


def _dial_loopback_only(event: str, args: tuple) -> None:
    if event not in ("socket.connect", "socket.sendto"):
        return
    sock, address = args[0], args[1]
    if sock.family not in (socket.AF_INET, socket.AF_INET6):
        return  # AF_UNIX and the like stay on this machine
    host = str(address[0])
    try:
        ip = ipaddress.ip_address(host.split("%")[0])
    except ValueError:
        admitted = host == "localhost"
    else:
        mapped = getattr(ip, "ipv4_mapped", None)
        admitted = ip.is_loopback or (mapped is not None and mapped.is_loopback)
    if not admitted:
        raise PermissionError(f"the tests dial loopback only, not {host} (tests/conftest.py)")


sys.addaudithook(_dial_loopback_only)


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The longest files first, each file's tests kept in their order (a stable sort)."""
    rank = {name: index for index, name in enumerate(LONGEST_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(LONGEST_FILES)))


def reference_coefficients(params: PhysicalParameters) -> np.ndarray:
    """The eight exact NARX coefficients, derived here from SPEC §1 without the library.

    With the forward shift q and forward differences, mass 1 reads A1(q)·x1 = F + k2·x2 and
    mass 2 reads A2(q)·x2 + k3·x2³ = k2·x1, where
    A1 = m1/Ts²·(q−1)² + c1/Ts·(q−1) + (k1 + k2) and A2 = m2/Ts²·(q−1)² + c2/Ts·(q−1) + k2.
    Applying A1 to the second equation and substituting the first:
    (A1·A2 − k2²)·y + k3·A1·y³ = k2·F. Divide by the q⁴ coefficient and shift back by 4.
    """
    p = params
    q_minus_1 = np.array([-1.0, 1.0])
    d2 = P.polymul(q_minus_1, q_minus_1)
    A1 = P.polyadd(P.polyadd(p.m1 / p.ts**2 * d2, p.c1 / p.ts * q_minus_1), [p.k1 + p.k2])
    A2 = P.polyadd(P.polyadd(p.m2 / p.ts**2 * d2, p.c2 / p.ts * q_minus_1), [p.k2])
    lhs_linear = P.polysub(P.polymul(A1, A2), [p.k2**2])  # degree 4, ascending
    lead = lhs_linear[4]
    # y[t] = −Σ_{i=1..4} lhs[4−i]/lead·y[t−i] − k3·Σ_{i=2..4} A1[4−i]/lead·y³[t−i] + k2/lead·x[t−4]
    a = np.array([-lhs_linear[4 - i] / lead for i in range(1, 5)])
    cubic = np.array([-p.k3 * A1[4 - i] / lead for i in range(2, 5)])
    return np.concatenate([a, cubic, [p.k2 / lead]])


def hand_regressors(
    structure: list[list[tuple[str, int, int]]], x: np.ndarray, y: np.ndarray, lag: int
) -> tuple[np.ndarray, np.ndarray]:
    """Φ[r, j] = Π signal[t − lag_f]^power_f for t = lag + r, by an explicit loop over t."""
    signals = {"x": np.asarray(x, dtype=float), "y": np.asarray(y, dtype=float)}
    n = len(y)
    Phi = np.empty((n - lag, len(structure)))
    for r, t in enumerate(range(lag, n)):
        for j, term in enumerate(structure):
            value = 1.0
            for signal, factor_lag, power in term:
                value *= signals[signal][t - factor_lag] ** power
            Phi[r, j] = value
    return Phi, np.asarray(y, dtype=float)[lag:]


def exact_regressors(x: np.ndarray, y: np.ndarray, lag: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised regressors of the exact structure (columns in EXACT_STRUCTURE order)."""
    n = len(y)
    cols = [y[lag - i : n - i] for i in (1, 2, 3, 4)]
    cols += [y[lag - i : n - i] ** 3 for i in (2, 3, 4)]
    cols.append(x[lag - 4 : n - 4])
    return np.column_stack(cols), y[lag:]


def scaled_lstsq(Phi: np.ndarray, target: np.ndarray) -> np.ndarray:
    """OLS by numpy's SVD solver on unit-norm columns, mapped back to the original units."""
    scale = np.linalg.norm(Phi, axis=0)
    theta, *_ = np.linalg.lstsq(Phi / scale, target, rcond=None)
    return theta / scale


def exact_narx_residual(x: np.ndarray, y: np.ndarray, coefficients: np.ndarray) -> np.ndarray:
    """e[t] = y[t] − φ[t]ᵀθ for the exact structure, t = 4 … N−1."""
    Phi, target = exact_regressors(x, y)
    return target - Phi @ coefficients


@dataclass(frozen=True)
class Experiments:
    """Records (x, y, k) for fitting a fault-mode model, with the scenario that made them."""

    runs: list[tuple[np.ndarray, np.ndarray, float]]


def make_experiments(mode: str, magnitudes: np.ndarray, disturbance_std: float, seed0: int) -> Experiments:
    runs = []
    for i, k in enumerate(magnitudes):
        rec = simulate(
            Scenario(fault=mode, k=float(k), disturbance_std=disturbance_std),
            EXPERIMENT_SAMPLES,
            seed=seed0 + i,
        )
        runs.append((rec.x, rec.y, float(k)))
    return Experiments(runs)


@pytest.fixture(scope="session")
def silverbox_dir() -> Path:
    """The Silverbox files (skipped without them, failed with CI=true: ``benchmark_data``)."""
    return benchmark_data("silverbox", *SILVERBOX_SHA256)


@pytest.fixture(scope="session")
def params() -> PhysicalParameters:
    return PhysicalParameters()


@pytest.fixture(scope="session")
def noise_free_record() -> SimulatedRecord:
    """Healthy, no disturbance, 30 000 samples (SPEC §3 identification length)."""
    return simulate(Scenario(), 30_000, seed=11)


@pytest.fixture(scope="session")
def disturbed_record() -> SimulatedRecord:
    """Healthy, white force disturbance (std 800 N, 3.2 % of the excitation), 30 000 samples."""
    return simulate(Scenario(disturbance_std=DISTURBANCE_STD), 30_000, seed=12)


@pytest.fixture(scope="session")
def k2_experiments() -> Experiments:
    return make_experiments("k2", K2_MAGNITUDES, DISTURBANCE_STD, seed0=1000)


@pytest.fixture(scope="session")
def k2_noise_free_experiments() -> Experiments:
    return make_experiments("k2", K2_MAGNITUDES, 0.0, seed0=2000)


@pytest.fixture(scope="session")
def k2_model(k2_experiments: Experiments) -> FNARX:
    """The k2 fault-mode model of the paper's design, Chebyshev p = 2."""
    return fit_fnarx(k2_experiments.runs, EXACT_TERMS, name="k2")


@pytest.fixture(scope="session")
def k1_model() -> FNARX:
    """A k1 fault-mode model over [−32, 32] % (9 experiments)."""
    experiments = make_experiments("k1", np.arange(-32.0, 33.0, 8.0), DISTURBANCE_STD, seed0=3000)
    return fit_fnarx(experiments.runs, EXACT_TERMS, name="k1")


# --- PostgreSQL for the API tests (harness/postgres.py) -------------------------------------------
# One throwaway server per test session. Outside CI a machine without PostgreSQL skips the tests
# that use it, saying how to install it; with CI=true that is an error instead.


@pytest.fixture(scope="session")
def postgres_url():  # yields str
    """``postgresql+psycopg://narxwatch@127.0.0.1:PORT/narxwatch_test`` on a throwaway server."""
    from harness import postgres

    with postgres.postgres_server() as url:
        if url is None:
            pytest.skip(f"PostgreSQL unavailable: {postgres.missing_reason()}")
        yield url


# --- The API over HTTP, on SQLite and on PostgreSQL --------------------------------------------


@pytest.fixture(scope="session")
def sqlite_api_server(tmp_path_factory):
    """The real app on SQLite, served on loopback; the embedded job backend runs jobs on its thread."""
    from harness.live import LiveServer
    from service.config import Settings

    url = f"sqlite:///{tmp_path_factory.mktemp('api') / 'narxwatch.db'}"
    with LiveServer(Settings(database_url=url)) as server:
        yield server


@pytest.fixture(scope="session")
def postgresql_api_server(postgres_url, tmp_path_factory):
    """The real app on PostgreSQL, served on loopback; the distributed job backend runs queued jobs
    on two `narxwatch worker` processes."""
    from harness import migrated
    from harness.live import LiveServer
    from harness.workers import workers
    from service.config import Settings

    url = migrated.postgresql(postgres_url, "narxwatch_api")
    # No test on this server waits for a sweep (its schedules are never due: harness/estates.py;
    # no delivery or stalled job is waited for), which idle workers would otherwise run every
    # few seconds of the session: one a minute.
    with (
        LiveServer(Settings(database_url=url)) as server,
        workers(url, 2, tmp_path_factory.mktemp("workers"), worker_sweep_seconds="60"),
    ):
        yield server


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def api_server(request):
    """The real app served on loopback, once per database backend.

    Module-scoped over two session servers rather than one parametrised session fixture: pytest
    tears a parametrised fixture down whenever the parameter changes, and under pytest-xdist
    (`make test`) each worker runs whole files, sqlite then postgresql in every one, which would
    start the PostgreSQL app and its workers again for every file. Each server starts once per
    worker process instead, when a test first needs it."""
    return request.getfixturevalue(f"{request.param}_api_server")


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def database_server(request):
    """The app on each database, for a module on SQLite (its ``api_server``) whose few tests of
    what the database decides (constraints, row locks, the times it stores) run on both."""
    from harness.live import on_each_database

    return on_each_database(request, "sqlite_api_server", lambda server: server)


@pytest.fixture
def tenant(api_server):
    """A fresh organisation with an admin, an ingest and a viewer client."""
    from harness.live import Tenant

    tenant = Tenant.create(api_server)
    yield tenant
    for client in (tenant.admin, tenant.ingest, tenant.viewer):
        client.close()


def _fleet(url: str):  # yields harness.fleet.Fleet
    from harness.fleet import Fleet
    from harness.live import LiveServer
    from service.config import Settings
    from service.db import make_engine

    with LiveServer(Settings(database_url=url, job_backend="embedded")) as server:
        engine = make_engine(url)
        yield Fleet(server, engine)
        engine.dispose()


@pytest.fixture(scope="module")
def sqlite_fleet_server(tmp_path_factory):  # yields harness.fleet.Fleet
    """A server of its own on SQLite, so that nothing else writes while a test holds the state
    rows against the tables."""
    yield from _fleet(f"sqlite:///{tmp_path_factory.mktemp('fleet') / 'narxwatch.db'}")


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def fleet_server(request):  # yields harness.fleet.Fleet
    """A server of its own on each database (the embedded job backend on PostgreSQL too): on
    SQLite the module's ``sqlite_fleet_server``."""
    if request.param == "sqlite":
        yield request.getfixturevalue("sqlite_fleet_server")
        return
    from harness import migrated

    url = migrated.postgresql(request.getfixturevalue("postgres_url"), f"fleet_{uuid.uuid4().hex[:12]}")
    yield from _fleet(url)
