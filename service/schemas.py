"""Request and response bodies of the REST API (pydantic, strict on input)."""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Any, Literal

from croniter import CroniterError, croniter
from pydantic import (
    AfterValidator,
    AliasChoices,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    FiniteFloat,
    SerializerFunctionWrapHandler,
    StrictInt,
    field_validator,
    model_serializer,
    model_validator,
)

from models.alarms import DESIGN_SHIFT
from models.basis import FAMILIES
from models.inspection import ModeResult, Status
from models.pooled import MAX_DEGREE, MAX_VARIABLES
from models.vector import VectorModeFigures
from recordfiles.channels import MAX_CHANNELS
from recordfiles.channels import NAME_LENGTH as CHANNEL_NAME_LENGTH
from recordfiles.conditions import NAME_LENGTH, NAME_RULE, Condition, as_conditions
from recordfiles.names import normalised_name
from recordfiles.quantities import UNIT_HELP, Quantity, checked_unit
from service.jobs.types import JobState
from service.tables import MAX_ID


def _normalised(value: object) -> object:
    # Before the length and pattern checks, which then see the name as it will be stored; what is
    # not a string is left to the strict string check.
    return normalised_name(value) if isinstance(value, str) else value


# Every name a user gives goes through ``recordfiles.names.normalised_name`` (NFC, trimmed, nothing
# invisible or reordering), then its field's own rule.
Normalised = BeforeValidator(_normalised)
STRUCTURE_NAME_LENGTH = 200
# The structure-name filter of listings: no control characters (PostgreSQL's text refuses NUL).
NAME_PATTERN = r"^[^\x00-\x1f]*$"
Name = Annotated[str, Normalised, Field(min_length=1, max_length=STRUCTURE_NAME_LENGTH)]
# Fault-mode names: the same rule wherever one is given (bodies, history filters, dashboard).
MODE_NAME_PATTERN = r"^[A-Za-z0-9_.\-]+$"
MODE_NAME_LENGTH = 100
ModeName = Annotated[
    str, Normalised, Field(min_length=1, max_length=MODE_NAME_LENGTH, pattern=MODE_NAME_PATTERN)
]
Id = Annotated[StrictInt, Field(ge=1, le=MAX_ID)]
Magnitude = Annotated[FiniteFloat, Field(ge=-1e6, le=1e6)]
SamplingRate = Annotated[FiniteFloat, Field(gt=0, le=1e9)]
TermName = Annotated[str, Field(min_length=1, max_length=200)]


def _aware(value: dt.datetime) -> dt.datetime:
    if value.tzinfo is None:
        raise ValueError("give a timezone, e.g. 2026-11-21T10:00:00Z")
    try:
        return value.astimezone(dt.UTC)
    except OverflowError:
        raise ValueError("the time lies outside the years 1 to 9999 once converted to UTC") from None


def _iso(value: object) -> object:
    # Strict models take no strings for datetimes from Python objects (request bodies that
    # FastAPI has decoded): an ISO 8601 string is read here, and nothing looser (no numbers).
    if isinstance(value, str):
        try:
            return dt.datetime.fromisoformat(value)
        except ValueError:
            raise ValueError("give an ISO 8601 time with a zone, e.g. 2026-11-21T10:00:00Z") from None
    return value


AwareDatetime = Annotated[dt.datetime, BeforeValidator(_iso), AfterValidator(_aware)]


class Strict(BaseModel):
    model_config = ConfigDict(strict=True, extra="forbid")


def _unit(value: object) -> object:
    return checked_unit(value) if isinstance(value, str) else value


class Signal(Strict):
    """What a structure's excitation x or response y measures. Charts and reports label the
    signal, and the residual e of the response, with them; nothing is assumed where they are
    not given."""

    quantity: Quantity = Field(description="What the signal measures; 'other' for none of these")
    unit: Annotated[str | None, BeforeValidator(_unit)] = Field(
        default=None, description=f"Its unit as the rig records it, {UNIT_HELP}; null when not stated"
    )


Description = Annotated[str, Field(max_length=2000, pattern=r"^[^\x00]*$")]
EXCITATION_HELP = "What x measures, e.g. {quantity: force, unit: N}; null: not declared"
RESPONSE_HELP = (
    "What y (every response channel) measures, e.g. {quantity: acceleration, unit: m/s²}; null: not declared"
)


class StructureCreate(Strict):
    name: Name
    fs: SamplingRate
    description: Description = ""
    excitation: Signal | None = Field(default=None, description=EXCITATION_HELP)
    response: Signal | None = Field(default=None, description=RESPONSE_HELP)


