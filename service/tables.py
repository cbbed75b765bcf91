"""The database schema: organisations, keys, structures, model versions, records, verdicts."""

from __future__ import annotations

import datetime as dt
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    String,
    Text,
    TypeDecorator,
    UniqueConstraint,
    text,
)
from sqlalchemy.dialects.postgresql import BYTEA, JSONB
from sqlalchemy.orm import Mapped, mapped_column, relationship

from recordfiles.conditions import NAME_LENGTH
from recordfiles.quantities import UNIT_LENGTH, SignalDeclaration
from service.db import Base

Document = JSON().with_variant(JSONB(), "postgresql")
# A document that may be absent: None is SQL NULL, which ``IS NULL`` finds, not JSON's null.
OptionalDocument = JSON(none_as_null=True).with_variant(JSONB(none_as_null=True), "postgresql")
Blob = LargeBinary().with_variant(BYTEA(), "postgresql")
MAX_ID = 2**31 - 1  # ids are 32-bit integers (Integer) in every database narxwatch runs on


def utcnow() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


class UTCDateTime(TypeDecorator[dt.datetime]):
    """Timestamps stored in UTC and always returned timezone-aware (SQLite keeps no zone)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: dt.datetime | None, dialect: Any) -> dt.datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError("naive datetimes are ambiguous; give a timezone")
        return value.astimezone(dt.UTC)

    def process_result_value(self, value: dt.datetime | None, dialect: Any) -> dt.datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=dt.UTC) if value.tzinfo is None else value.astimezone(dt.UTC)


class Organisation(Base):
    __tablename__ = "organisations"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)


class ApiKey(Base):
    """An API key, stored as its SHA-256: keys are 256-bit random, so a fast hash is safe.

    ``expires_at`` (None: never) and ``revoked_at`` end it; ``last_used_at`` is kept to the
    minute (``service.security``), so that recording it is not a write on every request."""

    __tablename__ = "api_keys"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    organisation_id: Mapped[int] = mapped_column(ForeignKey("organisations.id", ondelete="CASCADE"))
    prefix: Mapped[str] = mapped_column(String(16), unique=True)
    key_hash: Mapped[str] = mapped_column(String(64))
    role: Mapped[str] = mapped_column(String(16))
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)
    revoked_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)
    expires_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)
    last_used_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)

    organisation: Mapped[Organisation] = relationship()


class DashboardSession(Base):
    """A dashboard login. Its cookie holds a random token; only the token's SHA-256 is stored,
    with the key it was opened with, so revoking the key ends the login too."""

    __tablename__ = "dashboard_sessions"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)
    api_key_id: Mapped[int] = mapped_column(ForeignKey("api_keys.id", ondelete="CASCADE"), index=True)
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)
    expires_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, index=True)


class Structure(Base):
    """A monitored asset."""

    __tablename__ = "structures"
    __table_args__ = (UniqueConstraint("organisation_id", "name"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    organisation_id: Mapped[int] = mapped_column(
        ForeignKey("organisations.id", ondelete="CASCADE"), index=True
    )
    name: Mapped[str] = mapped_column(String(200))
    fs: Mapped[float] = mapped_column(Float)
    description: Mapped[str] = mapped_column(Text, default="")
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)
    # What x and y measure (``recordfiles.quantities``); NULL when not declared, and a unit NULL
    # when not stated. Every response channel of the structure is of the response's quantity.
    excitation_quantity: Mapped[str | None] = mapped_column(String(16), nullable=True)
    excitation_unit: Mapped[str | None] = mapped_column(String(UNIT_LENGTH), nullable=True)
    response_quantity: Mapped[str | None] = mapped_column(String(16), nullable=True)
    response_unit: Mapped[str | None] = mapped_column(String(UNIT_LENGTH), nullable=True)

    @property
    def excitation(self) -> SignalDeclaration | None:
        return _declared(self.excitation_quantity, self.excitation_unit)

    @property
    def response(self) -> SignalDeclaration | None:
        return _declared(self.response_quantity, self.response_unit)


def _declared(quantity: str | None, unit: str | None) -> SignalDeclaration | None:
    return None if quantity is None else SignalDeclaration(quantity, unit)  # type: ignore[arg-type]


class ModelVersion(Base):
    """An immutable trained model; one version per name is active at a time, which a partial
    unique index guarantees (``service.domain.modelling`` serialises the changes per structure)."""

    __tablename__ = "model_versions"
    __table_args__ = (
        UniqueConstraint("structure_id", "name", "version"),
        Index(
            "uq_model_versions_active",
            "structure_id",
            "name",
            unique=True,
            sqlite_where=text("active"),
            postgresql_where=text("active"),
        ),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    structure_id: Mapped[int] = mapped_column(ForeignKey("structures.id", ondelete="CASCADE"), index=True)
    kind: Mapped[str] = mapped_column(String(16))
    name: Mapped[str] = mapped_column(String(100))
    version: Mapped[int] = mapped_column(Integer)
    document: Mapped[dict[str, Any]] = mapped_column(Document)
    training: Mapped[dict[str, Any]] = mapped_column(Document)
    statistics: Mapped[dict[str, Any]] = mapped_column(Document)
    active: Mapped[bool] = mapped_column(Boolean, default=False)
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)


# Records whose signals are still stored: the only ones the retention's signal pass looks at, so
# that each of its runs reads what is new past the horizon, not every record pruned before.
SIGNALS_KEPT = text("signals_pruned_at IS NULL")


class Record(Base):
    """An excitation/response record; x and y are stored as .npy bytes.

    A record of several response channels (``recordfiles.channels``) has y of shape (N, K) and the
    channels' names in ``channels``, in y's column order; one of one response has y of shape (N,)
    and ``channels`` None.

    ``signals_pruned_at`` is when the organisation's retention (``service.domain.retention``)
    dropped x and y (then empty); the row stays, with its conditions, for its verdicts."""

    __tablename__ = "records"
    __table_args__ = (
        UniqueConstraint("structure_id", "sha256"),
        Index(
            "ix_records_signals_kept",
            "structure_id",
            "acquired_at",
            sqlite_where=SIGNALS_KEPT,
            postgresql_where=SIGNALS_KEPT,
        ),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    structure_id: Mapped[int] = mapped_column(ForeignKey("structures.id", ondelete="CASCADE"), index=True)
    fs: Mapped[float] = mapped_column(Float)
    n_samples: Mapped[int] = mapped_column(Integer)
    acquired_at: Mapped[dt.datetime] = mapped_column(UTCDateTime)
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)
    sha256: Mapped[str] = mapped_column(String(64))
    x: Mapped[bytes] = mapped_column(Blob)
    y: Mapped[bytes] = mapped_column(Blob)
    channels: Mapped[list[str] | None] = mapped_column(OptionalDocument, nullable=True)
    signals_pruned_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)

    conditions: Mapped[list[RecordCondition]] = relationship(
        order_by="RecordCondition.name", passive_deletes=True
    )


class RecordCondition(Base):
    """One operating condition of a record (``recordfiles.conditions``): a row per name, so that a
    structure's records can be found and ordered by a condition's value through the index."""

    __tablename__ = "record_conditions"
    __table_args__ = (Index("ix_record_conditions_value", "structure_id", "name", "value"),)

    record_id: Mapped[int] = mapped_column(ForeignKey("records.id", ondelete="CASCADE"), primary_key=True)
    name: Mapped[str] = mapped_column(String(NAME_LENGTH), primary_key=True)
    # The record's structure, repeated so that the index serves "records of a structure by condition".
    structure_id: Mapped[int] = mapped_column(ForeignKey("structures.id", ondelete="CASCADE"))
    value: Mapped[float] = mapped_column(Float)
    unit: Mapped[str | None] = mapped_column(String(UNIT_LENGTH), nullable=True)


class Verdict(Base):
    """Every figure of one inspection, unique per record and set of model versions."""

    __tablename__ = "verdicts"
    __table_args__ = (
        UniqueConstraint("record_id", "model_set"),
        Index("ix_verdicts_history", "structure_id", "acquired_at", "id"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    record_id: Mapped[int] = mapped_column(ForeignKey("records.id", ondelete="CASCADE"), index=True)
    structure_id: Mapped[int] = mapped_column(ForeignKey("structures.id", ondelete="CASCADE"))
    acquired_at: Mapped[dt.datetime] = mapped_column(UTCDateTime)
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)
    model_set: Mapped[str] = mapped_column(String(200))
    status: Mapped[str] = mapped_column(String(16))
    fault_detected: Mapped[bool] = mapped_column(Boolean)
    fault_mode: Mapped[str | None] = mapped_column(String(100), nullable=True)
    reference_mode: Mapped[str | None] = mapped_column(String(100), nullable=True)
    k_hat: Mapped[float | None] = mapped_column(Float, nullable=True)
    sigma_k: Mapped[float | None] = mapped_column(Float, nullable=True)
    interval_low: Mapped[float | None] = mapped_column(Float, nullable=True)
    interval_high: Mapped[float | None] = mapped_column(Float, nullable=True)
    alpha: Mapped[float] = mapped_column(Float)
    # None for a verdict of a healthy baseline alone, which has no Ljung–Box test
    lags: Mapped[int | None] = mapped_column(Integer, nullable=True)
    n_samples: Mapped[int] = mapped_column(Integer)
    # None for a verdict of a pooled baseline alone, which has no magnitude test
    z_critical: Mapped[float | None] = mapped_column(Float, nullable=True)
    # None for a vector verdict, which no whiteness test detects (models.vector.vector_verdict)
    q_critical_detection: Mapped[float | None] = mapped_column(Float, nullable=True)
    detected_by: Mapped[list[str]] = mapped_column(Document)
    modes: Mapped[list[dict[str, Any]]] = mapped_column(Document)
    # The figures of a verdict of a healthy baseline alone (models.novelty.NoveltyVerdict.to_dict);
    # None for every other verdict.
    novelty: Mapped[dict[str, Any] | None] = mapped_column(OptionalDocument, nullable=True)

    models: Mapped[list[ModelVersion]] = relationship(secondary="verdict_models")
    # The conditions of the verdict's record, which every verdict answer shows.
    conditions: Mapped[list[RecordCondition]] = relationship(
        primaryjoin="Verdict.record_id == foreign(RecordCondition.record_id)",
        order_by="RecordCondition.name",
        viewonly=True,
    )

    @property
    def interval(self) -> tuple[float, float] | None:
        """k̂'s interval as the API gives it; None for a verdict that sizes no fault."""
        if self.interval_low is None or self.interval_high is None:
            return None
        return (self.interval_low, self.interval_high)

    @property
    def model_versions(self) -> list[ModelVersion]:
        """The versions that judged the record, by name."""
        return sorted(self.models, key=lambda m: m.name)


