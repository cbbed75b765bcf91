"""Response channels: a record of several sensors carries x and several named responses.

A record of one response has ``y`` and is stored and answered as it always was. A record of
several carries 2 to :data:`MAX_CHANNELS` named channels (``a1``, ``a2``, ``a3``) of one length
each, x's; every way into the service (a JSON ``channels`` list, CSV columns, NPZ members or MAT
variables named by repeated ``y`` parameters) ends in :func:`checked_channels`, so one rule holds
for all of them:

- a name is a letter followed by at most 31 letters, digits or underscores (column and variable
  names as the benchmarks publish them, such as ``Acceleration2``), and not ``x`` or ``fs``;
- each name is given once, and the names are kept in the order given: a vector model's channels
  are matched by name, whatever their order in a record.

The bound keeps a vector model's size (K equations over K·p lags each) and a record's cost small.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

from models.errors import InputError
from recordfiles.names import normalised_name

MAX_CHANNELS = 8
NAME_LENGTH = 32
NAME_RULE = re.compile(rf"[A-Za-z][A-Za-z0-9_]{{0,{NAME_LENGTH - 1}}}")
RESERVED = ("x", "fs")


def checked_channels(names: Sequence[str]) -> tuple[str, ...]:
    """The channel names of a record of several responses, in the order given and normalised
    (``recordfiles.names``), after checking their number, each name against the rule and that none
    is given twice."""
    if len(names) > MAX_CHANNELS:
        raise InputError(
            f"the record has {len(names)} response channels; a record may have at most {MAX_CHANNELS}"
        )
    if len(names) < 2:
        raise InputError("a record of several channels needs at least two; give one response as y")
    names = [normalised_name(name, "channel name") for name in names]
    for name in names:
        if not NAME_RULE.fullmatch(name) or name.lower() in RESERVED:
            raise InputError(
                f"the channel name {name[:40]!r} is not allowed: a channel's name is a letter followed by at "
                f"most {NAME_LENGTH - 1} letters, digits or underscores, and not x or fs"
            )
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise InputError(f"the channel {repeated[0]!r} is given twice; give each channel once")
    return tuple(names)


def describe(names: Sequence[str]) -> str:
    return ", ".join(names) or "none"


def matched(record: Sequence[str], model: Sequence[str], model_name: str) -> list[int]:
    """For each of the model's channels, its column in the record; refused, naming the channels
    missing from the record and those it has beyond the model's, unless they are the same set."""
    missing = [name for name in model if name not in record]
    extra = [name for name in record if name not in model]
    if missing or extra:
        parts = [
            f"lacks {describe(missing)}" if missing else "",
            f"also has {describe(extra)}" if extra else "",
        ]
        raise InputError(
            f"the record's channels ({describe(record)}) are not those of the vector model {model_name!r} "
            f"({describe(model)}): it " + " and ".join(part for part in parts if part)
        )
    return [list(record).index(name) for name in model]
