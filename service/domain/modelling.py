"""Model versions: training from stored records, immutable versions, one active per name."""

from __future__ import annotations

import json
import threading
from collections import Counter, OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
from sqlalchemy import bindparam, func, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, defer

from models.baseline_choice import CHOICE_COLUMNS, CHOICE_MIN_SAMPLES, MAX_CHOSEN_TERMS, choose_baseline_terms
from models.errors import InputError
from models.fnarx import FNARX, fit_fnarx
from models.free_run_inspection import FreeRunMode, fit_free_run_modes
from models.narx import NARX, fit_narx
from models.novelty import NoveltyReference, novelty_reference
from models.output_error import fit_output_error
from models.pooled import MAGNITUDE, MAX_VARIABLES, PooledExperiment, PooledModel, fit_pooled
from models.terms import Term, parse_terms
from models.vector import VectorFNARX, fit_vector_fnarx
from recordfiles.channels import matched
from service.config import Settings
from service.domain.errors import ConflictError, NotFoundError
from service.domain.records import condition_values, signals
from service.domain.structures import get_owned, get_structure, list_owned
from service.schemas import (
    BaselineTrain,
    FaultModeTrain,
    PooledBaselineTrain,
    PooledFaultModeTrain,
    Train,
    VectorFaultModeTrain,
)
from service.security import Principal
from service.tables import ModelVersion, Record, Structure

BASELINE = "baseline"
# Where a plain baseline's document keeps the reference of its healthy free-run error.
REFERENCE = "novelty_reference"
_CACHE_SIZE = 256


@dataclass(frozen=True)
class NoveltyBaseline:
    """A plain baseline fitted by output error with the reference of its healthy free-run error
    (``models.novelty``): it judges a structure's records alone, when no fault mode does."""

    model: NARX
    reference: NoveltyReference

    @classmethod
    def from_document(cls, document: dict[str, Any]) -> NoveltyBaseline:
        return cls(NARX.from_document(document), NoveltyReference.from_document(document[REFERENCE]))


Parsed = FNARX | PooledModel | VectorFNARX | FreeRunMode | NoveltyBaseline
# Versions are immutable, so a parsed model can be kept; keyed by id and creation time so that
# two databases in one process (tests) never share an entry. Requests and the embedded worker
# share it from several threads: an OrderedDict reordered by two at once can lose entries.
_parsed: OrderedDict[tuple[int, str], Parsed] = OrderedDict()
_parsed_lock = threading.Lock()


def train_baseline(
    session: Session, principal: Principal, structure_id: int, body: BaselineTrain, settings: Settings
) -> ModelVersion:
    """The healthy structure's NARX, by least squares; then, if it is linear in its output, by
    output error from the estimated start, with the reference of its healthy free-run error kept
    in its document, so that it can judge the structure's records alone (``models.novelty``).
    A baseline that cannot (nonlinear in its output, a free run that diverges) is stored as
    fitted, and ``statistics["novelty"]`` says why."""
    structure = get_structure(session, principal, structure_id)
    records, _ = _training_records(session, principal, structure, body, settings)
    pairs = [signals(r) for r in records]
    terms, chosen = baseline_terms(pairs, body.terms)
    model = fit_narx(pairs, terms)
    document = model.to_document()
    try:
        model = fit_output_error(model, pairs, start_from="estimated").model
        reference = novelty_reference(model, pairs)
    except InputError as refusal:
        novelty: dict[str, Any] = {"judges_records": False, "reason": str(refusal)}
    else:
        document = model.to_document() | {REFERENCE: reference.to_document()}
        novelty = {
            "judges_records": True,
            "fit": "output error from the estimated start",
            "sigma2": reference.sigma2,
            "directions": reference.rank,
            "start_up": reference.start_up,
            "marginal": reference.marginal,
        }
    training = {"record_ids": body.record_ids, "terms": model.term_names, **chosen}
    statistics = {"sigma2": model.sigma2, "n_obs": model.n_obs, "novelty": novelty}
    document = bounded_document(document, settings)
    return new_version(session, structure, "baseline", BASELINE, document, training, statistics)