class StructureState(Base):
    """Where a structure stands, kept in the transaction of each write that changes it
    (``service.domain.fleet``), so that neither the fleet views nor ``/metrics`` read its history.

    ``status`` is that of the ``latest`` verdict (newest acquisition, then newest id; None before
    the first), ``since`` when its current run of that status began; ``records`` and the verdict
    counts, one a status, are how many the structure has. ``organisation_id`` is the structure's, kept
    here so that a page of the fleet is one range of an index: ``ix_structure_states_fleet``, or
    ``ix_structure_states_fleet_status`` for a page of one status. (No index holds the latest
    verdict's columns, which change at every verdict: PostgreSQL can then update the row in place.)
    """

    __tablename__ = "structure_states"
    __table_args__ = (
        Index("ix_structure_states_fleet", "organisation_id", "structure_id"),
        Index("ix_structure_states_fleet_status", "organisation_id", "status", "structure_id"),
    )

    structure_id: Mapped[int] = mapped_column(
        ForeignKey("structures.id", ondelete="CASCADE"), primary_key=True, autoincrement=False
    )
    organisation_id: Mapped[int] = mapped_column(ForeignKey("organisations.id", ondelete="CASCADE"))
    status: Mapped[str | None] = mapped_column(String(16), nullable=True)
    since: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)
    latest_verdict_id: Mapped[int | None] = mapped_column(
        ForeignKey("verdicts.id", ondelete="SET NULL"), nullable=True
    )
    latest_acquired_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)
    records: Mapped[int] = mapped_column(BigInteger, default=0)
    healthy: Mapped[int] = mapped_column(BigInteger, default=0)
    faulty: Mapped[int] = mapped_column(BigInteger, default=0)
    unknown_fault: Mapped[int] = mapped_column(BigInteger, default=0)
    anomaly: Mapped[int] = mapped_column(BigInteger, default=0)

    latest: Mapped[Verdict | None] = relationship()


