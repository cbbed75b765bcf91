"""Names people give, normalised and safe to display (recordfiles.names), in every field that takes
one: the request bodies' schemas, the channel and condition names of records however they come,
and organisations created with a key. Structures, the one free-text name, are tested over HTTP in
test_api_errors.py."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from pydantic import BaseModel, ValidationError
from sqlalchemy import select

from harness import migrated
from models.errors import InputError
from recordfiles.channels import checked_channels
from recordfiles.conditions import Condition, checked_conditions
from recordfiles.names import normalised_name
from recordfiles.reader import Layout, parse_record
from service.db import make_engine, session_factory, transaction
from service.schemas import (
    ChannelUpload,
    FaultModeTrain,
    PooledBaselineTrain,
    PooledFaultModeTrain,
    StructureCreate,
    VectorFaultModeTrain,
)
from service.security import Role, create_key
from service.tables import Organisation

# A name → what its refusal says: the character by its code point, and where it stands.
REFUSED = {
    "lone-space": (" ", "cannot be empty or only whitespace"),
    "no-break-spaces": ("\u00a0\u3000", "cannot be empty or only whitespace"),
    "byte-order-mark": ("\ufeff", "byte-order mark (zero-width no-break space): U+FEFF"),
    "right-to-left-override": ("k2\u202e", "U+202E (RIGHT-TO-LEFT OVERRIDE) is character 3"),
    "left-to-right-mark": (
        "\u200ek2",
        "bidirectional control character, which reorders what is shown: U+200E",
    ),
    "first-strong-isolate": ("k\u20682", "U+2068 (FIRST STRONG ISOLATE) is character 2"),
    "arabic-letter-mark": ("k2\u061c", "U+061C"),
    "zero-width-joiner": ("k\u200d2", "invisible format character: U+200D"),
    "bell": ("k\x072", "control character: U+0007"),
    "c1-control": ("k\x852", "control character: U+0085"),
    "lone-surrogate": ("k\ud800", "lone surrogate, not a character: U+D800"),
}

TWO = [{"record_id": 1, "k": 0.0}, {"record_id": 2, "k": 1.0}]
# Each schema field that takes a name: the schema, a valid body holding ``name`` there, and the
# body's name as the model holds it.
FIELDS: dict[str, tuple[type[BaseModel], Callable[[str], dict[str, Any]], Callable[[Any], str]]] = {
    "structure": (StructureCreate, lambda n: {"name": n, "fs": 1500.0}, lambda m: m.name),
    "fault-mode": (
        FaultModeTrain,
        lambda n: {"name": n, "k_min": 0.0, "k_max": 1.0, "experiments": TWO},
        lambda m: m.name,
    ),
    "pooled-fault-mode": (PooledFaultModeTrain, lambda n: {"name": n, "experiments": TWO}, lambda m: m.name),
    "vector-fault-mode": (VectorFaultModeTrain, lambda n: {"name": n, "experiments": TWO}, lambda m: m.name),
    "pooled-variable": (
        PooledBaselineTrain,
        lambda n: {"record_ids": [1, 2], "variables": [n]},
        lambda m: m.variables[0],
    ),
    "pooled-fault-mode-variable": (
        PooledFaultModeTrain,
        lambda n: {"name": "k2", "experiments": TWO, "variables": [n]},
        lambda m: m.variables[0],
    ),
    "channel": (ChannelUpload, lambda n: {"name": n, "y": [1.0]}, lambda m: m.name),
}


@pytest.mark.parametrize("field", FIELDS)
@pytest.mark.parametrize(("name", "fragment"), REFUSED.values(), ids=REFUSED.keys())
def test_every_name_field_refuses_what_would_not_display_as_it_is(field, name, fragment):
    schema, body, _ = FIELDS[field]
    with pytest.raises(ValidationError) as refused:
        schema.model_validate(body(name))
    (error,) = refused.value.errors()
    assert fragment in error["msg"], error
    assert error["loc"][0] in ("name", "variables"), error["loc"]


@pytest.mark.parametrize("field", FIELDS)
def test_every_name_field_stores_the_name_trimmed_and_composed(field):
    schema, body, read = FIELDS[field]
    assert read(schema.model_validate(body(" \u00a0temp_2\t"))) == "temp_2"
    if field == "structure":  # the free-text one: others admit ASCII identifiers only
        assert read(schema.model_validate(body(" Cafe\u0301 "))) == "Caf\u00e9"


def test_the_rule_itself():
    assert normalised_name("  Pump 3 ") == "Pump 3"
    assert normalised_name("e\u0301") == "\u00e9"
    assert normalised_name("Pump\u00a0 3") == "Pump\u00a0 3", "inner spacing is the name's own"
    assert normalised_name("\u0645\u0636\u062e\u0629") == "\u0645\u0636\u062e\u0629", (
        "right-to-left script is fine"
    )
    with pytest.raises(InputError, match=r"a channel name cannot hold .* of the channel name given"):
        normalised_name("a\u202e1", "channel name")


@pytest.mark.parametrize(("name", "fragment"), REFUSED.values(), ids=REFUSED.keys())
def test_channel_and_condition_names_from_any_source_follow_the_rule(name, fragment):
    """Names that come in files (CSV headers, NPZ members) or JSON meet the same rule in the
    modules every way in ends in."""
    with pytest.raises(InputError, match="channel name") as refused:
        checked_channels([name, "b2"])
    assert fragment in str(refused.value)
    with pytest.raises(InputError, match="condition name") as refused:
        checked_conditions([Condition(name, 1.0, "K")])
    assert fragment in str(refused.value)


def test_channel_and_condition_names_are_trimmed():
    assert checked_channels([" a1", "b2\u00a0"]) == ("a1", "b2")
    (condition,) = checked_conditions([Condition(" temperature ", 12.5, "\u00b0C")])
    assert condition == Condition("temperature", 12.5, "\u00b0C")
    with pytest.raises(InputError, match="given twice"):
        checked_conditions([Condition("speed", 1.0), Condition("speed ", 2.0)])


def test_channels_named_on_the_command_line_are_read_by_their_normalised_names():
    """``--y " a1" --y b2`` reads the columns a1 and b2, named so, as an upload naming them does."""
    data = b"x,a1,b2\n" + b"".join(b"%d,%d,%d\n" % (i, 2 * i, 3 * i) for i in range(300))
    record = parse_record(data, ".csv", Layout(fs=100.0, channels=(" a1", "b2\u00a0")))
    assert record.channels == ("a1", "b2")
    assert record.y.tolist()[:3] == [[0, 0], [2, 3], [4, 6]]


def test_an_organisation_created_with_a_key_gets_a_normalised_name_or_none(tmp_path: Path):
    url = migrated.sqlite(tmp_path / "names.db")
    sessions = session_factory(make_engine(url))
    for refused in ("\u202eacme", " ", "ac\ufeffme"):
        with pytest.raises(InputError, match="organisation name"), transaction(sessions) as session:
            create_key(session, refused, Role.admin)
    with transaction(sessions) as session:
        create_key(session, "  Acme\u0301 ", Role.admin)
        create_key(session, "Acm\u00e9", Role.viewer)  # the same organisation
    with sessions() as session:
        assert session.scalars(select(Organisation.name)).all() == ["Acm\u00e9"]