def train_fault_mode(
    session: Session, principal: Principal, structure_id: int, body: FaultModeTrain, settings: Settings
) -> ModelVersion:
    structure = get_structure(session, principal, structure_id)
    records, _ = _training_records(session, principal, structure, body, settings)
    terms, taken = given_or_baseline_terms(session, structure, body.terms)
    if body.noise == "sensor":
        return _train_free_run_modes(session, principal, structure, body, records, terms, taken, settings)
    model = fit_fnarx(
        [(*signals(r), e.k) for r, e in zip(records, body.experiments, strict=True)],
        terms,
        name=body.name,
        family=body.basis,
        size=body.degree + 1,
        k_range=(body.k_min, body.k_max),
    )
    training = _fault_mode_training(body, model.term_names, taken)
    statistics = {"experiment_sigma2": model.experiment_sigma2.tolist(), "n_obs": model.n_obs}
    document = bounded_document(model.to_document(), settings)
    return new_version(session, structure, "fault_mode", body.name, document, training, statistics)


def _fault_mode_training(body: FaultModeTrain, terms: list[str], taken: dict[str, Any]) -> dict[str, Any]:
    """What a fault-mode version keeps of its training: the request as given, and its terms."""
    return {
        "experiments": [e.model_dump() for e in body.experiments],
        "k_min": body.k_min,
        "k_max": body.k_max,
        "basis": body.basis,
        "degree": body.degree,
        "terms": terms,
        "noise": body.noise,
        **taken,
    }


def _train_free_run_modes(
    session: Session,
    principal: Principal,
    structure: Structure,
    body: FaultModeTrain,
    records: list[Record],
    terms: tuple[Term, ...],
    taken: dict[str, Any],
    settings: Settings,
) -> ModelVersion:
    """A sensor-noise fault mode (``models.free_run_inspection``), fitted jointly with the
    structure's other active sensor-noise modes from their stored experiments: the modes share one
    healthy θ₀, and one fitted apart would carry its own experiments' error of it, which the
    localisation would take for a fault. Each of the others gets a new version too (its training
    as before, ``fitted_with`` naming the modes fitted together); the trained mode's is returned."""
    others = _other_free_run_modes(session, structure, body.name)
    names = [term.name for term in terms]
    for version in others:
        if version.training["terms"] != names:
            raise ConflictError(
                f"sensor-noise fault mode {version.name!r} has other terms "
                f"({', '.join(version.training['terms'])}); "
                "the sensor-noise modes of a structure are fitted together around one healthy model: "
                f"train {body.name!r} with its terms, or train {version.name!r} again with these"
            )
    experiments = {body.name: [(*signals(r), e.k) for r, e in zip(records, body.experiments, strict=True)]}
    for version in others:
        stored = owned_records(session, principal, structure, _experiment_ids(version))
        experiments[version.name] = [
            (*signals(r), e["k"]) for r, e in zip(stored, version.training["experiments"], strict=True)
        ]
    fitted_with = sorted(experiments)
    trainings = {body.name: _fault_mode_training(body, names, taken)}
    for version in others:  # a queued training's mark stays with the version it stored
        trainings[version.name] = {k: v for k, v in version.training.items() if k != "job"}
    stored_versions = {}
    for mode in fit_free_run_modes(experiments, terms):
        statistics = {
            "experiment_sigma2": mode.model.experiment_sigma2.tolist(),
            "n_obs": mode.model.n_obs,
            "sigma2": mode.sigma2,
            "dof": mode.dof,
            "scale": mode.scale,  # above 1: its own experiments, held out, said σ̂_k was too small
        }
        training = trainings[mode.name] | {"fitted_with": fitted_with}
        document = bounded_document(mode.to_document(), settings)
        stored_versions[mode.name] = new_version(
            session, structure, "fault_mode", mode.name, document, training, statistics
        )
    return stored_versions[body.name]