class RetentionPolicy(Base):
    """How long an organisation keeps its records' signals and its verdicts, in days (None:
    forever); an organisation without a row keeps the defaults (``service.domain.retention``).
    ``last_pruned_at`` is when its last pruning was queued, claimed by compare-and-set."""

    __tablename__ = "retention_policies"

    organisation_id: Mapped[int] = mapped_column(
        ForeignKey("organisations.id", ondelete="CASCADE"), primary_key=True, autoincrement=False
    )
    signal_days: Mapped[int | None] = mapped_column(Integer, nullable=True)
    verdict_days: Mapped[int | None] = mapped_column(Integer, nullable=True)
    updated_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)
    last_pruned_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)


class VerdictModel(Base):
    """The exact model versions a verdict was computed with."""

    __tablename__ = "verdict_models"

    verdict_id: Mapped[int] = mapped_column(ForeignKey("verdicts.id", ondelete="CASCADE"), primary_key=True)
    model_version_id: Mapped[int] = mapped_column(
        ForeignKey("model_versions.id", ondelete="RESTRICT"), primary_key=True
    )


class Refinement(Base):
    """One pass of the refinement loop on stored records, starting from a baseline version
    (``base_model_id``) or, with none, from the linear orders the loop chose.

    ``records`` lists the records it was fitted on and those it was judged on, whole;
    ``record_id`` is the first record fitted. ``refined_model_id`` names the new, inactive
    version the effects it added produced, or the linear model chosen when there was no base
    (None when a base was given and no effect was significant); ``report`` holds the effects
    with their evidence and the held-out errors before and after.
    """

    __tablename__ = "refinements"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    structure_id: Mapped[int] = mapped_column(ForeignKey("structures.id", ondelete="CASCADE"), index=True)
    record_id: Mapped[int] = mapped_column(ForeignKey("records.id", ondelete="CASCADE"))
    base_model_id: Mapped[int | None] = mapped_column(
        ForeignKey("model_versions.id", ondelete="RESTRICT"), nullable=True
    )
    refined_model_id: Mapped[int | None] = mapped_column(
        ForeignKey("model_versions.id", ondelete="RESTRICT"), nullable=True
    )
    report: Mapped[dict[str, Any]] = mapped_column(Document)
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)

    base_model: Mapped[ModelVersion | None] = relationship(foreign_keys=[base_model_id])
    refined_model: Mapped[ModelVersion | None] = relationship(foreign_keys=[refined_model_id])
    records: Mapped[list[RefinementRecord]] = relationship(
        order_by="RefinementRecord.position", cascade="all, delete-orphan"
    )

    def record_ids_of(self, role: str) -> list[int]:
        """The ids of the records in ``role`` ("estimation" or "test"), in the order given."""
        return [r.record_id for r in self.records if r.role == role]