class StructureUpdate(Strict):
    """The fields sent change, the others stay. The sampling rate is not among them: every record
    of the structure was stored at it."""

    name: Name | None = None
    description: Description | None = None
    excitation: Signal | None = Field(default=None, description=EXCITATION_HELP)
    response: Signal | None = Field(default=None, description=RESPONSE_HELP)

    @model_validator(mode="before")
    @classmethod
    def _kept(cls, data: Any) -> Any:
        # Said here, before the generic refusals of an extra field or a null string, because
        # the reason is what a person needs.
        if isinstance(data, dict):
            if "fs" in data:
                raise ValueError(
                    "a structure's fs cannot change: its records were stored at it and its models "
                    "identified at it; create another structure for another rate"
                )
            for name in ("name", "description"):
                if name in data and data[name] is None:
                    raise ValueError(f"{name} cannot be null: leave it out to keep it")
        return data


class StructureOut(BaseModel):
    id: int
    name: str
    fs: float
    description: str
    created_at: dt.datetime
    excitation: Signal | None = Field(description="What x measures; null when not declared")
    response: Signal | None = Field(
        description="What y (every response channel) measures; null when not declared"
    )


class StructureListed(StructureOut):
    """A structure as ``GET /structures`` lists it: with where it stands, kept on write."""

    status: Status | None = Field(description="Its latest verdict's status; null before its first verdict")
    since: dt.datetime | None = Field(
        description="When that status began: the acquisition time of the first verdict after the last "
        "one of another status"
    )


Terms = Annotated[list[TermName], Field(min_length=1, max_length=500)]
CHOSEN_TERMS_HELP = (
    "The model's terms, e.g. y[t-1], x[t], y[t-1]^3. Without them they are chosen for the structure from "
    "these healthy records: the linear orders and input delay (0 lets x[t] in) that simulate held-out parts "
    "of them best, then nonlinear terms only where they lower that free run; the version's training.choice "
    "says what was chosen and how well it simulates the held-out parts"
)
BASELINE_TERMS_HELP = (
    "The model's terms, e.g. y[t-1], x[t], y[t-1]^3. Without them, the structure's active baseline's "
    "(train a baseline first); the version's training.terms_from names that baseline"
)


class BaselineTrain(Strict):
    """Train the healthy structure's NARX from stored records."""

    record_ids: Annotated[list[Id], Field(min_length=1, max_length=1000)]
    terms: Terms | None = Field(None, description=CHOSEN_TERMS_HELP)


class Experiment(Strict):
    record_id: Id
    k: Magnitude


NOISE_HELP = (
    "Where the structure's noise is: process (a force on the structure; the paper's chain, one-step "
    "residual and Ljung–Box) or sensor (on the measured force and response; the free-run chain, "
    "models.free_run_inspection: degree 1, the range the experiments' magnitudes, at three or more, "
    "and every sensor-noise mode of the structure refitted with this one around one healthy model)"
)


class FaultModeTrain(Strict):
    """Train a fault-mode FNARX from stored records at known magnitudes."""

    name: ModeName
    k_min: Magnitude
    k_max: Magnitude
    degree: Annotated[StrictInt, Field(ge=1, le=8)] = 1
    basis: Literal[FAMILIES] = "chebyshev2"  # type: ignore[valid-type]
    experiments: Annotated[list[Experiment], Field(min_length=2, max_length=1000)]
    terms: Terms | None = Field(None, description=BASELINE_TERMS_HELP)
    noise: Literal["process", "sensor"] = Field("process", description=NOISE_HELP)


ConditionName = Annotated[
    str, Normalised, Field(min_length=1, max_length=NAME_LENGTH, pattern=f"^{NAME_RULE.pattern}$")
]
PooledVariables = Annotated[list[ConditionName], Field(min_length=1, max_length=MAX_VARIABLES)]
PooledDegree = Annotated[StrictInt, Field(ge=0, le=MAX_DEGREE)]
POOLED_VARIABLES_HELP = (
    "The operating variables the coefficients are functions of; by default every condition the first "
    "record carries"
)
POOLED_DEGREE_HELP = "The highest degree per argument the information criterion may choose"


class PooledBaselineTrain(Strict):
    """Train a pooled baseline (``models.pooled``) from healthy stored records acquired over a range of
    operating conditions."""

    record_ids: Annotated[list[Id], Field(min_length=2, max_length=1000)]
    terms: Terms | None = Field(None, description=BASELINE_TERMS_HELP)
    variables: PooledVariables | None = Field(None, description=POOLED_VARIABLES_HELP)
    max_degree: PooledDegree = Field(2, description=POOLED_DEGREE_HELP)