def _other_free_run_modes(session: Session, structure: Structure, name: str) -> list[ModelVersion]:
    """The structure's active sensor-noise fault-mode versions other than ``name``'s."""
    versions = session.scalars(ACTIVE_OF_KIND, {"structure_id": structure.id, "kind": "fault_mode"})
    return [v for v in versions if v.name != name and v.training.get("noise") == "sensor"]


def _experiment_ids(version: ModelVersion) -> list[int]:
    return [e["record_id"] for e in version.training["experiments"]]


def train_pooled(
    session: Session,
    principal: Principal,
    structure_id: int,
    body: PooledBaselineTrain | PooledFaultModeTrain,
    settings: Settings,
) -> ModelVersion:
    """A pooled baseline or fault mode (``models.pooled``) from stored records and the conditions
    they were stored with; its degrees per argument chosen by BIC and kept with the version."""
    structure = get_structure(session, principal, structure_id)
    records, _ = _training_records(session, principal, structure, body, settings)
    variables = _pooled_variables(records, body)
    if isinstance(body, PooledBaselineTrain):
        kind, name, magnitudes = "baseline", BASELINE, [None] * len(records)
        given = {"record_ids": body.record_ids}
    else:
        kind, name, magnitudes = "fault_mode", body.name, [e.k for e in body.experiments]
        given = {"experiments": [e.model_dump() for e in body.experiments]}
    experiments = [
        PooledExperiment(*signals(r), condition_values(r.conditions), k)
        for r, k in zip(records, magnitudes, strict=True)
    ]
    terms, taken = given_or_baseline_terms(session, structure, body.terms)
    model = fit_pooled(experiments, terms, name=name, variables=variables, max_degree=body.max_degree)
    training = given | {
        "variables": list(model.variables),
        "max_degree": body.max_degree,
        "terms": [term.name for term in model.terms],
        **taken,
    }
    statistics = {
        "degrees": model.degrees,
        "ranges": {argument: list(span) for argument, span in model.ranges.items()},
        "criterion": [
            {"degrees": list(row.degrees), "bic": row.bic, "sigma2": row.sigma2} for row in model.criterion
        ],
        "experiment_sigma2": model.experiment_sigma2.tolist(),
        "n_obs": model.n_obs,
    }
    document = bounded_document(model.to_document(), settings)
    return new_version(session, structure, kind, name, document, training, statistics)


def train_vector(
    session: Session, principal: Principal, structure_id: int, body: VectorFaultModeTrain, settings: Settings
) -> ModelVersion:
    """A vector fault mode (``models.vector``) from stored records of several channels, which must
    all have the same channels; they are put in the first record's order, kept with the version
    (``training["channels"]``) for the inspections to match records' channels by name."""
    structure = get_structure(session, principal, structure_id)
    records, _ = _training_records(session, principal, structure, body, settings)
    names = list(records[0].channels or ())
    experiments = []
    for record, experiment in zip(records, body.experiments, strict=True):
        x, y = signals(record)
        experiments.append((x, y[:, matched(record.channels or (), names, body.name)], experiment.k))
    model = fit_vector_fnarx(
        body.name, experiments, lags=body.lags, basis_size=body.degree + 1, family=body.basis
    )
    training = {
        "experiments": [e.model_dump() for e in body.experiments],
        "channels": names,
        "lags": body.lags,
        "basis": body.basis,
        "degree": body.degree,
    }
    statistics = {
        "sigma": model.sigma.tolist(),
        "k_range": [model.basis.k_min, model.basis.k_max],
        "n_obs": sum(record.n_samples - body.lags for record in records),
    }
    document = bounded_document(model.to_document(), settings)
    return new_version(session, structure, "fault_mode", body.name, document, training, statistics)


