"""Upload bodies: read with a size limit, then parsed by content type (JSON, CSV, NPZ)."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

import numpy as np
from fastapi import HTTPException, Request, status
from pydantic import ValidationError

from models.errors import InputError
from service.schemas import RecordUpload
from simulator.recordfile import parse_csv, parse_npz

JSON = "application/json"
CSV = "text/csv"
NPZ_TYPES = ("application/x-npz", "application/zip", "application/octet-stream")

REQUEST_BODY = {
    "required": True,
    "content": {
        JSON: {"schema": {"$ref": "#/components/schemas/RecordUpload"}},
        CSV: {"schema": {"type": "string", "description": "optional '# fs=1500' line, header 'x,y', rows"}},
        "application/x-npz": {"schema": {"type": "string", "format": "binary"}},
    },
}


@dataclass(frozen=True)
class Upload:
    x: np.ndarray | list[float]
    y: np.ndarray | list[float]
    fs: float | None
    acquired_at: dt.datetime | None


async def read_body(request: Request, limit: int) -> bytes:
    """The request body, refused with 413 as soon as it exceeds ``limit`` bytes."""
    declared = request.headers.get("content-length")
    if declared is not None:
        if not declared.isdigit():
            raise HTTPException(status.HTTP_400_BAD_REQUEST, "the Content-Length header is not a number")
        if int(declared) > limit:
            raise _too_large(limit)
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise _too_large(limit)
        chunks.append(chunk)
    return b"".join(chunks)


def parse_upload(body: bytes, content_type: str, acquired_at: dt.datetime | None) -> Upload:
    """A record from a body of the given media type; 415 for any other type."""
    media = content_type.split(";")[0].strip().lower()
    if media == JSON:
        try:
            record = RecordUpload.model_validate_json(body)
        except ValidationError as exc:
            raise InputError(_describe(exc)) from None
        return Upload(record.x, record.y, record.fs, record.acquired_at or acquired_at)
    if media == CSV:
        parsed = parse_csv(body)
    elif media in NPZ_TYPES:
        parsed = parse_npz(body)
    else:
        raise HTTPException(
            status.HTTP_415_UNSUPPORTED_MEDIA_TYPE,
            f"unsupported Content-Type {media or '(none)'!r}: send {JSON}, {CSV} or application/x-npz",
        )
    return Upload(parsed.x, parsed.y, parsed.fs, acquired_at)


def _describe(error: ValidationError) -> str:
    parts = []
    for item in error.errors()[:5]:
        where = ".".join(str(part) for part in item["loc"]) or "body"
        parts.append(f"{where}: {item['msg']}")
    more = error.error_count() - len(parts)
    return "invalid record: " + "; ".join(parts) + (f"; and {more} more" if more > 0 else "")


def _too_large(limit: int) -> HTTPException:
    return HTTPException(
        status.HTTP_413_REQUEST_ENTITY_TOO_LARGE,
        f"the upload exceeds the limit of {limit} bytes (NARXWATCH_MAX_UPLOAD_BYTES)",
    )