class RefinementRecord(Base):
    """A record a refinement was fitted on (``role`` "estimation") or judged on, whole ("test"),
    at its ``position`` in the request's list of its role."""

    __tablename__ = "refinement_records"

    refinement_id: Mapped[int] = mapped_column(
        ForeignKey("refinements.id", ondelete="CASCADE"), primary_key=True
    )
    record_id: Mapped[int] = mapped_column(
        ForeignKey("records.id", ondelete="CASCADE"), primary_key=True, index=True
    )
    role: Mapped[str] = mapped_column(String(16))
    position: Mapped[int] = mapped_column(Integer)


class Job(Base):
    """A queued task of the embedded job backend (the distributed one keeps Procrastinate's).

    ``task`` names a function of ``service.jobs.tasks`` and ``args`` its keyword arguments. A
    worker claims a job by setting ``locked_until``; a job whose lease ran out (its worker died)
    is claimed again, so every job runs at least once. Tasks are idempotent: an inspection stores
    at most one verdict per record and model set. ``priority`` is minus the number of its
    organisation's jobs waiting when it was queued (``service.jobs``: fair share).
    """

    __tablename__ = "jobs"
    __table_args__ = (
        Index("ix_jobs_due", "status", "run_after"),
        Index("ix_jobs_waiting", "organisation_id", "status"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    # None only for jobs queued before jobs knew their organisation (they are listed to no one).
    organisation_id: Mapped[int | None] = mapped_column(
        ForeignKey("organisations.id", ondelete="CASCADE"), index=True, nullable=True
    )
    task: Mapped[str] = mapped_column(String(50))
    args: Mapped[dict[str, Any]] = mapped_column(Document)
    status: Mapped[str] = mapped_column(String(16), default="queued")
    priority: Mapped[int] = mapped_column(Integer, server_default="0")
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    run_after: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)
    locked_until: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)
    last_error: Mapped[str | None] = mapped_column(Text, nullable=True)
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)
    finished_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)