# A queued training's body by the kind its job names (``service.jobs.tasks.train_model``).
TRAININGS: dict[str, type[Train]] = {
    "baseline": BaselineTrain,
    "fault_mode": FaultModeTrain,
    "pooled_baseline": PooledBaselineTrain,
    "pooled_fault_mode": PooledFaultModeTrain,
    "vector_fault_mode": VectorFaultModeTrain,
}


def training_kind(body: Train) -> str:
    """The name a queued training's job gives its body (:data:`TRAININGS`)."""
    return next(kind for kind, schema in TRAININGS.items() if isinstance(body, schema))


def train(
    session: Session, principal: Principal, structure_id: int, body: Train, settings: Settings
) -> ModelVersion:
    """The training ``body`` asks for; its new version becomes the active one of its name."""
    if isinstance(body, BaselineTrain):
        return train_baseline(session, principal, structure_id, body, settings)
    if isinstance(body, FaultModeTrain):
        return train_fault_mode(session, principal, structure_id, body, settings)
    if isinstance(body, VectorFaultModeTrain):
        return train_vector(session, principal, structure_id, body, settings)
    return train_pooled(session, principal, structure_id, body, settings)


def version_of_job(session: Session, structure_id: int, token: str) -> ModelVersion | None:
    """The version a queued training (marked ``training["job"]``) has stored already, if any."""
    return versions_of_jobs(session, [(structure_id, token)]).get(token)


def versions_of_jobs(session: Session, jobs: Iterable[tuple[int, str]]) -> dict[str, ModelVersion]:
    """The versions queued trainings (structure id, job token) have stored, by token: one query
    for a page of jobs, whose structures' versions are read without their documents."""
    wanted = {token: structure_id for structure_id, token in jobs}
    if not wanted:
        return {}
    query = select(ModelVersion).where(ModelVersion.structure_id.in_(set(wanted.values())))
    versions = session.scalars(query.options(defer(ModelVersion.document)))
    return {v.training["job"]: v for v in versions if wanted.get(v.training.get("job")) == v.structure_id}


def training_cells(
    session: Session,
    principal: Principal,
    structure_id: int,
    body: Train,
    settings: Settings,
) -> int:
    """What a training costs in cells (samples × coefficients), from the records' lengths alone:
    it decides whether the training runs at once or as a job. Refuses one over the limits."""
    structure = get_structure(session, principal, structure_id)
    return _training_records(session, principal, structure, body, settings)[1]


def check_cost(cells: int, coefficients: int, settings: Settings, what: str) -> None:
    """Refuse a fit whose model or regressor matrix exceeds the configured bounds."""
    if coefficients > settings.max_model_coefficients:
        raise InputError(
            f"{what} would have {coefficients} coefficients (terms × basis functions); the limit is "
            f"{settings.max_model_coefficients} (NARXWATCH_MAX_MODEL_COEFFICIENTS)"
        )
    if cells > settings.max_training_cells:
        raise InputError(
            f"{what} would fit {cells} cells (samples × coefficients); the limit is "
            f"{settings.max_training_cells} (NARXWATCH_MAX_TRAINING_CELLS): use fewer or shorter records"
        )


def bounded_document(document: dict[str, Any], settings: Settings) -> dict[str, Any]:
    """The model's document, refused if larger than the service keeps: every page and inspection
    that uses the model reads it whole."""
    size = len(json.dumps(document))
    if size > settings.max_model_document_bytes:
        raise InputError(
            f"the model's document would be {size} bytes; the limit is {settings.max_model_document_bytes} "
            "(NARXWATCH_MAX_MODEL_DOCUMENT_BYTES): use fewer terms"
        )
    return document


def list_models(session: Session, principal: Principal, structure_id: int) -> list[ModelVersion]:
    # Listings show versions, not their documents: a parsed model is read when it is used.
    order = (ModelVersion.name, ModelVersion.version)
    return list_owned(session, principal, ModelVersion, structure_id, order, [defer(ModelVersion.document)])


