"""The demo organisation: a 2-DOF structure with a baseline and k1 and k2 fault-mode models."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from service.domain import modelling, records, structures
from service.schemas import BaselineTrain, Experiment, FaultModeTrain, StructureCreate
from service.security import Principal, Role
from service.tables import ApiKey, Organisation, Structure
from simulator.paper import StudySettings
from simulator.simulate import simulate

ORGANISATION = "demo"
STRUCTURE = "2-DOF rig (paper parameters)"


def seed_demo(session: Session, progress: Callable[[str], None] = lambda _: None) -> Structure:
    """Create the demo once; later calls find it and change nothing."""
    organisation = session.scalar(select(Organisation).where(Organisation.name == ORGANISATION))
    if organisation is None:
        organisation = Organisation(name=ORGANISATION)
        session.add(organisation)
        session.flush()
    principal = Principal(organisation.id, Role.admin, key_id=0)
    existing = session.scalar(
        select(Structure).where(Structure.organisation_id == organisation.id, Structure.name == STRUCTURE)
    )
    if existing is not None:
        return existing
    settings = StudySettings()
    structure = structures.create_structure(
        session,
        principal,
        StructureCreate(
            name=STRUCTURE,
            fs=settings.scenario().fs,
            description="Two masses, cubic spring on mass 2; force on mass 1, displacement of mass 2.",
        ),
    )
    seeds = np.random.SeedSequence(2026).spawn(1 + 2 * len(settings.experiment_k))
    progress("baseline record")
    healthy = simulate(settings.scenario(), settings.baseline_samples, seeds[0])
    baseline, _ = records.store_record(session, structure, healthy.x, healthy.y, healthy.fs, None, 1)
    modelling.train_baseline(session, principal, structure.id, BaselineTrain(record_ids=[baseline.id]))
    for index, mode in enumerate(("k2", "k1")):
        progress(f"{mode} experiments")
        experiments = []
        for j, k in enumerate(settings.experiment_k):
            seed = seeds[1 + index * len(settings.experiment_k) + j]
            run = simulate(settings.scenario(mode, k), settings.experiment_samples, seed)
            record, _ = records.store_record(session, structure, run.x, run.y, run.fs, None, 1)
            experiments.append(Experiment(record_id=record.id, k=k))
        k_min, k_max = min(settings.experiment_k), max(settings.experiment_k)
        modelling.train_fault_mode(
            session,
            principal,
            structure.id,
            FaultModeTrain(name=mode, k_min=k_min, k_max=k_max, experiments=experiments),
        )
    return structure


def has_keys(session: Session, organisation_name: str) -> bool:
    query = select(ApiKey.id).join(Organisation).where(Organisation.name == organisation_name).limit(1)
    return session.scalar(query) is not None