class JobCount(Base):
    """How many jobs of the embedded backend ended in ``state`` (done or failed), counted as each
    ends: their rows are never deleted, so counting them at each scrape would grow with history."""

    __tablename__ = "job_counts"

    state: Mapped[str] = mapped_column(String(16), primary_key=True)
    count: Mapped[int] = mapped_column(BigInteger, default=0)


class Schedule(Base):
    """A periodic inspection of one structure: every ``interval_seconds`` or on a cron expression.

    ``next_run_at`` is the next due time; a sweeper that finds it past moves it on with a
    compare-and-set on its old value, so each due time is acted on once however many sweep.
    """

    __tablename__ = "schedules"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    structure_id: Mapped[int] = mapped_column(ForeignKey("structures.id", ondelete="CASCADE"), index=True)
    action: Mapped[str] = mapped_column(String(32))
    interval_seconds: Mapped[int | None] = mapped_column(Integer, nullable=True)
    cron: Mapped[str | None] = mapped_column(String(100), nullable=True)
    next_run_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, index=True)
    last_run_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)


class JobError(Base):
    """The last error of a distributed (Procrastinate) job, which Procrastinate does not keep;
    the embedded backend keeps it in ``jobs.last_error``. Rows of jobs Procrastinate has pruned
    are pruned with them."""

    __tablename__ = "job_errors"

    job_id: Mapped[int] = mapped_column(BigInteger, primary_key=True, autoincrement=False)
    error: Mapped[str] = mapped_column(Text)
    at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)