def activate_model(session: Session, principal: Principal, structure_id: int, model_id: int) -> ModelVersion:
    get_structure(session, principal, structure_id)
    version = session.get(ModelVersion, model_id)
    if version is None or version.structure_id != structure_id:
        raise NotFoundError("model version", model_id)
    _lock_versions(session, structure_id)
    _deactivate(session, structure_id, version.name)
    version.active = True
    session.flush()
    return version


# The active versions of one kind, by name, without their documents (parsed_model reads one only
# when it has not parsed it before). Built once: every inspection looks its models up.
ACTIVE_OF_KIND = (
    select(ModelVersion)
    .where(
        ModelVersion.structure_id == bindparam("structure_id"),
        ModelVersion.kind == bindparam("kind"),
        ModelVersion.active.is_(True),
    )
    .order_by(ModelVersion.name)
    .options(defer(ModelVersion.document))
)


def active_fault_modes(
    session: Session, structure: Structure
) -> list[tuple[ModelVersion, FNARX | PooledModel | VectorFNARX | FreeRunMode]]:
    """The active fault-mode versions of a structure, by name, with their parsed models (vector ones,
    for records of several channels, and sensor-noise ones included)."""
    versions = session.scalars(ACTIVE_OF_KIND, {"structure_id": structure.id, "kind": "fault_mode"})
    return [(version, parsed_model(version)) for version in versions]


def active_baseline(
    session: Session, structure: Structure
) -> tuple[ModelVersion, PooledModel | NoveltyBaseline | None] | None:
    """The structure's active baseline, if it has one, with its parsed model if it can inspect
    records alone: a pooled baseline, or a plain one with the reference of its healthy free-run
    error (:func:`train_baseline`; its ``statistics["novelty"]`` says why one has none). Without
    fault modes it is what inspects the structure's records; with them it takes no part."""
    version = session.scalars(ACTIVE_OF_KIND, {"structure_id": structure.id, "kind": "baseline"}).first()
    if version is None:
        return None
    pooled = version.training.get("variables") is not None
    if not pooled and not version.statistics.get("novelty", {}).get("judges_records"):
        return version, None
    model = parsed_model(version)
    return version, model if isinstance(model, PooledModel | NoveltyBaseline) else None


def parsed_model(version: ModelVersion) -> Parsed:
    """The parsed model of a fault-mode (sensor-noise ones included), pooled or vector version, or
    of a plain baseline that judges records alone, kept once parsed: versions never change."""
    key = (version.id, version.created_at.isoformat())
    with _parsed_lock:
        model = _parsed.get(key)
    if model is None:  # parsed outside the lock: two threads may both parse it, harmlessly
        document = version.document
        kinds: dict[str, type[Parsed]] = {
            "pooled": PooledModel,
            "vector": VectorFNARX,
            "narx": NoveltyBaseline,
            "free_run_mode": FreeRunMode,
        }
        model = kinds.get(document.get("kind", ""), FNARX).from_document(document)
        with _parsed_lock:
            _parsed[key] = model
            if len(_parsed) > _CACHE_SIZE:
                _parsed.popitem(last=False)
    return model


def owned_records(
    session: Session, principal: Principal, structure: Structure, ids: list[int]
) -> list[Record]:
    """The records, each once, without their signals: those are read only once the fit is allowed."""
    repeated = [(i, n) for i, n in Counter(ids).items() if n > 1]
    if repeated:
        raise InputError(f"record {repeated[0][0]} is listed {repeated[0][1]} times; list each record once")
    unread = [defer(Record.x), defer(Record.y)]
    records = [get_owned(session, principal, Record, i, "record", options=unread) for i in ids]
    for record in records:
        if record.structure_id != structure.id:
            raise InputError(f"record {record.id} belongs to another structure, not {structure.name!r}")
    return records


