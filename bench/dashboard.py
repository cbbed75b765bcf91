"""Load time of the dashboard's structure page with a long history (target: 10 000 verdicts, ≤ 1 s).

    .venv/bin/python bench/dashboard.py [--verdicts 10000] [--repeats 20] [--database-url URL]

What it does, in order:

1. Serves the real app (``harness/live.py``: uvicorn on a free loopback port, in a thread of this
   process) on a fresh SQLite file in a temporary folder, or on ``--database-url`` (an existing
   database, e.g. ``postgresql+psycopg://…``; a new organisation is created in it).
2. Over HTTP, as ``harness/dashboard_helpers.monitored_structure`` does: an organisation with a key
   of each role, a structure, and a k2 fault-mode model trained from three simulated experiments.
3. Seeds the history. ``--distinct`` (200) records are simulated along a degradation ramp (k2
   magnitude rising from 0 to 30 % over time, 300–600 samples each, above the inspection's
   minimum of 5·lags + 8 = 208) and each is inspected once, in process, by the real chain
   (``service.domain.inspections.evaluate`` with the structure's active model and the server's
   settings). Then ``--verdicts`` records and verdicts are stored through the domain functions
   (``records.store_record``, ``inspections.store_verdict``) in a few transactions, one
   acquisition every 10 minutes, oldest first: verdict j reuses the inspection of distinct record
   ``j · distinct // verdicts``, so each inspection result stands for about 50 consecutive verdicts
   and the history is one ramp in time. Copy c of a record has its first response sample moved by
   c units in the last place (records are unique by content hash; a relative change of ~1e-14 is
   far below the measurement noise), and its verdict is the one computed from the unmoved record.
   Inspection results are reused because this bench measures the page, not the inspection
   (``bench/test_bench_inspection.py`` does): 10 000 real inspections would only make the seeding
   slower, while the page reads the same columns either way.
4. Logs in through ``POST /dashboard/login`` with the viewer key (the session cookie is Secure, so
   ``dashboard_helpers.logged_in`` hands it to the httpx client, as a browser would) and times
   ``GET /dashboard/structures/{id}``, ``GET /dashboard`` (the fleet) and
   ``GET /dashboard/records/{id}`` (the newest record) on one keep-alive connection: one warm-up,
   then ``--repeats`` requests each, measured on the client from sending the request to having
   read the whole answer (loopback, so that is the server's time plus a few tenths of a ms).
   The record page draws the whole record, and these records are short (300–600 samples): its
   time is that of a short record, not of a 2000-sample upload. The structure page is checked:
   its Q chart must hold one point per verdict and its k̂ chart one per verdict with a magnitude
   (unknown faults have none).
5. When ``/usr/bin/chromium`` and the ``playwright`` package are there: a headless Chromium logs
   in through the form, draws the structure page once (plotly.js is then in its cache, as on a
   person's second visit), then loads it ``--browser-repeats`` times. Each load is timed in the
   page from navigation start (``performance.now()``'s origin) to the moment every chart of the
   page in the first screenful (k̂ and Q; the coefficient trajectories further down are drawn
   when scrolled to) is marked drawn by ``dashboard.js``,
   caught by a MutationObserver injected before the page's scripts; the HTML's arrival
   (``responseEnd``) and ``DOMContentLoaded`` are given for where the time goes.

The server, the client and Chromium (its WebGL on the CPU: SwiftShader, ``--disable-gpu``)
share the machine's cores: a person's machine with a GPU likely draws the charts faster.

Prints a table (min, median, p95, max in ms and the answer's size) and a final line saying
whether the 1 s target is met by the server median and by the browser median. Exits non-zero
when a page answers other than 200 or the charts do not hold every verdict. Nothing asserts on
time.
"""

from __future__ import annotations

import argparse
import datetime as dt
import statistics
import sys
import tempfile
import time
import uuid
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's bench and harness, run as a script

from models.blas import one_blas_thread

one_blas_thread()  # before numpy is imported: one BLAS thread, as in narxwatch's processes
import httpx
import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from harness.api_helpers import Org, create_structure, simulated, train_fault_mode
from harness.dashboard_helpers import CHROMIUM, CHROMIUM_ARGS, DASHBOARD, charts, logged_in
from harness.live import LiveServer
from service.config import Settings
from service.domain import inspections, records
from service.tables import Structure