class InspectionFailure(Base):
    """A record its structure's models could not inspect (too short for their lags, values
    they cannot take), with the reason: schedules skip it until the model set changes."""

    __tablename__ = "inspection_failures"
    __table_args__ = (UniqueConstraint("record_id", "model_set"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    record_id: Mapped[int] = mapped_column(ForeignKey("records.id", ondelete="CASCADE"), index=True)
    model_set: Mapped[str] = mapped_column(String(200))
    reason: Mapped[str] = mapped_column(Text)
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)


# Alarms that are not resolved: at most one per structure, rule kind and fault mode. Two partial
# indexes, because a unique index treats NULLs as distinct and a persistence alarm has no mode.
UNRESOLVED = text("state != 'resolved'")
UNRESOLVED_WITHOUT_MODE = text("state != 'resolved' AND fault_mode IS NULL")


class AlarmRule(Base):
    """A structure's alarm rule of one ``kind`` (persistence, cusum or severity) with its
    ``parameters``; a structure with no rule stored is watched by the defaults
    (``service.domain.alarms``)."""

    __tablename__ = "alarm_rules"
    __table_args__ = (UniqueConstraint("structure_id", "kind"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    structure_id: Mapped[int] = mapped_column(ForeignKey("structures.id", ondelete="CASCADE"), index=True)
    kind: Mapped[str] = mapped_column(String(16))
    parameters: Mapped[dict[str, Any]] = mapped_column(Document)
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)


class AlarmState(Base):
    """Where a structure's alarm rules stand, kept in the transaction of each verdict
    (``service.domain.alarms``): per rule and fault mode, what the rule needs of the records it
    has counted (a CUSUM's two sums, persistence's last m outcomes, the current run of firings,
    the unresolved alarm), and the newest verdict counted. A verdict newer than that one updates
    it without reading the history; a structure without a row (after the migration, or after the
    retention dropped it with verdicts, or an alarm resolved by hand) has it rebuilt from its
    history the next time its rules run."""

    __tablename__ = "alarm_states"

    structure_id: Mapped[int] = mapped_column(
        ForeignKey("structures.id", ondelete="CASCADE"), primary_key=True, autoincrement=False
    )
    # JSON as text: written whole and read whole, never queried inside.
    state: Mapped[str] = mapped_column(Text)


class Alarm(Base):
    """A rule that fired on a structure's verdicts, from open through acknowledged to resolved.

    ``triggered_at`` is the acquisition time of the record on which the rule fired,
    ``drift_started_at`` (CUSUM only) that of the first record of the drift it detected;
    ``evaluated_through`` the newest record's, updated at each evaluation: after the alarm is
    resolved, the rule looks only at records acquired later. ``rule`` keeps the rule's
    parameters (and design) as they were when it fired. ``fault_mode`` is None for a
    persistence alarm, which counts faults of any mode.
    """

    __tablename__ = "alarms"
    __table_args__ = (
        Index(
            "uq_alarms_unresolved",
            "structure_id",
            "rule_kind",
            "fault_mode",
            unique=True,
            sqlite_where=UNRESOLVED,
            postgresql_where=UNRESOLVED,
        ),
        Index(
            "uq_alarms_unresolved_without_mode",
            "structure_id",
            "rule_kind",
            unique=True,
            sqlite_where=UNRESOLVED_WITHOUT_MODE,
            postgresql_where=UNRESOLVED_WITHOUT_MODE,
        ),
        Index("ix_alarms_listing", "structure_id", "opened_at", "id"),
        # An organisation's alarms newest first, without reading another's (migration 0019).
        Index("ix_alarms_organisation", "organisation_id", "id"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    structure_id: Mapped[int] = mapped_column(ForeignKey("structures.id", ondelete="CASCADE"))
    organisation_id: Mapped[int] = mapped_column(ForeignKey("organisations.id", ondelete="CASCADE"))
    rule_kind: Mapped[str] = mapped_column(String(16))
    rule: Mapped[dict[str, Any]] = mapped_column(Document)
    fault_mode: Mapped[str | None] = mapped_column(String(100), nullable=True)
    state: Mapped[str] = mapped_column(String(16))
    opened_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)
    record_id: Mapped[int | None] = mapped_column(
        ForeignKey("records.id", ondelete="SET NULL"), nullable=True
    )
    triggered_at: Mapped[dt.datetime] = mapped_column(UTCDateTime)
    drift_started_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)
    evaluated_through: Mapped[dt.datetime] = mapped_column(UTCDateTime)
    acknowledged_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)
    acknowledged_key_id: Mapped[int | None] = mapped_column(
        "acknowledged_by", ForeignKey("api_keys.id", ondelete="SET NULL"), nullable=True
    )
    acknowledgement_note: Mapped[str | None] = mapped_column(Text, nullable=True)
    resolved_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)
    resolved_key_id: Mapped[int | None] = mapped_column(
        "resolved_by", ForeignKey("api_keys.id", ondelete="SET NULL"), nullable=True
    )
    resolution: Mapped[str | None] = mapped_column(String(16), nullable=True)
    resolution_note: Mapped[str | None] = mapped_column(Text, nullable=True)
    # When it was last announced again while open (``service.domain.renotify``); None: not yet.
    renotified_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)

    acknowledged_key: Mapped[ApiKey | None] = relationship(foreign_keys=[acknowledged_key_id])
    resolved_key: Mapped[ApiKey | None] = relationship(foreign_keys=[resolved_key_id])
    transitions: Mapped[list[AlarmTransition]] = relationship(
        order_by="AlarmTransition.id", cascade="all, delete-orphan"
    )

    @property
    def acknowledged_by(self) -> str | None:
        """The prefix of the API key that acknowledged the alarm; None if none did."""
        return self.acknowledged_key.prefix if self.acknowledged_key is not None else None

    @property
    def resolved_by(self) -> str | None:
        """The prefix of the API key that resolved the alarm; None when the service did (or none)."""
        return self.resolved_key.prefix if self.resolved_key is not None else None