def _lock_versions(session: Session, structure_id: int) -> None:
    """Take the structure's row lock before changing which of its versions is active.

    Trainings and activations of one structure then run one after another, each seeing what the
    previous one committed: none can deactivate the versions it saw while another's new active
    version is not yet visible to it, and none waits for row locks taken in another order (a
    deadlock). ``FOR NO KEY UPDATE``, not ``FOR UPDATE``: uploads and inspections, whose foreign
    keys take ``KEY SHARE`` locks on the same row, neither wait for it nor make it wait. SQLite
    renders a plain read: it has one writer, and the first write below takes its lock.
    The partial unique index on active versions refuses a second one in any case.
    """
    session.execute(select(Structure.id).where(Structure.id == structure_id).with_for_update(key_share=True))


def _training_records(
    session: Session,
    principal: Principal,
    structure: Structure,
    body: Train,
    settings: Settings,
) -> tuple[list[Record], int]:
    """The training's records (signals unread) and its cost in cells, refused over the limits;
    what can be checked without the signals is, so that a queued training fails for no reason
    its request could have given."""
    if isinstance(body, BaselineTrain | PooledBaselineTrain):
        ids = body.record_ids
    else:
        if body.name == BASELINE:
            raise InputError("'baseline' names the healthy model; give the fault mode another name")
        if isinstance(body, FaultModeTrain) and not body.k_min < body.k_max:
            raise InputError(f"k_min ({body.k_min}) must be below k_max ({body.k_max})")
        if isinstance(body, FaultModeTrain) and body.noise == "sensor":
            _check_free_run_training(body)
        ids = [e.record_id for e in body.experiments]
    records = owned_records(session, principal, structure, ids)
    if isinstance(body, VectorFaultModeTrain):
        return records, _vector_cells(records, body, settings)
    check_one_response(records, structure, "this training")
    if isinstance(body, BaselineTrain) and body.terms is None:
        return records, _choice_cells(records, settings)
    terms = len(given_or_baseline_terms(session, structure, body.terms)[0])
    if isinstance(body, BaselineTrain):
        size = 1
    elif isinstance(body, FaultModeTrain) and body.noise == "sensor":
        cells = _free_run_cells(session, principal, structure, body, records, terms)
        check_cost(cells, terms * (body.degree + 1), settings, "this training")
        return records, cells
    elif isinstance(body, FaultModeTrain):
        size = body.degree + 1
    else:
        # The largest candidate of the degree search: its basis functions are fewer than the records.
        arguments = len(_pooled_variables(records, body)) + isinstance(body, PooledFaultModeTrain)
        size = min((body.max_degree + 1) ** arguments, len(records) - 1)
    cells = sum(r.n_samples for r in records) * terms * size
    check_cost(cells, terms * size, settings, "this training")
    return records, cells


def _check_free_run_training(body: FaultModeTrain) -> None:
    """Refuse a sensor-noise training the free-run fit cannot give: its modes are linear in k
    (degree 1), their range is their experiments' magnitudes, at three or more (its jackknife
    refits a line without each one)."""
    if body.degree != 1 or body.basis != FaultModeTrain.model_fields["basis"].default:
        raise InputError(
            "a sensor-noise fault mode is linear in k: give degree 1 and the default basis "
            f"(got degree {body.degree}, basis {body.basis!r})"
        )
    magnitudes = sorted({e.k for e in body.experiments})
    if len(magnitudes) < 3:
        raise InputError(
            f"a sensor-noise fault mode needs experiments at three magnitudes or more, got "
            f"{', '.join(f'{k:g}' for k in magnitudes)}: its estimation error is measured by refitting "
            "without each one"
        )
    if (body.k_min, body.k_max) != (magnitudes[0], magnitudes[-1]):
        raise InputError(
            f"a sensor-noise fault mode's range is its experiments' magnitudes: give k_min {magnitudes[0]:g} "
            f"and k_max {magnitudes[-1]:g} (got {body.k_min:g} and {body.k_max:g}), or add experiments "
            "at the range's ends"
        )


