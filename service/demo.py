"""The demo organisation: a 2-DOF structure with a baseline and k1 and k2 fault-mode models."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from service.config import Settings
from service.domain import alarms, inspections, modelling, records, structures
from service.schemas import BaselineTrain, Experiment, FaultModeTrain, Signal, StructureCreate
from service.security import Principal, Role
from service.tables import ApiKey, Organisation, Structure, utcnow
from simulator.physics import EXCITATION, RESPONSE
from simulator.simulate import simulate
from simulator.study import StudySettings
from simulator.theory import EXACT_TERMS

ORGANISATION = "demo"
STRUCTURE = "2-DOF rig (paper parameters)"
HISTORY_RECORDS = 28
HISTORY_STEP = dt.timedelta(hours=6)
HEALTHY_RECORDS = 16
FAULT_START, FAULT_END = 4.0, 20.0  # k2 [%]
# The demo is the paper's rig: its models take the rig's exact structure (SPEC §2), not terms chosen
# from its records.
RIG_TERMS = [term.name for term in EXACT_TERMS]


def seed_demo(
    session: Session, settings: Settings, progress: Callable[[str], None] = lambda _: None
) -> Structure:
    """Create the demo once; later calls find it and change nothing."""
    organisation = session.scalar(select(Organisation).where(Organisation.name == ORGANISATION))
    if organisation is None:
        organisation = Organisation(name=ORGANISATION)
        session.add(organisation)
        session.flush()
    principal = Principal(organisation.id, Role.admin, key_id=0)
    # The organisation's first structure, by id, not by name: an admin may have renamed it.
    existing = session.scalar(
        select(Structure).where(Structure.organisation_id == organisation.id).order_by(Structure.id).limit(1)
    )
    if existing is not None:
        return existing
    study = StudySettings()
    structure = structures.create_structure(
        session,
        principal,
        StructureCreate(
            name=STRUCTURE,
            fs=study.scenario().fs,
            description="Two masses, cubic spring on mass 2; force on mass 1, displacement of mass 2.",
            excitation=Signal.model_validate(EXCITATION, from_attributes=True),
            response=Signal.model_validate(RESPONSE, from_attributes=True),
        ),
    )
    seeds = np.random.SeedSequence(2026).spawn(1 + 2 * len(study.experiment_k))
    progress("baseline record")
    healthy = simulate(study.scenario(), study.baseline_samples, seeds[0])
    baseline, _ = records.store_record(session, structure, healthy.x, healthy.y, healthy.fs, None)
    modelling.train_baseline(
        session, principal, structure.id, BaselineTrain(record_ids=[baseline.id], terms=RIG_TERMS), settings
    )
    for index, mode in enumerate(("k2", "k1")):
        progress(f"{mode} experiments")
        experiments = []
        for j, k in enumerate(study.experiment_k):
            seed = seeds[1 + index * len(study.experiment_k) + j]
            run = simulate(study.scenario(mode, k), study.experiment_samples, seed)
            record, _ = records.store_record(session, structure, run.x, run.y, run.fs, None)
            experiments.append(Experiment(record_id=record.id, k=k))
        k_min, k_max = min(study.experiment_k), max(study.experiment_k)
        modelling.train_fault_mode(
            session,
            principal,
            structure.id,
            FaultModeTrain(name=mode, k_min=k_min, k_max=k_max, experiments=experiments, terms=RIG_TERMS),
            settings,
        )
    progress("a week of inspected records")
    _history(session, structure, settings, study)
    return structure


def _history(session: Session, structure: Structure, settings: Settings, study: StudySettings) -> None:
    """A week of records every six hours, inspected: healthy, then a k2 fault growing to 20 %,
    so that the dashboard has a story to tell from the first start."""
    now = utcnow().replace(minute=0, second=0, microsecond=0)
    seeds = np.random.SeedSequence(2027).spawn(HISTORY_RECORDS)
    models = inspections.models_to_inspect_with(session, structure)
    alarms.lock(session, structure.id)  # before the state row that storing a record locks
    for index, seed in enumerate(seeds):
        growing = index - HEALTHY_RECORDS
        k = (
            0.0
            if growing < 0
            else FAULT_START + (FAULT_END - FAULT_START) * growing / (HISTORY_RECORDS - HEALTHY_RECORDS - 1)
        )
        run = simulate(study.scenario("k2", k), study.experiment_samples, seed)
        evaluation = inspections.evaluate(models, settings, run.x, run.y, {})
        acquired = now - (HISTORY_RECORDS - 1 - index) * HISTORY_STEP
        record, _ = records.store_record(session, structure, run.x, run.y, run.fs, acquired)
        inspections.store_verdict(session, record, structure, evaluation, settings, new_record=True)


def has_keys(session: Session, organisation_name: str) -> bool:
    query = select(ApiKey.id).join(Organisation).where(Organisation.name == organisation_name).limit(1)
    return session.scalar(query) is not None