class AlarmTransition(Base):
    """One change of an alarm's state (``from_state`` None when it opened). ``key_id`` is the API
    key that made it; None when the service's rule evaluation did (opened, resolved as cleared)."""

    __tablename__ = "alarm_transitions"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    alarm_id: Mapped[int] = mapped_column(ForeignKey("alarms.id", ondelete="CASCADE"), index=True)
    from_state: Mapped[str | None] = mapped_column(String(16), nullable=True)
    to_state: Mapped[str] = mapped_column(String(16))
    at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)
    key_id: Mapped[int | None] = mapped_column(ForeignKey("api_keys.id", ondelete="SET NULL"), nullable=True)
    note: Mapped[str | None] = mapped_column(Text, nullable=True)

    key: Mapped[ApiKey | None] = relationship()

    @property
    def by(self) -> str | None:
        """The prefix of the API key that made the change; None when the service's rules did."""
        return self.key.prefix if self.key is not None else None


class Webhook(Base):
    """An organisation's HTTPS (or HTTP) endpoint told of the ``events`` it wants.

    ``secret`` signs every delivery (``service.domain.notifications``), so it is kept to be read
    back, not hashed: sealed under the server's keys (``service.sealing``), a Fernet token of at
    most 356 characters for the longest secret the API takes (200); the API never shows it
    again after creation."""

    __tablename__ = "webhooks"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    organisation_id: Mapped[int] = mapped_column(
        ForeignKey("organisations.id", ondelete="CASCADE"), index=True
    )
    url: Mapped[str] = mapped_column(String(2000))
    secret: Mapped[str] = mapped_column(String(400))
    events: Mapped[list[str]] = mapped_column(Document)
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)


class EmailSubscription(Base):
    """E-mail ``addresses`` of an organisation told of the ``events`` they want, through the
    server's SMTP relay (``NARXWATCH_SMTP_*``)."""

    __tablename__ = "email_subscriptions"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    organisation_id: Mapped[int] = mapped_column(
        ForeignKey("organisations.id", ondelete="CASCADE"), index=True
    )
    addresses: Mapped[list[str]] = mapped_column(Document)
    events: Mapped[list[str]] = mapped_column(Document)
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)


# Deliveries no longer owed: the only ones the retention deletes, by organisation and age.
SETTLED = text("status <> 'pending'")


class Delivery(Base):
    """One event for one webhook or e-mail subscription, and the log of its attempts.

    The rows are an outbox: written in the transaction of the change they announce, swept into
    jobs once committed. ``next_attempt_at`` is when it is due while ``pending``; a sweep that
    claims it moves it on (compare-and-set), and the job it defers acts only while it still
    holds that value, so each claim is acted on by one job. ``key`` is sent as the
    ``Idempotency-Key``, the same on every attempt. Settled ones (delivered or failed) are kept
    as long as the organisation keeps its verdicts (``service.domain.retention``).
    """

    __tablename__ = "deliveries"
    __table_args__ = (
        Index("ix_deliveries_due", "status", "next_attempt_at"),
        Index(
            "ix_deliveries_settled",
            "organisation_id",
            "created_at",
            sqlite_where=SETTLED,
            postgresql_where=SETTLED,
        ),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    organisation_id: Mapped[int] = mapped_column(ForeignKey("organisations.id", ondelete="CASCADE"))
    webhook_id: Mapped[int | None] = mapped_column(
        ForeignKey("webhooks.id", ondelete="CASCADE"), index=True, nullable=True
    )
    email_subscription_id: Mapped[int | None] = mapped_column(
        ForeignKey("email_subscriptions.id", ondelete="CASCADE"), index=True, nullable=True
    )
    key: Mapped[str] = mapped_column(String(36), unique=True)
    event: Mapped[str] = mapped_column(String(50))
    payload: Mapped[dict[str, Any]] = mapped_column(Document)
    status: Mapped[str] = mapped_column(String(16), default="pending")
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    next_attempt_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)
    last_status_code: Mapped[int | None] = mapped_column(Integer, nullable=True)
    last_error: Mapped[str | None] = mapped_column(Text, nullable=True)
    delivered_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)