def _free_run_cells(
    session: Session,
    principal: Principal,
    structure: Structure,
    body: FaultModeTrain,
    records: list[Record],
    terms: int,
) -> int:
    """A sensor-noise training's cost in cells: every jointly fitted mode's samples times the
    joint fit's coefficients (θ₀ and one δ a mode), once for the fit and once more for each
    experiment's jackknife refit (``models.free_run_inspection.fit_free_run_modes``)."""
    others = _other_free_run_modes(session, structure, body.name)
    every = records + [
        r
        for version in others
        for r in owned_records(session, principal, structure, _experiment_ids(version))
    ]
    coefficients = terms * (len(others) + 2)
    return sum(r.n_samples for r in every) * coefficients * (len(every) + 1)


def baseline_terms(
    histories: list[tuple[np.ndarray, np.ndarray]], given: list[str] | None
) -> tuple[tuple[Term, ...], dict[str, Any]]:
    """A baseline's terms: those ``given``, or those chosen for the structure from its healthy
    ``histories`` (:func:`models.baseline_choice.choose_baseline_terms`), with what the training
    keeps of the choice (``choice``: the orders, delay, nonlinear terms added and the held-out
    free run) so that a person sees why the model has the terms it has."""
    if given:
        return parse_terms(given), {}
    choice = choose_baseline_terms(histories)
    return choice.terms, {"choice": choice.to_dict()}


def given_or_baseline_terms(
    session: Session, structure: Structure, given: list[str] | None
) -> tuple[tuple[Term, ...], dict[str, Any]]:
    """A fault mode's or pooled model's terms: those ``given``, or the structure's active
    baseline's, the model its fault modes extend; with what the training keeps of where they came
    from (``terms_from``). No baseline and no terms is refused: no structure's terms are assumed."""
    if given:
        return parse_terms(given), {}
    query = select(ModelVersion).where(
        ModelVersion.structure_id == structure.id,
        ModelVersion.name == BASELINE,
        ModelVersion.active.is_(True),
    )
    baseline = session.scalar(query.options(defer(ModelVersion.document)))
    if baseline is None:
        raise ConflictError(
            f"structure {structure.name!r} has no active baseline to take the terms from: train a baseline "
            f"first (POST /api/v1/structures/{structure.id}/models/baseline chooses its terms from healthy "
            "records) or give terms"
        )
    source = {"model_id": baseline.id, "name": baseline.name, "version": baseline.version}
    return parse_terms(baseline.training["terms"]), {"terms_from": source}


def _choice_cells(records: list[Record], settings: Settings) -> int:
    """What choosing a baseline's terms costs in cells (``CHOICE_COLUMNS`` a sample), refused
    over the limits or for a record too short to hold out part of, before any signal is read."""
    short = next((r for r in records if r.n_samples < CHOICE_MIN_SAMPLES), None)
    if short is not None:
        raise InputError(
            f"record {short.id} has {short.n_samples} samples; choosing a baseline's terms holds out part "
            f"of each record and needs at least {CHOICE_MIN_SAMPLES}: use longer records, or give the "
            "baseline's terms"
        )
    cells = sum(r.n_samples for r in records) * CHOICE_COLUMNS
    try:
        check_cost(cells, MAX_CHOSEN_TERMS, settings, "choosing this baseline's terms")
    except InputError as exc:
        raise InputError(f"{exc}, or give the baseline's terms") from None
    return cells


def check_one_response(records: list[Record], structure: Structure, what: str) -> None:
    """Refuse a record of several channels where ``what`` takes records of one response y."""
    several = next((r for r in records if r.channels), None)
    if several is not None:
        raise InputError(
            f"record {several.id} has {len(several.channels or ())} response channels "
            f"({', '.join(several.channels or ())}); {what} takes records of one response y: "
            f"train a vector fault mode (POST /api/v1/structures/{structure.id}/models/vector-fault-modes)"
        )


