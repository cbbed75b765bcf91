"""Upload bodies: read with a size limit, then parsed by content type (JSON, CSV, NPZ, MAT)."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

import numpy as np
from fastapi import HTTPException, status
from pydantic import ValidationError

from models.errors import InputError
from recordfiles.channels import checked_channels
from recordfiles.conditions import MAX_CONDITIONS, Condition, checked_conditions
from recordfiles.quantities import UNIT_LENGTH
from recordfiles.reader import (
    DEFAULT_LAYOUT,
    Layout,
    parse_record,
    parse_record_set,
    record_samples,
    too_many_samples,
)
from service.schemas import MAX_REFINEMENT_RECORDS, ChannelUpload, RecordUpload

JSON = "application/json"
CSV = "text/csv"
NPZ_TYPES = ("application/x-npz", "application/zip", "application/octet-stream")
MAT = "application/x-matlab-data"  # as mime.types names .mat files
# The record file format (recordfiles.reader) of each media type but JSON.
FILE_FORMATS = {CSV: ".csv", MAT: ".mat"} | dict.fromkeys(NPZ_TYPES, ".npz")
# Commas of a JSON record beyond those between its samples: between the fields, and three for each
# condition with any its unit holds.
JSON_SLACK_COMMAS = 8 + MAX_CONDITIONS * (3 + UNIT_LENGTH)

REQUEST_BODY = {
    "required": True,
    "content": {
        JSON: {"schema": {"$ref": "#/components/schemas/RecordUpload"}},
        CSV: {
            "schema": {
                "type": "string",
                "description": "optional comment lines ('# fs=1500', conditions such as "
                "'# temperature=12.5 °C'), a header naming the columns, rows",
            }
        },
        "application/x-npz": {"schema": {"type": "string", "format": "binary"}},
        MAT: {"schema": {"type": "string", "format": "binary", "description": "MATLAB v4/v5/v7 MAT file"}},
    },
}


RECORD_SET_BODY = {
    "required": True,
    "content": {media: REQUEST_BODY["content"][media] for media in (CSV, MAT)},
}


@dataclass(frozen=True)
class Upload:
    x: np.ndarray | list[float]
    y: np.ndarray | list[float]  # (N, K) for a record of several channels
    fs: float | None
    acquired_at: dt.datetime | None
    conditions: tuple[Condition, ...]  # checked, sorted by name
    channels: tuple[str, ...] = ()  # checked, in the order given; none for a record of one response


def parse_upload(
    body: bytes,
    content_type: str,
    acquired_at: dt.datetime | None,
    max_bytes: int,
    layout: Layout = DEFAULT_LAYOUT,
) -> Upload:
    """A record from a body of the given media type; 415 for any other type.

    ``max_bytes`` bounds the arrays an NPZ or MAT file may unpack to, as the body limit bounds
    the body, and so the samples of a record in any format
    (:func:`recordfiles.reader.record_samples`). ``layout`` names the CSV columns or MAT
    variables that hold x and y.
    """
    media = content_type.split(";")[0].strip().lower()
    max_samples = record_samples(max_bytes)
    if media == JSON:
        if layout != DEFAULT_LAYOUT:
            raise InputError(
                "a JSON record has the fields x and y; the parameters x and y name the columns of "
                "a CSV or the variables of a MAT file"
            )
        # x and y of n samples take 2n − 2 commas, and the fields two or three more.
        if body.count(b",") > 2 * max_samples + JSON_SLACK_COMMAS:
            raise too_many_samples("the JSON holds", max_samples)
        try:
            record = RecordUpload.model_validate_json(body)
        except ValidationError as exc:
            raise InputError(_describe(exc)) from None
        conditions = checked_conditions(record.conditions)
        when = record.acquired_at or acquired_at
        if record.y is not None:
            if max(len(record.x), len(record.y)) > max_samples:
                raise too_many_samples("the JSON holds", max_samples)
            return Upload(record.x, record.y, record.fs, when, conditions)
        assert record.channels is not None  # one of the two, as the schema checks
        return _with_channels(record.x, record.channels, record.fs, when, conditions, max_bytes)
    suffix = FILE_FORMATS.get(media)
    if suffix is None:
        raise HTTPException(
            status.HTTP_415_UNSUPPORTED_MEDIA_TYPE,
            f"unsupported Content-Type {media or '(none)'!r}: send {JSON}, {CSV}, application/x-npz or {MAT}",
        )
    parsed = parse_record(body, suffix, layout, max_bytes)
    return Upload(parsed.x, parsed.y, parsed.fs, acquired_at, parsed.conditions, parsed.channels)


def parse_upload_set(
    body: bytes, content_type: str, acquired_at: dt.datetime | None, max_bytes: int, layout: Layout
) -> tuple[tuple[Layout, Upload], ...]:
    """The records of a CSV or MAT body, each with the signals that hold it
    (:func:`recordfiles.reader.parse_record_set`): k when the layout's x and y each name a group
    of k signals. 415 for any other media type, each record bounded as an upload is, and k by
    the records a refinement fits (each is checked and inserted under the write lock: short
    columns would otherwise make thousands of records of one body)."""
    media = content_type.split(";")[0].strip().lower()
    if media not in (CSV, MAT):
        raise HTTPException(
            status.HTTP_415_UNSUPPORTED_MEDIA_TYPE,
            f"a record set is a CSV ({CSV}) or a MAT file ({MAT}) holding the records' signals side by "
            f"side; got {media or '(none)'!r} (upload a single record to .../records)",
        )
    records = parse_record_set(body, FILE_FORMATS[media], layout, max_bytes)
    if len(records) > MAX_REFINEMENT_RECORDS:
        raise InputError(
            f"the file holds {len(records)} records; a set may hold at most {MAX_REFINEMENT_RECORDS}, "
            "as many as a refinement fits: upload it in parts"
        )
    return tuple(
        (named, Upload(record.x, record.y, record.fs, acquired_at, record.conditions))
        for named, record in records
    )


def _with_channels(
    x: list[float],
    channels: list[ChannelUpload],
    fs: float,
    acquired_at: dt.datetime | None,
    conditions: tuple[Condition, ...],
    max_bytes: int,
) -> Upload:
    """A JSON record of several channels, after checking their names and lengths."""
    names = checked_channels([channel.name for channel in channels])
    max_samples = record_samples(max_bytes, len(names))
    if len(x) > max_samples:
        raise too_many_samples("the JSON holds", max_samples, len(names))
    for channel in channels:
        if len(channel.y) != len(x):
            raise InputError(
                f"x has {len(x)} samples but the channel {channel.name!r} has {len(channel.y)}; "
                "x and every channel must be sampled together"
            )
    y = np.column_stack([np.asarray(channel.y, dtype=np.float64) for channel in channels])
    return Upload(x, y, fs, acquired_at, conditions, names)


def signal_layout(x: str, y: list[str], name_length: int) -> Layout:
    """The signals an upload's parameters name: one response y, or several channels named as they
    are (``y`` given 2 to 8 times), each name at most ``name_length`` characters."""
    for name in (x, *y):
        if len(name) > name_length:
            raise InputError(f"the signal name {name[:40]!r}… is longer than {name_length} characters")
    return Layout(x, y[0]) if len(y) == 1 else Layout(x, channels=tuple(checked_channels(y)))


def _describe(error: ValidationError) -> str:
    parts = []
    for item in error.errors()[:5]:
        where = ".".join(str(part) for part in item["loc"]) or "body"
        parts.append(f"{where}: {item['msg']}")
    more = error.error_count() - len(parts)
    return "invalid record: " + "; ".join(parts) + (f"; and {more} more" if more > 0 else "")
