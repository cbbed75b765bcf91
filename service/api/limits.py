"""Bounds on every request body, in size and in time, enforced before any route reads it.

A declared ``Content-Length`` over the limit is answered 413 at once; a body without one is
counted as it arrives and refused as soon as it passes the limit, so no request, on any route
and whether authenticated or not, can make the server hold more than the limit. Record uploads
may be large (``max_upload_bytes``); every other body is a small JSON document
(``max_request_bytes``), which FastAPI parses on the event loop before the route, and before
authentication: nested empty arrays cost Python some 25 times their text, so an upload-sized
body on any route would cost hundreds of megabytes and stall the process. The whole body
must also arrive within ``body_timeout`` seconds of the request's headers, or it is answered 408:
a client trickling its body cannot keep a request (and what it holds) alive for long.

Both refusals are raised from ``receive`` as HTTP exceptions, where the route reads the body:
FastAPI passes those through its body parsing (any other error there becomes a 400), and the
app's handler answers them like every other error, closing the connection whose body is unread.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from dataclasses import dataclass

import anyio
from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

CLOSE = {"Connection": "close"}  # the unread rest of the body makes the connection unusable


@dataclass(frozen=True)
class BodyLimit:
    """A largest body, and the setting that sets it (named in the refusal)."""

    bytes: int
    setting: str


class BodyTooLargeError(HTTPException):
    def __init__(self, limit: BodyLimit) -> None:
        detail = f"the request body exceeds the limit of {limit.bytes} bytes ({limit.setting})"
        super().__init__(413, detail, headers=CLOSE)


class BodyTimeoutError(HTTPException):
    def __init__(self, seconds: float) -> None:
        detail = (
            f"the request body did not arrive within {seconds:g} s (NARXWATCH_BODY_TIMEOUT_SECONDS); "
            "send it faster or in smaller parts"
        )
        super().__init__(408, detail, headers=CLOSE)


class BodyLimitMiddleware:
    """``uploads``: the paths (routes' ``path_regex``) whose bodies are records, bounded by
    ``upload_limit``; every other body is bounded by ``limit``."""

    def __init__(
        self,
        app: ASGIApp,
        limit: BodyLimit,
        upload_limit: BodyLimit,
        uploads: Sequence[re.Pattern[str]],
        timeout: float,
    ) -> None:
        self.app = app
        self.default_limit = limit
        self.upload_limit = upload_limit
        self.uploads = tuple(uploads)
        self.timeout = timeout

    def limit_of(self, path: str) -> BodyLimit:
        if any(upload.match(path) for upload in self.uploads):
            return self.upload_limit
        return self.default_limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.limit_of(scope["path"])
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and not declared.isdigit():
            await _answer(send, HTTPException(400, "the Content-Length header is not a number", CLOSE))
            return
        if declared is not None and int(declared) > limit.bytes:
            await _answer(send, BodyTooLargeError(limit))
            return
        deadline = anyio.current_time() + self.timeout
        received = 0
        complete = False

        async def bounded_receive() -> Message:
            nonlocal received, complete
            if complete:  # after the body: a wait for the client's disconnect, unbounded
                return await receive()
            try:
                with anyio.fail_after(deadline - anyio.current_time()):
                    message = await receive()
            except TimeoutError:
                raise BodyTimeoutError(self.timeout) from None
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit.bytes:
                    raise BodyTooLargeError(limit)
                complete = not message.get("more_body", False)
            return message

        await self.app(scope, bounded_receive, send)


async def _answer(send: Send, refusal: HTTPException) -> None:
    """Answer before the app is called, from the declared headers alone."""
    body = json.dumps({"detail": refusal.detail}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    headers += [(name.lower().encode(), value.encode()) for name, value in (refusal.headers or {}).items()]
    await send({"type": "http.response.start", "status": refusal.status_code, "headers": headers})
    await send({"type": "http.response.body", "body": body})
