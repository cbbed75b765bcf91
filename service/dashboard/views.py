"""What each dashboard page shows, gathered from the domain services and shaped for its template."""

from __future__ import annotations

import datetime as dt
from collections import Counter
from dataclasses import dataclass
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from models.errors import InputError
from models.fnarx import FNARX
from models.free_run_inspection import FreeRunMode
from models.pooled import PooledModel
from models.validation import one_step_fit
from models.vector import VectorFNARX
from recordfiles.channels import matched
from service.dashboard import figures
from service.domain import alarms, fleet, history, modelling, records, refinements, structures, timeline
from service.domain.history import Status
from service.domain.inspections import MODEL_REFS
from service.schemas import ModeResult, VerdictOut
from service.security import Principal
from service.tables import ModelVersion, Record, Structure, Verdict

# Samples of a record drawn on its page; longer records show their start (the residual's
# autocorrelation is always of the whole record).
RECORD_POINTS = 20_000
HISTORY_PAGE = 25
FLEET_PAGE = 50  # structures per fleet page
CHART_ALARMS = 100  # the newest alarms marked on the k̂ chart
# The fleet page's open alarms: the oldest this many, with the count of all. Every structure's page
# lists its own; a fleet with a tenth of 10 000 structures in alarm made a page of 460 KB.
FLEET_ALARMS = 50
# A structure's page lists this many unresolved alarms in view (open ones first), the rest folded
# away, and its newest resolved ones folded too: the page opens on the status and the charts.
STRUCTURE_ALARMS = 3
RESOLVED_ALARMS = 10


@dataclass(frozen=True)
class HistoryFilter:
    """The verdict table's filters and page, as the history API takes them."""

    status: Status | None = None
    fault_mode: str | None = None
    start: dt.datetime | None = None
    end: dt.datetime | None = None
    cursor: str | None = None

    def query(self, **changes: Any) -> dict[str, str]:
        """The page's query parameters with ``changes`` applied (None drops one)."""
        values = {
            "status": self.status,
            "fault_mode": self.fault_mode,
            "start": self.start.isoformat() if self.start else None,
            "end": self.end.isoformat() if self.end else None,
            "cursor": self.cursor,
        } | changes
        return {key: str(value) for key, value in values.items() if value}


@dataclass(frozen=True)
class FleetFilter:
    """The fleet table's filters and page, as ``GET /structures`` takes them."""

    standing: fleet.Standing | None = None
    name: str | None = None
    cursor: str | None = None

    def query(self, **changes: Any) -> dict[str, str]:
        """The page's query parameters with ``changes`` applied (None drops one)."""
        values = {"status": self.standing, "name": self.name, "cursor": self.cursor} | changes
        return {key: str(value) for key, value in values.items() if value}


def fleet_page(session: Session, principal: Principal, filters: FleetFilter) -> dict[str, Any]:
    page = fleet.fleet(
        session,
        principal,
        standing=filters.standing,
        name=filters.name,
        cursor=filters.cursor,
        limit=FLEET_PAGE,
    )
    unresolved = alarms.unresolved_alarms(session, principal, limit=FLEET_ALARMS)
    return {
        "rows": page.items,
        "next_cursor": page.next_cursor,
        "filters": filters,
        "standings": fleet.STANDINGS,
        "alarms": unresolved,
        "alarms_total": alarms.count_unresolved(session, principal)
        if len(unresolved) == FLEET_ALARMS
        else len(unresolved),
        # The alarm table names each alarm's structure, which may be on another page.
        "names": structures.structure_names(session, principal, {a.structure_id for a in unresolved}),
    }


def structure_page(
    session: Session, principal: Principal, structure_id: int, filters: HistoryFilter, limit: dt.datetime
) -> dict[str, Any]:
    """``limit``: the latest acquisition that stands for the structure (``records.acquisition_limit``)."""
    structure = structures.get_structure(session, principal, structure_id)
    status = fleet.structure_status(session, structure)
    points = timeline.timeline(session, structure_id)
    page = history.history(
        session,
        principal,
        structure_id,
        start=filters.start,
        end=filters.end,
        status=filters.status,
        fault_mode=filters.fault_mode,
        cursor=filters.cursor,
        limit=HISTORY_PAGE,
    )
    versions = modelling.list_models(session, principal, structure_id)
    # A pooled fault mode's trajectories depend on the conditions too: none is drawn for it here.
    active_modes = [
        v
        for v in versions
        if v.active and v.kind == "fault_mode" and isinstance(modelling.parsed_model(v), FNARX)
    ]
    alpha = status.latest.alpha if status.latest is not None else 0.05
    level = f"{1 - alpha:.0%}"
    # A structure has at most one unresolved alarm per rule and fault mode: all of them are read.
    unresolved = sorted(
        alarms.unresolved_alarms(session, principal, structure_id), key=lambda a: a.state != "open"
    )
    rules = alarms.get_rules(session, principal, structure_id, limit)
    cusums = alarms.cusum_series(session, structure_id, limit)
    charted = alarms.list_alarms(session, principal, structure_id=structure_id, limit=CHART_ALARMS).items
    # A chart with nothing to draw is left out: a structure judged by its baseline alone has no k̂
    # and no fault mode's Q, only its severity (which then marks the alarms).
    k_hat = cusums or any(p.k_hat is not None for p in points.points)
    charts = (
        ({"k_hat": figures.k_hat_figure(points.points, level, cusums, charted)} if k_hat else {})
        | ({"q": figures.q_figure(points.points, alpha)} if any(p.modes for p in points.points) else {})
        | (
            {"severity": figures.severity_figure(points.points, () if k_hat else charted)}
            if any(p.severity is not None for p in points.points)
            else {}
        )
        | {
            f"k_hat-{name}": figures.k_hat_condition_figure(points.points, name, unit, level)
            for name, unit in points.units.items()
        }
        | {
            f"trajectories-{v.name}": figures.trajectories_figure(modelling.parsed_model(v))  # type: ignore[arg-type]
            for v in active_modes
        }
    )
    resolved = alarms.list_alarms(
        session, principal, structure_id=structure_id, state="resolved", limit=RESOLVED_ALARMS
    )
    return {
        "structure": structure,
        "alarms": unresolved[:STRUCTURE_ALARMS],
        "more_alarms": unresolved[STRUCTURE_ALARMS:],
        "alarm_states": Counter(a.state for a in unresolved),
        "resolved": resolved.items,
        "more_resolved": resolved.next_cursor is not None,
        "cusum_problem": rules.cusum_problem,
        "cusum_skipped": rules.cusum_skipped,
        "names": {structure.id: structure.name},
        "status": status,
        "timeline": points,
        "page": page,
        "filters": filters,
        "fault_modes": sorted({v.name for v in versions if v.kind == "fault_mode"}),
        "models": [v for v in versions if v.active],
        "trajectory_models": active_modes,
        "refinements": refinements.list_refinements(session, principal, structure_id),
        "charts": charts,
    }