class PooledFaultModeTrain(Strict):
    """Train a pooled fault mode, its coefficients functions of the operating variables and k, from
    stored records at known magnitudes spread over the conditions."""

    name: ModeName
    experiments: Annotated[list[Experiment], Field(min_length=2, max_length=1000)]
    terms: Terms | None = Field(None, description=BASELINE_TERMS_HELP)
    variables: PooledVariables | None = Field(None, description=POOLED_VARIABLES_HELP)
    max_degree: PooledDegree = Field(2, description=POOLED_DEGREE_HELP)


MAX_VECTOR_LAGS = 10


class VectorFaultModeTrain(Strict):
    """Train a vector fault mode (``models.vector``) from stored records of several channels at known
    magnitudes: one equation per channel over every channel's lags, each coefficient a function of k."""

    name: ModeName
    experiments: Annotated[list[Experiment], Field(min_length=2, max_length=1000)]
    lags: Annotated[StrictInt, Field(ge=1, le=MAX_VECTOR_LAGS)] = Field(
        2,
        description="p: the lags of every channel and of x in each equation (2 for displacements of a chain)",
    )
    degree: Annotated[StrictInt, Field(ge=1, le=4)] = Field(
        1, description="The degree of the functions of k (basis functions: degree + 1)"
    )
    basis: Literal[FAMILIES] = "chebyshev2"  # type: ignore[valid-type]


Train = BaselineTrain | FaultModeTrain | PooledBaselineTrain | PooledFaultModeTrain | VectorFaultModeTrain


class ModelOut(BaseModel):
    id: int
    kind: Literal["baseline", "fault_mode"]
    name: str
    version: int
    active: bool
    created_at: dt.datetime
    terms: list[str]
    training: dict[str, Any] = Field(
        description="How the version was trained: its records or experiments and its terms; for a "
        "baseline whose terms were chosen, choice: the orders {ny, nx}, the input delay, the nonlinear "
        "terms_added and held_out {free_run_rms, free_run_nrmse, samples}, the chosen structure's free run "
        "over held-out parts of its records; for a model that took the active baseline's terms, terms_from "
        "{model_id, name, version}"
    )
    statistics: dict[str, Any]


class JobAccepted(BaseModel):
    """Work queued as a job rather than run within its request; follow it at ``location``."""

    job_id: int
    location: str
    detail: str


CONDITIONS_HELP = (
    "The operating conditions the record was acquired under, sorted by name: each a name (a lowercase "
    "identifier), a finite value and its unit or null"
)


def _stored_conditions(rows: list[Any]) -> list[Any]:
    """A stored record's condition rows as its conditions; conditions given as such pass."""
    return rows if all(isinstance(row, Condition | dict) for row in rows) else as_conditions(rows)


# The conditions of a stored record, in an answer validated from its attributes.
StoredConditions = Annotated[list[Condition], BeforeValidator(_stored_conditions)]


class ChannelUpload(Strict):
    """One response channel of a record of several: its name and its samples."""

    name: Annotated[str, Normalised, Field(min_length=1, max_length=CHANNEL_NAME_LENGTH)]
    y: Annotated[list[FiniteFloat], Field(min_length=1)]


class RecordUpload(Strict):
    """A record as JSON: excitation x and response y (in the units its structure declares) or
    several named response ``channels`` (``recordfiles.channels``), sampling rate fs [Hz], and
    the operating conditions it was acquired under (checked by
    ``recordfiles.conditions.checked_conditions``)."""

    x: Annotated[list[FiniteFloat], Field(min_length=1)]
    y: Annotated[list[FiniteFloat], Field(min_length=1)] | None = None
    channels: Annotated[list[ChannelUpload], Field(min_length=2, max_length=MAX_CHANNELS)] | None = Field(
        None,
        description="Instead of y, for a record of several sensors: 2 to 8 channels, each a name (a letter, "
        "then letters, digits or underscores) and as many samples as x, e.g. {name: a1, y: [...]}",
    )
    fs: SamplingRate
    acquired_at: AwareDatetime | None = None
    conditions: list[Condition] = Field(
        default=[], description="At most 16, each name once, e.g. {name: temperature, value: 12.5, unit: °C}"
    )

    @model_validator(mode="after")
    def _one_response_or_channels(self) -> RecordUpload:
        if (self.y is None) == (self.channels is None):
            raise ValueError("give y (one response) or channels (several named responses), not both")
        return self


