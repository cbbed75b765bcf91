"""Logs as one JSON object a line (or plain text), each stamped with its request's id.

The request id is the client's ``X-Request-ID`` when it is a sane token, else a fresh one; it is
echoed in the answer, so a client's report and the service's lines can be matched. Nothing here
logs headers, query strings or bodies: API keys travel in the Authorization header and must never
reach a log.
"""

from __future__ import annotations

import logging
import logging.config
import re
from typing import Any

from asgi_correlation_id import correlation_id
from pythonjsonlogger.core import RESERVED_ATTRS
from pythonjsonlogger.json import JsonFormatter

REQUEST_ID_HEADER = "X-Request-ID"
# Short, printable, no spaces or quotes: an id a client chose must not be able to forge log lines.
_SANE_REQUEST_ID = re.compile(r"[A-Za-z0-9._:-]{1,128}")


def is_sane_request_id(value: str) -> bool:
    return _SANE_REQUEST_ID.fullmatch(value) is not None


class RequestIdFilter(logging.Filter):
    """Stamps every record with the id of the request being handled (None outside requests).

    On the handler, not a logger: a logger's filters miss the records its children propagate.
    """

    def filter(self, record: logging.LogRecord) -> bool:
        record.request_id = correlation_id.get()
        return True


def json_formatter() -> logging.Formatter:
    return JsonFormatter(
        "%(levelname)s %(name)s %(message)s %(request_id)s",
        rename_fields={"levelname": "level", "name": "logger"},
        timestamp=True,  # ISO 8601, UTC
        # uvicorn repeats some messages with terminal colour codes as an extra field.
        reserved_attrs=[*RESERVED_ATTRS, "color_message"],
    )


def text_formatter() -> logging.Formatter:
    return logging.Formatter("%(asctime)s %(levelname)s %(name)s request_id=%(request_id)s %(message)s")


def logging_config(level: str, json: bool) -> dict[str, Any]:
    """A ``logging.config.dictConfig`` document: every logger, uvicorn's included, writes through
    one stderr handler; uvicorn applies it in each worker process it starts."""
    formatter = json_formatter if json else text_formatter
    return {
        "version": 1,
        "disable_existing_loggers": False,
        "filters": {"request_id": {"()": RequestIdFilter}},
        "formatters": {"default": {"()": formatter}},
        "handlers": {
            "stderr": {
                "class": "logging.StreamHandler",
                "stream": "ext://sys.stderr",
                "formatter": "default",
                "filters": ["request_id"],
            }
        },
        "root": {"level": level, "handlers": ["stderr"]},
        "loggers": {
            name: {"handlers": [], "propagate": True}
            for name in ("uvicorn", "uvicorn.error", "uvicorn.access")
        },
    }


def configure_logging(level: str, json: bool) -> None:
    logging.config.dictConfig(logging_config(level, json))