TARGET_SECONDS = 1.0
TARGET_VERDICTS = 10_000
FIRST_ACQUISITION = dt.datetime(2026, 1, 1, tzinfo=dt.UTC)
EVERY = dt.timedelta(minutes=10)
MAX_K = 30.0
SAMPLES = (300, 600)
TRANSACTION_ROWS = 2500
SEED = 20261201
BROWSER_TIMEOUT_MS = 60_000
# Injected before the page's own scripts: notes performance.now() (ms since navigation start)
# when the last chart in the first screenful is marked drawn by dashboard.js (charts further
# down are drawn as they are scrolled to).
DRAWN_PROBE = """
(() => {
  const allDrawn = () => {
    const charts = [...document.querySelectorAll("[data-chart]")].filter(
      (chart) => chart.getBoundingClientRect().top < window.innerHeight,
    );
    return charts.length > 0 && charts.every((chart) => chart.dataset.drawn === "true");
  };
  new MutationObserver((_, observer) => {
    if (allDrawn()) {
      window.__chartsDrawnAt = performance.now();
      observer.disconnect();
    }
  }).observe(document, { subtree: true, attributes: true, attributeFilter: ["data-drawn"] });
})();
"""

console = Console(width=max(Console().width, 116))  # a table of full rows in a pipe too


@dataclass
class Seeded:
    structure_id: int
    viewer_key: str
    newest_record_id: int
    verdicts: int
    statuses: dict[str, int]
    with_k_hat: int  # verdicts with a magnitude: the k̂ chart's points (unknown faults have none)


@dataclass
class Timing:
    name: str
    seconds: list[float]
    size_bytes: int | None = None
    note: str = ""