class ModelRef(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    id: int
    name: str
    version: int


class NoveltyFigures(BaseModel):
    """A record judged against its structure's healthy baseline alone (``models.novelty``): its
    free-run error regressed on the run's sensitivities, T ~ F(dof, residual_dof) for a healthy
    record, an anomaly when T exceeds the threshold F_{1−α}. Figures a diverged free run makes
    infinite are null."""

    statistic: float | None = Field(description="T, the record's statistic")
    threshold: float = Field(description="F_{1−α}(dof, residual_dof): an anomaly above it")
    p_value: float = Field(description="P(F(dof, residual_dof) > T): the chance of so large a T when healthy")
    severity: float | None = Field(
        description="The record's free-run error variance over a healthy record's: 1 when healthy, whatever "
        "the record's length; the figure to trend"
    )
    free_run: Literal["settled", "marginal", "diverged"] = Field(
        description="settled; marginal (the baseline's free run does not ring down: the designed rate does "
        "not hold); diverged (the free run left every bound at sample diverged_at: an anomaly)"
    )
    sigma2: float | None = Field(description="The record's free-run error variance [response units²]")
    expected_sigma2: float = Field(description="A healthy record's, from the baseline's training records")
    dof: float
    residual_dof: float
    used_samples: int = Field(description="The samples judged, after the free run's initial outputs")
    diverged_at: int | None


class VerdictOut(BaseModel):
    # Validated from a stored verdict's attributes (service.tables.Verdict).
    model_config = ConfigDict(from_attributes=True)

    id: int
    record_id: int
    structure_id: int
    acquired_at: dt.datetime
    created_at: dt.datetime
    status: Status = Field(
        description="healthy; faulty (localised to fault_mode and sized); unknown_fault (a fault no fault "
        "mode describes); anomaly (a record unlike the healthy baseline's, for a structure judged by its "
        "baseline alone: novelty has the figures)"
    )
    fault_detected: bool
    fault_mode: str | None
    reference_mode: str | None
    k_hat: float | None
    sigma_k: float | None
    interval: tuple[float, float] | None
    alpha: float = Field(description="The designed false-alarm rate (NARXWATCH_ALPHA)")
    lags: int | None = Field(
        description="The Ljung–Box tests' lags; null for a verdict of a healthy baseline alone (none made)"
    )
    n_samples: int
    z_critical: float | None = Field(
        description="The magnitude test's critical |k̂|/σ̂_k; null for a verdict of a pooled baseline alone, "
        "which tests the residual's variance and whiteness at the record's conditions (as detected_by "
        "names them)"
    )
    q_critical_detection: float | None = Field(
        description="The critical Ljung–Box Q beyond which even the best mode's residual is a fault no model "
        "describes; null for a vector verdict (a record of several channels), which no whiteness test "
        "detects: it is faulty when a mode's magnitude test detects, localised to the maximum-likelihood mode"
    )
    detected_by: list[str]
    modes: list[VectorModeFigures | ModeResult] = Field(
        description="Every fault mode's figures. For a vector verdict each mode also has channel_rms (each "
        "channel's residual RMS, by name), residual_variance is the generalised variance det Σ̂ of its "
        "vector residual, q, q_critical, p_value and accepted are Hosking's multivariate portmanteau test "
        "of it, and "
        "sigma_k_record equals sigma_k (Gauss–Newton on the record's own residual covariance)"
    )
    novelty: NoveltyFigures | None = Field(
        None,
        description="The figures of a verdict of a healthy baseline alone (status healthy or anomaly; its "
        "version in model_versions); null for every other verdict",
    )
    model_versions: list[ModelRef]
    conditions: StoredConditions = Field(description=CONDITIONS_HELP)

    @field_validator("modes", mode="before")
    @classmethod
    def _mode_figures(cls, modes: list[Any]) -> list[Any]:
        """Stored modes are plain documents: a vector verdict's are told by their channel_rms."""
        return [
            (VectorModeFigures(**mode) if "channel_rms" in mode else ModeResult(**mode))
            if isinstance(mode, dict)
            else mode
            for mode in modes
        ]


class RecordOut(BaseModel):
    id: int
    structure_id: int
    fs: float
    n_samples: int
    acquired_at: dt.datetime
    created_at: dt.datetime
    sha256: str
    conditions: StoredConditions = Field(description=CONDITIONS_HELP)
    channels: list[str] | None = Field(
        None,
        description="The names of a record's response channels, in the order uploaded; absent for a "
        "record of one response y",
    )
    created: bool = Field(description="False when the same data had been uploaded before")
    signals_pruned_at: dt.datetime | None = Field(
        None, description="When the organisation's retention dropped the record's signals; null while kept"
    )
    verdict: VerdictOut | None = None

    @model_serializer(mode="wrap")
    def _one_response_as_before(self, handler: SerializerFunctionWrapHandler):  # type: ignore[no-untyped-def]
        # A record of one response answers exactly as before records had channels: without the field.
        # (Unannotated: pydantic would take a return annotation as the answer's schema, dropping its fields.)
        answer = handler(self)
        if self.channels is None:
            answer.pop("channels", None)
        return answer


class VerdictPage(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    items: list[VerdictOut]
    next_cursor: str | None = Field(description="Pass as `cursor` for the next (older) page; null at the end")


class TrendPoint(BaseModel):
    # One verdict on a k̂ chart, validated from a stored verdict, whose id it calls verdict_id.
    model_config = ConfigDict(from_attributes=True)

    verdict_id: int = Field(validation_alias=AliasChoices("verdict_id", "id"))
    acquired_at: dt.datetime
    status: str
    fault_mode: str | None
    k_hat: float | None
    sigma_k: float | None
    conditions: StoredConditions = Field(description=CONDITIONS_HELP)


class Summary(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    structure_id: int
    total: int
    counts: dict[str, int]
    latest: VerdictOut | None
    trend: list[TrendPoint] = Field(description="The newest verdicts, oldest first, for a k̂ chart")
    k_hat_slope_per_day: float | None = Field(
        description="Least-squares slope of k̂ over time for the latest verdict's mode, %/day"
    )


SampleIndex = Annotated[StrictInt, Field(ge=0, le=2**31 - 1)]
SampleRange = Annotated[list[SampleIndex], Field(min_length=2, max_length=2, description="[first, end)")]


MAX_REFINEMENT_RECORDS = 100  # of each kind: the cells bound limits their total length as well


class RefinementCreate(Strict):
    """Refine a baseline version on stored records. On one record (``record_id``): its
    estimation samples [a, b) fit, its test samples [c, d) judge (default: the first two thirds
    and the last third); estimation parts [[a, b], [c, d], …] are fitted as records of their own,
    no lag reaching from one to the next, so that what lies between them (a glitch) is left out.
    On several (``record_ids``): all of them fit at once, and each of ``test_record_ids`` is judged
    whole; the first ``transient`` samples of each record hold its transient: every record is
    fitted through them and run from its start, and a test record is scored after them.
    Without ``base_model_id`` (a structure no baseline describes yet) the loop starts from the
    linear model whose orders simulate best, and reports them."""

    record_id: Id | None = None
    record_ids: Annotated[list[Id], Field(min_length=1, max_length=MAX_REFINEMENT_RECORDS)] | None = None
    test_record_ids: Annotated[list[Id], Field(min_length=1, max_length=MAX_REFINEMENT_RECORDS)] | None = None
    base_model_id: Id | None = None
    estimation: (
        SampleRange
        | Annotated[list[SampleRange], Field(min_length=1, max_length=MAX_REFINEMENT_RECORDS)]
        | None
    ) = None
    test: SampleRange | None = None
    transient: Annotated[StrictInt, Field(ge=0, le=10_000_000)] = 0
    initial: Annotated[StrictInt, Field(ge=0, le=100_000)] = 0
    alpha: Annotated[FiniteFloat, Field(gt=0, lt=1)] = 0.01

    @model_validator(mode="after")
    def _one_protocol(self) -> RefinementCreate:
        if (self.record_id is None) == (self.record_ids is None):
            raise ValueError("give record_id (one record, with estimation and test parts) or record_ids")
        if self.record_ids is None:
            if self.test_record_ids is not None or self.transient:
                raise ValueError(
                    "test_record_ids and transient go with record_ids; on one record, give its "
                    "estimation and test parts"
                )
        elif self.test_record_ids is None:
            raise ValueError("with record_ids, give test_record_ids: the records the models are judged on")
        elif self.estimation is not None or self.test is not None:
            raise ValueError("estimation and test parts go with record_id; record_ids are fitted whole")
        return self

    @property
    def estimation_parts(self) -> list[tuple[int, int]] | None:
        """``estimation`` as a list of parts (one [a, b) is one part)."""
        given = self.estimation
        if given is None:
            return None
        if isinstance(given[0], int):
            return [(given[0], given[1])]
        return [(a, b) for a, b in given]

    @property
    def estimation_record_ids(self) -> list[int]:
        if self.record_ids is not None:
            return self.record_ids
        assert self.record_id is not None  # one of the two, as the validator checks
        return [self.record_id]


class RefinementOut(BaseModel):
    """``record_id`` is the first of ``record_ids``, the records fitted; ``test_record_ids`` are
    those judged whole (none when a test part of the one record judged). ``base_model`` is None
    when the loop started from the linear orders it chose (``report.orders_chosen``).
    ``report.amplitude_range`` says up to what scale of the fitted records' inputs each model's
    free run stays bounded (``bounded_to``, null: no limit) and where it diverges (``diverges_at``)."""

    id: int
    structure_id: int
    record_id: int
    record_ids: list[int]
    test_record_ids: list[int]
    base_model: ModelRef | None  # None: the loop chose a linear model's orders
    refined_model: ModelRef | None
    created_at: dt.datetime
    report: dict[str, Any]


MIN_INTERVAL_SECONDS = 10  # the sweepers look every few seconds; shorter would not be kept
MAX_INTERVAL_SECONDS = 366 * 86400


def _cron(expression: str) -> str:
    """Five fields (minute hour day month weekday) that some day matches."""
    if len(expression.split()) != 5:
        raise ValueError("give five fields: minute hour day-of-month month day-of-week, e.g. '*/15 * * * *'")
    try:
        croniter(expression, dt.datetime.now(dt.UTC)).get_next(dt.datetime)
    except (CroniterError, ValueError, KeyError) as exc:
        raise ValueError(f"not a cron expression that ever runs: {exc}") from None
    return expression


Action = Literal["inspect_pending", "reinspect_latest"]


class ScheduleCreate(Strict):
    """Run ``action`` on a structure every ``interval_seconds`` or on a ``cron`` expression (UTC).

    ``inspect_pending`` inspects every record of the structure that has no verdict yet;
    ``reinspect_latest`` inspects its newest record with the active models.
    """

    action: Action
    interval_seconds: Annotated[StrictInt, Field(ge=MIN_INTERVAL_SECONDS, le=MAX_INTERVAL_SECONDS)] | None = (
        None
    )
    cron: Annotated[str, Field(max_length=100), AfterValidator(_cron)] | None = None
    first_run_at: Annotated[
        AwareDatetime | None, Field(description="First due time of an interval schedule (default: now)")
    ] = None

    @model_validator(mode="after")
    def _one_timing(self) -> ScheduleCreate:
        if (self.interval_seconds is None) == (self.cron is None):
            raise ValueError("give exactly one of interval_seconds and cron")
        if self.cron is not None and self.first_run_at is not None:
            raise ValueError("first_run_at applies to interval schedules; a cron schedule runs on its times")
        return self


class ScheduleOut(BaseModel):
    id: int
    structure_id: int
    action: Action
    interval_seconds: int | None
    cron: str | None
    next_run_at: dt.datetime
    last_run_at: dt.datetime | None
    created_at: dt.datetime


class KeyCreate(Strict):
    """A new key of the caller's organisation; without ``expires_at`` it lasts until revoked."""

    role: Literal["admin", "ingest", "viewer"]
    expires_at: AwareDatetime | None = None


MAX_RETENTION_DAYS = 36_500  # a hundred years; beyond it, keep forever (null)
RetentionDays = Annotated[StrictInt, Field(ge=1, le=MAX_RETENTION_DAYS)] | None


class Retention(Strict):
    """How long the organisation keeps its records' signals (x and y) and its verdicts, in days
    of acquisition time; null keeps them forever. Signals go first: a verdict outlives the
    signals it was computed from, never the other way round."""

    signal_days: RetentionDays = Field(description="Days a record's signals are kept; null: forever")
    verdict_days: RetentionDays = Field(
        description="Days verdicts (and their records) are kept; null: forever"
    )

    @model_validator(mode="after")
    def _signals_first(self) -> Retention:
        forever = MAX_RETENTION_DAYS + 1
        signals, verdicts = self.signal_days or forever, self.verdict_days or forever
        if signals > verdicts:
            raise ValueError(
                f"signal_days ({self.signal_days or 'forever'}) must not exceed verdict_days "
                f"({self.verdict_days}): a verdict's record keeps its signals no longer than the verdict"
            )
        return self


class RetentionOut(Retention):
    defaults: bool = Field(description="True while the organisation keeps the service's defaults")
    last_pruned_at: dt.datetime | None = Field(description="When the last pruning was queued; null: never")


class KeyOut(BaseModel):
    """An API key as listed: never the key nor its hash."""

    id: int
    prefix: str
    role: str
    created_at: dt.datetime
    expires_at: dt.datetime | None
    last_used_at: dt.datetime | None
    revoked_at: dt.datetime | None


class KeyCreated(KeyOut):
    key: str = Field(description="The key itself: shown this once, stored only as its hash.")


class JobOut(BaseModel):
    """A queued task of the caller's organisation: ``error`` is the last failure's reason (kept
    when a retry then succeeded); ``args`` names what it works on (a record, a schedule)."""

    id: int
    task: str
    args: dict[str, Any]
    state: JobState
    attempts: int
    error: str | None
    created_at: dt.datetime | None
    model: ModelRef | None = Field(
        default=None,
        description="What a training made: its model version, once the job is done; null for other tasks",
    )


class JobPage(BaseModel):
    items: list[JobOut]
    next_cursor: int | None = Field(description="Pass as `cursor` for the next (older) page; null at the end")


# --- notifications (service.domain.notifications) ------------------------------------------------

Event = Literal["alarm.opened", "alarm.acknowledged", "alarm.resolved", "alarm.renotified"]
Events = Annotated[list[Event], Field(min_length=1, max_length=4, description="The events wanted")]
# A signing secret as strong as the HMAC's key should be: 32 characters of a random token
# (Stripe's are 32 base64 characters after ``whsec_``).
MIN_SECRET_LENGTH = 32
EMAIL_PATTERN = r"^[^@\s,;<>()\"\[\]\\]+@[^@\s,;<>()\"\[\]\\]+\.[^@\s,;<>()\"\[\]\\]+$"
EmailAddress = Annotated[str, Field(max_length=254, pattern=EMAIL_PATTERN)]


def _url_characters(url: str) -> str:
    if any(ord(c) <= 0x20 or ord(c) == 0x7F for c in url):
        raise ValueError("a URL holds no spaces or control characters: percent-encode them")
    return url


class WebhookCreate(Strict):
    """An endpoint told of the ``events`` it wants, each POST signed with ``secret``."""

    url: Annotated[str, Field(min_length=1, max_length=2000), AfterValidator(_url_characters)]
    secret: Annotated[str, Field(min_length=MIN_SECRET_LENGTH, max_length=200, pattern=r"^[\x21-\x7e]+$")]
    events: Events


class WebhookOut(BaseModel):
    """A webhook as listed: never its secret."""

    id: int
    url: str
    events: list[Event]
    created_at: dt.datetime


class EmailSubscriptionCreate(Strict):
    addresses: Annotated[list[EmailAddress], Field(min_length=1, max_length=20)]
    events: Events


class EmailSubscriptionOut(BaseModel):
    id: int
    addresses: list[str]
    events: list[Event]
    created_at: dt.datetime


class DeliveryOut(BaseModel):
    """One event for one webhook or subscription: ``attempts`` made so far, the last answer's
    status code (HTTP, or SMTP reply) and error; ``next_attempt_at`` while it is pending."""

    id: int
    key: str = Field(description="Sent as Idempotency-Key, the same on every attempt")
    event: Event
    status: Literal["pending", "delivered", "failed"]
    attempts: int
    last_status_code: int | None
    last_error: str | None
    next_attempt_at: dt.datetime | None
    delivered_at: dt.datetime | None
    created_at: dt.datetime


class DeliveryPage(BaseModel):
    items: list[DeliveryOut]
    next_cursor: int | None = Field(description="Pass as `cursor` for the next (older) page; null at the end")


# --- alarms ---------------------------------------------------------------------------------

AlarmState = Literal["open", "acknowledged", "resolved"]
RuleKind = Literal["persistence", "cusum", "severity"]
Records = Annotated[StrictInt, Field(ge=1, le=10_000)]
NOTE_PATTERN = r"^[^\x00]*$"
Note = Annotated[str, Field(max_length=2000, pattern=NOTE_PATTERN)]


class PersistenceRule(Strict):
    """Fire when ``k`` of the last ``m`` verdicts are faulty, unknown or an anomaly (any fault mode)."""

    kind: Literal["persistence"]
    k: Annotated[StrictInt, Field(ge=1, le=1000)] = 3
    m: Annotated[StrictInt, Field(ge=1, le=1000)] = 5
    clear_after: Records = Field(5, description="Records in a row without firing before an alarm resolves")

    @model_validator(mode="after")
    def _k_of_m(self) -> PersistenceRule:
        if self.m < self.k:
            raise ValueError(f"m (the window, {self.m}) must be at least k (the faults in it, {self.k})")
        return self


class CusumRule(Strict):
    """A two-sided CUSUM per fault mode on z = k̂/σ̂k of each verdict, designed (never tuned) for
    ``false_alarms_per_year`` per structure at ``records_per_day`` and tuned to a step of ``shift`` σ."""

    kind: Literal["cusum"]
    false_alarms_per_year: Annotated[FiniteFloat, Field(gt=0, le=365)] = 1.0
    records_per_day: Annotated[FiniteFloat, Field(gt=0, le=100_000)] = 4.0
    shift: Annotated[FiniteFloat, Field(gt=0, le=20)] = DESIGN_SHIFT
    clear_after: Records = Field(25, description="Records in a row without a signal before an alarm resolves")


class SeverityRule(Strict):
    """Fire when a verdict's interval for k lies wholly beyond ±``threshold`` (% of k, as k̂)."""

    kind: Literal["severity"]
    threshold: Annotated[FiniteFloat, Field(le=1e6)] = 10.0
    clear_after: Records = Field(5, description="Records in a row without firing before an alarm resolves")

    @model_validator(mode="after")
    def _positive(self) -> SeverityRule:
        if self.threshold <= 0:
            raise ValueError(
                f"the severity threshold is a magnitude of k in %, applied to losses and gains alike: "
                f"give it positive (got {self.threshold})"
            )
        return self


AlarmRule = Annotated[PersistenceRule | CusumRule | SeverityRule, Field(discriminator="kind")]


class AlarmRules(Strict):
    """A structure's alarm rules, at most one of each kind; kinds left out do not fire."""

    rules: Annotated[list[AlarmRule], Field(min_length=1, max_length=3)]

    @model_validator(mode="after")
    def _one_per_kind(self) -> AlarmRules:
        kinds = [rule.kind for rule in self.rules]
        if len(set(kinds)) != len(kinds):
            raise ValueError(f"give each kind of rule at most once; got {', '.join(kinds)}")
        return self


class CusumDesignOut(BaseModel):
    """The CUSUM each fault mode is watched with: reference and threshold in σ units, run lengths
    in records (in control: the structure's target times its number of fault modes, averaged over
    the models' own error; at the shift: for a structure without that error)."""

    modes: int
    reference: float
    threshold: float
    arl_in_control: float
    arl_at_shift: float
    common_share: float = Field(description="The share of σ̂k² common to all records (the models' own error)")


class AlarmRulesOut(BaseModel):
    structure_id: int
    defaults: bool = Field(description="True when no rule was set: the service's defaults apply")
    rules: list[AlarmRule]
    cusum_design: CusumDesignOut | None
    cusum_problem: str | None = Field(description="Why the CUSUM rule does not run, when it does not")
    cusum_skipped: dict[str, str] = Field(
        default_factory=dict,
        description="The fault modes whose CUSUM the newest record did not step, each with why",
    )


class AlarmOut(BaseModel):
    """An alarm; ``*_by`` name the API key (its prefix) that acted, null for the service itself."""

    # Validated from a stored alarm's attributes (service.tables.Alarm).
    model_config = ConfigDict(from_attributes=True)

    id: int
    structure_id: int
    rule_kind: RuleKind
    rule: dict[str, Any]
    fault_mode: str | None
    state: AlarmState
    opened_at: dt.datetime
    record_id: int | None
    triggered_at: dt.datetime = Field(description="Acquisition time of the record the rule fired on")
    drift_started_at: dt.datetime | None = Field(description="CUSUM: acquisition time the drift began")
    acknowledged_at: dt.datetime | None
    acknowledged_by: str | None
    acknowledgement_note: str | None
    resolved_at: dt.datetime | None
    resolved_by: str | None
    resolution: Literal["cleared", "by_hand", "rule_removed", "rule_not_running"] | None
    resolution_note: str | None


class AlarmTransitionOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    from_state: AlarmState | None
    to_state: AlarmState
    at: dt.datetime
    by: str | None = Field(description="The acting API key's prefix; null when the service's rules acted")
    note: str | None


class AlarmDetail(AlarmOut):
    transitions: list[AlarmTransitionOut]


class AlarmPage(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    items: list[AlarmOut]
    next_cursor: int | None = Field(description="Pass as `cursor` for the next (older) page; null at the end")


class AlarmAction(Strict):
    note: Note = ""