def record_page(session: Session, principal: Principal, record_id: int, mode: str | None) -> dict[str, Any]:
    """The record with its newest verdict, and the fit of one fault mode at its k̂ (by default the
    verdict's reference mode, else the mode with the smallest residual variance)."""
    record = records.get_record(session, principal, record_id)
    structure = structures.get_structure(session, principal, record.structure_id)
    verdict = session.scalar(
        select(Verdict)
        .where(Verdict.record_id == record.id)
        .order_by(Verdict.created_at.desc(), Verdict.id.desc())
        .limit(1)
        .options(MODEL_REFS)
    )
    context: dict[str, Any] = {"record": record, "structure": structure, "verdict": None, "charts": {}}
    if verdict is None:
        return context
    out = VerdictOut.model_validate(verdict, from_attributes=True)
    if not out.modes:  # the verdict of a pooled baseline alone: no fault mode to draw the fit of
        return context | {"verdict": out}
    chosen = _chosen_mode(out.modes, out.reference_mode, mode)
    if record.signals_pruned_at is not None:  # the verdict stands; the fit needs the signals
        return context | {"verdict": out, "mode": chosen}
    version = next(v for v in verdict.models if v.name == chosen.name)
    parsed = modelling.parsed_model(version)
    if isinstance(parsed, FreeRunMode):  # judged by its free run: no one-step fit to draw
        return context | {"verdict": out, "mode": chosen, "free_run": True}
    if isinstance(parsed, VectorFNARX):
        return context | _channel_residuals(record, structure, out, chosen, version, parsed)
    fault_mode = (
        parsed.fnarx_at(records.condition_values(record.conditions))
        if isinstance(parsed, PooledModel)
        else parsed
    )
    model = fault_mode.narx_at(chosen.k_hat)
    fit = one_step_fit(model, *records.signals(record), out.lags, out.alpha)
    label = f"{chosen.name} model at k̂ = {chosen.k_hat:.2f} %"
    context |= {
        "verdict": out,
        "mode": chosen,
        "version": version,
        "fit": fit,
        "shown": min(RECORD_POINTS, fit.measured.size),
        "charts": figures.record_figures(
            fit, record.fs, model.max_lag, RECORD_POINTS, label, structure.response
        ),
    }
    return context


def _channel_residuals(
    record: Record,
    structure: Structure,
    out: VerdictOut,
    chosen: ModeResult,
    version: ModelVersion,
    model: VectorFNARX,
) -> dict[str, Any]:
    """A vector verdict's page: the chosen mode's one-step residual at its k̂ on each channel, in
    the order the model names them."""
    channels = version.training["channels"]
    x, y = records.signals(record)
    residual = model.residual(x, y[:, matched(record.channels or (), channels, version.name)], chosen.k_hat)
    label = f"{chosen.name} model at k̂ = {chosen.k_hat:.2f} %"
    shown = min(RECORD_POINTS, len(residual))
    return {
        "verdict": out,
        "mode": chosen,
        "version": version,
        "channels": channels,
        "residual_samples": len(residual),
        "shown": shown,
        "charts": figures.channel_figures(
            residual, channels, record.fs, model.lags, RECORD_POINTS, label, structure.response
        ),
    }


def _chosen_mode(modes: list[ModeResult], reference: str | None, wanted: str | None) -> ModeResult:
    by_name = {m.name: m for m in modes}
    if wanted is not None:
        if wanted not in by_name:
            raise InputError(
                f"this verdict has no fault mode {wanted!r}; it has {', '.join(sorted(by_name))}"
            )
        return by_name[wanted]
    if reference is not None:
        return by_name[reference]
    return min(modes, key=lambda m: m.residual_variance)


def refinement_page(session: Session, principal: Principal, refinement_id: int) -> dict[str, Any]:
    refinement = refinements.get_refinement(session, principal, refinement_id)
    structure = structures.get_structure(session, principal, refinement.structure_id)
    report = refinement.report
    # Reports stored before refinements judged several records hold one test, as before/after.
    tests = report.get("tests") or [{"before": report["before"], "after": report["after"]}]
    return {
        "refinement": refinement,
        "structure": structure,
        "report": report,
        "tests": tests,
        "fitted": refinement.record_ids_of("estimation"),
        "charts": {
            "errors": figures.refinement_figure(report["before"], report["after"], structure.response)
        },
    }
