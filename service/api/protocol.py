"""A deadline for each request's head (its request line and headers), kept by the HTTP protocol.

A middleware sees a request only once its head is complete, so the body's bound
(``service.api.limits``) cannot cover the head: a client trickling a header line a few bytes at a
time, or opening a connection and saying nothing, would hold its connection, and a file
descriptor of the server, for as long as it liked. uvicorn bounds only the idle wait after a
response (``timeout_keep_alive``), and drops that bound at the first byte of the next request.

Here the head must be complete ``header_timeout_seconds`` after the connection opened, or after
the end of the previous response on a keep-alive connection; past that the connection is closed.
A head begun and not finished is answered 408 first (no response is under way then: the deadline
runs only between one response and the next head); a connection that sent nothing is closed
silently, as uvicorn closes an idle keep-alive connection, whose client may not be reading.
Both timers run after a response; whichever ends first closes an idle connection.

uvicorn picks httptools' parser when it is installed (``uvicorn[standard]`` installs it), so this
extends that protocol; the server is given the class (``http=``) rather than left to choose.
"""

from __future__ import annotations

import asyncio
import json
from typing import Any

from uvicorn.config import Config
from uvicorn.protocols.http.httptools_impl import STATUS_LINE, HttpToolsProtocol
from uvicorn.server import ServerState

from service.config import get_settings
from service.observability.metrics import HEADER_TIMEOUTS


class HeaderTimeoutProtocol(HttpToolsProtocol):
    # None: NARXWATCH_HEADER_TIMEOUT_SECONDS, read in the process serving (each uvicorn worker).
    timeout: float | None = None

    def __init__(
        self,
        config: Config,
        server_state: ServerState,
        app_state: dict[str, Any],
        _loop: asyncio.AbstractEventLoop | None = None,
    ) -> None:
        super().__init__(config, server_state, app_state, _loop)
        self.header_timeout = (
            self.timeout if self.timeout is not None else get_settings().header_timeout_seconds
        )
        self.header_deadline: asyncio.TimerHandle | None = None
        self.head_begun = False  # bytes of a head that is not complete yet were received

    def connection_made(self, transport: asyncio.Transport) -> None:
        super().connection_made(transport)
        self._arm_header_deadline()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_header_deadline()
        super().connection_lost(exc)

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self.head_begun = True

    def on_headers_complete(self) -> None:
        self.head_begun = False
        self._cancel_header_deadline()
        super().on_headers_complete()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        # uvicorn arms its keep-alive timer when the connection goes on and waits for a next
        # request; a next request already read (pipelined) has its head, and is started instead.
        if self.timeout_keep_alive_task is not None:
            self._arm_header_deadline()

    def _arm_header_deadline(self) -> None:
        self._cancel_header_deadline()
        self.header_deadline = self.loop.call_later(self.header_timeout, self._header_timeout_handler)

    def _cancel_header_deadline(self) -> None:
        if self.header_deadline is not None:
            self.header_deadline.cancel()
            self.header_deadline = None

    def _header_timeout_handler(self) -> None:
        self.header_deadline = None
        if self.transport.is_closing():
            return
        if self.head_begun:
            self.transport.write(self._request_timeout())
        HEADER_TIMEOUTS.labels(head="part" if self.head_begun else "none").inc()
        self.transport.close()

    def _request_timeout(self) -> bytes:
        """A 408 as the app words its errors (``{"detail": …}``), closing the connection."""
        detail = (
            f"the request's headers did not arrive within {self.header_timeout:g} s "
            "(NARXWATCH_HEADER_TIMEOUT_SECONDS)"
        )
        body = json.dumps({"detail": detail}).encode()
        headers = [*self.server_state.default_headers]
        headers += [
            (b"content-type", b"application/json"),
            (b"content-length", str(len(body)).encode()),
            (b"connection", b"close"),
        ]
        return b"".join(
            [STATUS_LINE[408], *(name + b": " + value + b"\r\n" for name, value in headers), b"\r\n", body]
        )


def header_timeout_protocol(seconds: float) -> type[HeaderTimeoutProtocol]:
    """The protocol with a deadline of its own, for a server started in this process from settings
    given to it rather than read from the environment (the tests' LiveServer)."""
    return type(HeaderTimeoutProtocol.__name__, (HeaderTimeoutProtocol,), {"timeout": seconds})