def _vector_cells(records: list[Record], body: VectorFaultModeTrain, settings: Settings) -> int:
    """A vector training's cost in cells, after checking that its records all have the same
    channels (in any order): samples × the columns of one equation, K·p lags of the channels and p
    of x times the basis functions; its coefficients are K times those columns."""
    first = records[0]
    for record in records:
        if not record.channels:
            raise InputError(
                f"record {record.id} has one response y; a vector fault mode is trained from records of "
                "several channels"
            )
        if sorted(record.channels) != sorted(first.channels or ()):
            raise InputError(
                f"the records of a vector training must have the same channels: record {first.id} has "
                f"{', '.join(first.channels or ())}, record {record.id} has {', '.join(record.channels)}"
            )
    channels = len(first.channels or ())
    columns = (channels + 1) * body.lags * (body.degree + 1)
    cells = sum(r.n_samples for r in records) * columns
    check_cost(cells, columns * channels, settings, "this training")
    return cells


def _pooled_variables(records: list[Record], body: PooledBaselineTrain | PooledFaultModeTrain) -> list[str]:
    """The operating variables a pooled training pools over (by default those of its first
    record), refused unless every record carries each and its values differ between records."""
    variables = body.variables or sorted(c.name for c in records[0].conditions)
    if not variables:
        raise InputError(
            f"record {records[0].id} carries no operating conditions: a pooled model needs records stored "
            "with the conditions they were acquired under (such as temperature)"
        )
    if len(variables) > MAX_VARIABLES or len(set(variables)) != len(variables):
        raise InputError(
            f"a pooled model takes 1 to {MAX_VARIABLES} distinct operating variables, "
            f"got {', '.join(variables)}"
        )
    if MAGNITUDE in variables:
        raise InputError(f"{MAGNITUDE!r} names the fault magnitude; it cannot be an operating variable")
    for name in variables:
        values = set()
        for record in records:
            carried = condition_values(record.conditions)
            if name not in carried:
                raise InputError(
                    f"record {record.id} carries no operating variable {name!r} "
                    f"(it carries {', '.join(sorted(carried)) or 'none'}); a pooled training needs it "
                    "on every record"
                )
            values.add(carried[name])
        if len(values) == 1:
            raise InputError(
                f"every record of this training has {name} = {values.pop():g}: a pooled model cannot "
                "learn how the dynamics change with it; add records acquired over its range"
            )
    return variables


def _deactivate(session: Session, structure_id: int, name: str) -> None:
    session.execute(
        update(ModelVersion)
        .where(ModelVersion.structure_id == structure_id, ModelVersion.name == name)
        .values(active=False)
    )


def new_version(
    session: Session,
    structure: Structure,
    kind: str,
    name: str,
    document: dict[str, Any],
    training: dict[str, Any],
    statistics: dict[str, Any],
    active: bool = True,
) -> ModelVersion:
    _lock_versions(session, structure.id)
    if active:
        _deactivate(session, structure.id, name)
    # Read after the lock (and, on SQLite, after the first write): no other version of the
    # name can be numbered in between.
    latest = session.scalar(
        select(func.max(ModelVersion.version)).where(
            ModelVersion.structure_id == structure.id, ModelVersion.name == name
        )
    )
    version = ModelVersion(
        structure_id=structure.id,
        kind=kind,
        name=name,
        version=(latest or 0) + 1,
        document=document,
        training=training,
        statistics=statistics,
        active=active,
    )
    session.add(version)
    try:
        session.flush()
    except IntegrityError:  # the request fails whole: its session is rolled back
        raise ConflictError(f"another version of {name!r} was created at the same moment; retry") from None
    return version