def progress() -> Progress:
    return Progress(
        TextColumn("{task.description:<34}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
    )


def distinct_copy(y: np.ndarray, copy: int) -> np.ndarray:
    """``y`` with its first sample moved by ``copy`` units in the last place: a new content hash."""
    moved = y.copy()
    moved[0] += copy * np.spacing(abs(moved[0]))
    return moved


def seed(server: LiveServer, n_verdicts: int, distinct: int) -> Seeded:
    """The structure, its k2 model over HTTP, then ``n_verdicts`` records and verdicts in bulk."""
    org = Org.create(server)
    with org.client("admin") as admin, org.client("ingest") as ingest:
        structure = create_structure(admin, f"bench rig {uuid.uuid4().hex[:6]}")
        train_fault_mode(admin, ingest, structure["id"], "k2", seed=SEED)
    rng = np.random.default_rng(SEED)
    magnitudes = np.linspace(0.0, MAX_K, distinct)
    lengths = rng.integers(SAMPLES[0], SAMPLES[1], distinct, endpoint=True)
    settings = server.settings
    statuses: dict[str, int] = {}
    with_k_hat = 0
    with progress() as bar, server.app.state.sessions() as session:
        structure_row = session.get(Structure, structure["id"])
        assert structure_row is not None
        simulating = bar.add_task("simulating distinct records", total=distinct)
        simulations = []
        for index, (k, n) in enumerate(zip(magnitudes, lengths, strict=True)):
            simulations.append(simulated("k2", float(k), [SEED, index], int(n)))
            bar.advance(simulating)
        inspecting = bar.add_task("inspecting each once", total=distinct)
        evaluations = []
        for record in simulations:
            evaluations.append(inspections.evaluate(session, structure_row, settings, record.x, record.y))
            bar.advance(inspecting)
        session.commit()  # ends the read transaction: SQLite then lets this session write
        storing = bar.add_task("storing records and verdicts", total=n_verdicts)
        newest = 0
        for first in range(0, n_verdicts, TRANSACTION_ROWS):
            for j in range(first, min(first + TRANSACTION_ROWS, n_verdicts)):
                source = j * distinct // n_verdicts
                copy = j - -(-source * n_verdicts // distinct)  # 0 for the first copy of a source
                record, created = records.store_record(
                    session,
                    structure_row,
                    simulations[source].x,
                    distinct_copy(simulations[source].y, copy),
                    simulations[source].fs,
                    FIRST_ACQUISITION + j * EVERY,
                )
                if not created:
                    raise SystemExit(f"copy {copy} of record {source} was stored before")
                verdict = inspections.store_verdict(
                    session, record, structure_row, evaluations[source], settings, new_record=True
                )
                statuses[verdict.status] = statuses.get(verdict.status, 0) + 1
                with_k_hat += verdict.k_hat is not None and verdict.reference_mode is not None
                newest = record.id
                bar.advance(storing)
            session.commit()
    return Seeded(structure["id"], org.keys["viewer"], newest, n_verdicts, statuses, with_k_hat)


def time_page(client: httpx.Client, name: str, path: str, repeats: int) -> tuple[Timing, httpx.Response]:
    """One warm-up, then ``repeats`` timed requests; the last answer is returned for checks."""
    response = client.get(path)
    if response.status_code != 200:
        raise SystemExit(f"GET {path} answered {response.status_code}: {response.text[:300]}")
    seconds = []
    for _ in range(repeats):
        began = time.perf_counter()
        response = client.get(path)
        seconds.append(time.perf_counter() - began)
        if response.status_code != 200:
            raise SystemExit(f"GET {path} answered {response.status_code}")
    return Timing(name, seconds, len(response.content)), response


def chart_points(page: httpx.Response) -> dict[str, int]:
    """Points of the structure page's k̂ and Q markers, as it embeds them for plotly.js."""
    figures = charts(page)
    return {
        name: sum(len(trace["x"]) for trace in figures[name]["data"] if trace.get("mode") == "markers")
        for name in ("k_hat", "q")
    }


def time_browser(url: str, structure_id: int, key: str, repeats: int) -> tuple[list[Timing], list[str]]:
    from playwright.sync_api import sync_playwright

    path = f"{DASHBOARD}/structures/{structure_id}"
    drawn: list[float] = []
    html: list[float] = []
    ready: list[float] = []
    errors: list[str] = []
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            context = browser.new_context(viewport={"width": 1360, "height": 900})
            context.set_default_timeout(BROWSER_TIMEOUT_MS)
            context.add_init_script(DRAWN_PROBE)
            page = context.new_page()
            page.on("pageerror", lambda error: errors.append(str(error)))

            def wait_drawn() -> float:
                page.wait_for_selector("#chart-q[data-drawn=true]")
                page.wait_for_selector("#chart-k_hat[data-drawn=true]")
                page.wait_for_function("window.__chartsDrawnAt !== undefined")
                return page.evaluate("window.__chartsDrawnAt") / 1000

            page.goto(f"{url}{DASHBOARD}/login?next={path}")
            page.fill("#api_key", key)
            page.click("#login")
            page.wait_for_url(f"{url}{path}")
            wait_drawn()  # the warm-up: plotly.js is now in the browser's cache
            for _ in range(repeats):
                page.goto(f"{url}{path}")
                drawn.append(wait_drawn())
                navigation = page.evaluate("performance.getEntriesByType('navigation')[0].toJSON()")
                html.append(navigation["responseEnd"] / 1000)
                ready.append(navigation["domContentLoadedEventStart"] / 1000)
        finally:
            browser.close()
    return [
        Timing("structure page, Chromium", drawn, note="navigation start → all drawn"),
        Timing("  of which: HTML received", html, note="responseEnd"),
        Timing("  of which: scripts run", ready, note="DOMContentLoaded (plotly.js run)"),
    ], errors


def browser_unavailable() -> str | None:
    if not CHROMIUM.exists():
        return f"{CHROMIUM} is not installed (sudo bash scripts/ensure-chromium.sh)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError as error:
        return f"the playwright package cannot be imported ({error})"
    return None


def report(timings: list[Timing], title: str) -> None:
    table = Table(title=title, title_justify="left")
    table.add_column("measure")
    table.add_column("n", justify="right")
    for column in ("min", "median", "p95", "max"):
        table.add_column(f"{column} [ms]", justify="right")
    table.add_column("size", justify="right")
    table.add_column("note")
    for timing in timings:
        ms = 1000 * np.array(timing.seconds)
        p95 = f"{np.percentile(ms, 95):.1f}" if ms.size >= 20 else "—"
        size = f"{timing.size_bytes / 1024:,.0f} KB" if timing.size_bytes is not None else ""
        table.add_row(
            timing.name,
            str(ms.size),
            f"{ms.min():.1f}",
            f"{np.median(ms):.1f}",
            p95,
            f"{ms.max():.1f}",
            size,
            timing.note,
        )
    console.print(table)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--verdicts", type=int, default=TARGET_VERDICTS, help="history length to seed")
    parser.add_argument("--distinct", type=int, default=200, help="distinct records inspected for real")
    parser.add_argument("--repeats", type=int, default=20, help="timed requests per page")
    parser.add_argument("--browser-repeats", type=int, default=5, help="timed loads in Chromium")
    parser.add_argument("--database-url", help="an existing database (default: a fresh SQLite file)")
    args = parser.parse_args(argv)
    if not 1 <= args.distinct <= args.verdicts:
        parser.error("--distinct must be between 1 and --verdicts")
    started = time.perf_counter()
    with ExitStack() as stack:
        url = args.database_url
        if url is None:
            folder = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="narxwatch-dashboard-")))
            url = f"sqlite:///{folder / 'narxwatch.db'}"
        server = stack.enter_context(LiveServer(Settings(database_url=url)))
        console.print(f"seeding {args.verdicts} verdicts from {args.distinct} inspected records …")
        seeded = seed(server, args.verdicts, args.distinct)
        seeding = time.perf_counter() - started
        console.print(f"seeded in {seeding:.1f} s: verdicts {seeded.statuses}")
        structure_path = f"{DASHBOARD}/structures/{seeded.structure_id}"
        with logged_in(server, seeded.viewer_key) as client:
            structure, page = time_page(client, "structure page (HTTP)", structure_path, args.repeats)
            fleet, _ = time_page(client, "fleet page (HTTP)", DASHBOARD, args.repeats)
            record, _ = time_page(
                client,
                "record page, newest (HTTP)",
                f"{DASHBOARD}/records/{seeded.newest_record_id}",
                args.repeats,
            )
        points = chart_points(page)
        structure.note = f"k̂ {points['k_hat']} + Q {points['q']} points"
        expected = {"k_hat": seeded.with_k_hat, "q": seeded.verdicts}
        failures = [
            f"the {name} chart holds {points[name]} points, not {count}"
            for name, count in expected.items()
            if points[name] != count
        ]
        unavailable = browser_unavailable()
        browser: list[Timing] = []
        if unavailable is None:
            console.print(f"timing the structure page in headless Chromium ({args.browser_repeats} loads) …")
            browser, errors = time_browser(
                server.url, seeded.structure_id, seeded.viewer_key, args.browser_repeats
            )
            failures += [f"the page raised in the browser: {error}" for error in errors]
    total = time.perf_counter() - started
    console.print()
    report(
        [structure, fleet, record, *browser],
        f"Dashboard with {seeded.verdicts} verdicts on one structure ({url.split(':')[0]})",
    )
    if unavailable is not None:
        console.print(f"browser column skipped: {unavailable}")
    console.print(f"total run time {total:.1f} s (seeding {seeding:.1f} s)")
    server_median = statistics.median(structure.seconds)
    verdict = "met" if server_median <= TARGET_SECONDS else "MISSED"
    line = f"server median {1000 * server_median:.0f} ms: {verdict}"
    if browser:
        browser_median = statistics.median(browser[0].seconds)
        line += f"; browser median {1000 * browser_median:.0f} ms: "
        line += "met" if browser_median <= TARGET_SECONDS else "MISSED"
    else:
        line += "; browser not measured"
    scale = "" if seeded.verdicts == TARGET_VERDICTS else f" (measured with {seeded.verdicts})"
    console.print(f"target: the structure page with 10 000 verdicts loads in ≤ 1 s{scale}: {line}")
    for failure in failures:
        console.print(f"[red]FAILED: {failure}[/red]")
    if failures:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
