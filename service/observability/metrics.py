"""Prometheus metrics: business counts read from the database, request latency kept per process.

Records, verdicts and ended jobs are counted in the database by the transactions that write them
(``structure_states``, ``job_counts``), so the counts are exact however many service and worker
processes write them, no process has to see every event, and a scrape reads a row per structure,
never the history. Request latency is a histogram each process keeps in memory; under several uvicorn
workers, prometheus-client's multiprocess mode (``PROMETHEUS_MULTIPROC_DIR``, set before the
processes start) keeps it in files that any worker's scrape adds up.
"""

from __future__ import annotations

import datetime as dt
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.metrics_core import CounterMetricFamily, GaugeMetricFamily, Metric, SummaryMetricFamily
from prometheus_client.multiprocess import MultiProcessCollector
from prometheus_client.registry import Collector
from prometheus_client.samples import Sample
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from service.domain.fleet import STATUSES
from service.jobs.types import QueueStats
from service.observability import MULTIPROCESS_DIR
from service.tables import StructureState

QUANTILES = (0.5, 0.95, 0.99)
LATENCY_WINDOW = dt.timedelta(minutes=5)

# The process's own registry: the default one would add process and platform metrics that mean
# nothing once several processes answer the same scrape.
_REQUESTS = CollectorRegistry()
REQUEST_SECONDS = Histogram(
    "narxwatch_http_request_duration_seconds",
    "Time from an HTTP request's arrival to the end of its answer, by route template.",
    ["method", "route", "status"],
    buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0),
    registry=_REQUESTS,
)
# Closed by the head's deadline (``service.api.protocol``): a burst of them is a slow-header
# attack, or clients behind a link slower than NARXWATCH_HEADER_TIMEOUT_SECONDS allows. Counted,
# not logged one by one: an attack would write a line per connection.
HEADER_TIMEOUTS = Counter(
    "narxwatch_http_header_timeouts",
    "Connections closed because a request's head did not arrive within "
    "NARXWATCH_HEADER_TIMEOUT_SECONDS, by what had arrived of it: part (answered 408) or none.",
    ["head"],
    registry=_REQUESTS,
)


@dataclass(frozen=True)
class DatabaseCollector:
    """Fleet-wide counts read from the database: no label value is an organisation's name or id,
    or anything an organisation chose."""

    session: Session
    queue_stats: Callable[[Session, dt.timedelta], QueueStats]

    def collect(self) -> Iterator[Metric]:
        columns = [StructureState.records, *(getattr(StructureState, status) for status in STATUSES)]
        records, *by_status = self.session.execute(
            select(*(func.coalesce(func.sum(c), 0) for c in columns))
        ).one()
        yield CounterMetricFamily(
            "narxwatch_records_received",
            "Records stored (an identical re-upload is the same record).",
            value=records,
        )
        # By status only, a set the code fixes: fault-mode names are chosen by each organisation,
        # so as label values they would be unbounded and would tell any reader of the metrics
        # what another organisation monitors.
        verdicts = CounterMetricFamily(
            "narxwatch_verdicts", "Inspections stored, by status.", labels=["status"]
        )
        for status, count in zip(STATUSES, by_status, strict=True):
            verdicts.add_metric([status], count)
        yield verdicts
        yield from queue_metrics(self.queue_stats(self.session, LATENCY_WINDOW))


def queue_metrics(stats: QueueStats) -> Iterator[Metric]:
    jobs = GaugeMetricFamily("narxwatch_jobs", "Jobs in the queue, by state.", labels=["state"])
    for state, count in sorted(stats.depth.items()):
        jobs.add_metric([state], count)
    yield jobs
    yield GaugeMetricFamily(
        "narxwatch_job_latency_window_seconds",
        "The window narxwatch_job_latency_seconds covers.",
        value=stats.window_seconds,
    )
    # Count and sum are over the window, not since start: read them as gauges (sum/count is the
    # window's mean latency, count/window its throughput), not through rate().
    latency = SummaryMetricFamily(
        "narxwatch_job_latency_seconds",
        "Seconds from enqueue to finish of the jobs finished within the window; count and sum too.",
        count_value=len(stats.latencies),
        sum_value=float(sum(stats.latencies)),
    )
    if stats.latencies:
        for quantile, value in zip(QUANTILES, np.quantile(stats.latencies, QUANTILES), strict=True):
            latency.samples.append(Sample(latency.name, {"quantile": str(quantile)}, float(value)))
    yield latency


def request_metrics() -> Collector:
    """This process's request histogram and head timeouts, or every process's in multiprocess mode."""
    directory = os.environ.get(MULTIPROCESS_DIR)
    return MultiProcessCollector(None, path=directory) if directory else _REQUESTS


def exposition(*collectors: Collector) -> bytes:
    """The text exposition of the request histogram and ``collectors``, collected now."""
    registry = CollectorRegistry()
    for collector in (request_metrics(), *collectors):
        registry.register(collector)
    return generate_latest(registry)
