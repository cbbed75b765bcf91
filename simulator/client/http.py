"""The narxwatch REST API over HTTP, as ``narxwatch-sim`` uses it."""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import httpx

from models.errors import InputError

API = "/api/v1"


class ServiceError(Exception):
    """The service refused a request or could not be reached; the message says which and why."""


class Service:
    """The narxwatch REST API over HTTP; every failure becomes a :class:`ServiceError`."""

    def __init__(self, url: str, key: str) -> None:
        if not url.startswith(("http://", "https://")):
            raise InputError(f"--url must start with http:// or https://, got {url!r}")
        self.url = url.rstrip("/")
        try:
            self._http = httpx.Client(
                base_url=self.url, headers={"Authorization": f"Bearer {key}"}, timeout=60
            )
        except httpx.InvalidURL as exc:
            raise InputError(f"--url {url!r} is not a usable URL ({exc})") from None

    def close(self) -> None:
        self._http.close()

    def request(self, method: str, path: str, **options: Any) -> Any:
        return self._json(self._send(method, path, **options), path)

    def pages(self, path: str, **options: Any) -> Iterator[Any]:
        """Every page of a listing, following its ``Link: <…>; rel="next"`` headers."""
        following: str | None = path
        while following is not None:
            response = self._send("GET", following, **options)
            yield self._json(response, path)
            following, options = response.links.get("next", {}).get("url"), {}  # the link keeps the query

    def _send(self, method: str, path: str, **options: Any) -> httpx.Response:
        try:
            response = self._http.request(method, path, **options)
        except httpx.TransportError as exc:
            reason = str(exc) or type(exc).__name__
            raise ServiceError(
                f"cannot reach narxwatch at {self.url} ({reason}); is the service running there?"
            ) from None
        if response.is_error:
            answer = f"{response.status_code} {response.reason_phrase}"
            raise ServiceError(f"the service answered {answer}: {server_detail(response)}")
        return response

    def _json(self, response: httpx.Response, path: str) -> Any:
        try:
            return response.json()
        except ValueError:
            raise ServiceError(
                f"{self.url} answered {path} without JSON: is it a narxwatch service?"
            ) from None

    def first_structure(self) -> dict[str, Any]:
        structures = self.request("GET", f"{API}/structures")
        if not structures:
            raise ServiceError(
                f"the API key sees no structure at {self.url}: create one (POST {API}/structures with an "
                "admin key) or pass --structure ID"
            )
        return structures[0]


def server_detail(response: httpx.Response) -> str:
    """The service's ``detail`` message: a string, or FastAPI's list of validation errors."""
    try:
        body = response.json()
    except ValueError:
        return "the answer holds no JSON; is the URL that of a narxwatch service?"
    detail = body.get("detail") if isinstance(body, dict) else body
    if isinstance(detail, str):
        return detail
    if isinstance(detail, list) and all(isinstance(item, dict) for item in detail):
        return "; ".join(
            f"{'.'.join(str(part) for part in item.get('loc', []))}: {item.get('msg', item)}"
            for item in detail
        )
    return json.dumps(detail)[:300]
