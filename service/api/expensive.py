"""Requests that cost much: a cap on those one organisation runs at once, a cap on the uploads
worked on at once, and work handed to a job.

Trainings, refinements and inspections of stored records take seconds and hold a thread and a
pooled connection while they run. Each organisation may run ``max_concurrent_expensive`` of
them at once in one process; more are answered 429, so that one organisation's burst cannot
take every thread and connection from the others. Work above ``queue_training_cells`` is not
run in its request at all: it is queued as a job and answered 202 with the job's address.
Record uploads are worked on ``max_concurrent_uploads`` at a time in one process, whoever sends
them (:class:`Uploads`).
"""

from __future__ import annotations

import threading
import uuid
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

import anyio
from fastapi import HTTPException, Request, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse
from sqlalchemy.orm import Session
from starlette.background import BackgroundTask

from service.jobs.tasks import job_principal
from service.schemas import JobAccepted
from service.security import Principal

JOBS_PATH = "/api/v1/jobs"
RETRY_AFTER_SECONDS = 5
Result = TypeVar("Result")


class Slots:
    """How many expensive requests each organisation is running in this process."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._lock = threading.Lock()
        self._running: Counter[int] = Counter()

    @contextmanager
    def held(self, organisation_id: int) -> Iterator[None]:
        """Run the block in one of the organisation's slots; 429 if all are taken."""
        with self._lock:
            if self._running[organisation_id] >= self.limit:
                raise HTTPException(
                    status.HTTP_429_TOO_MANY_REQUESTS,
                    "your organisation already runs as many trainings, refinements and inspections of "
                    f"stored records at once as this server allows ({self.limit}, "
                    f"NARXWATCH_MAX_CONCURRENT_EXPENSIVE); retry in {RETRY_AFTER_SECONDS} s",
                    headers={"Retry-After": str(RETRY_AFTER_SECONDS)},
                )
            self._running[organisation_id] += 1
        try:
            yield
        finally:
            with self._lock:
                self._running[organisation_id] -= 1

    def running(self, organisation_id: int) -> int:
        with self._lock:
            return self._running[organisation_id]


class Uploads:
    """The uploads this process works on at once (parse, check, inspect, store): at most
    ``limit``, whoever sends them.

    A parse holds a few times its body in memory, and parsing and inspecting hold the
    interpreter lock while they run: without a bound, one key's burst of uploads took the
    process's memory by gigabytes and other organisations' reads to seconds, and uploads
    interleaved on threads cost more CPU each than one after another. An upload beyond
    the limit waits on the event loop, holding no thread and no pooled connection, at most
    ``wait`` seconds for one to end, then is answered 503 with Retry-After: a queue bounded in
    time rather than a refusal at once, since a slot turns over within a second or so.
    """

    def __init__(self, limit: int, wait: float) -> None:
        self.limit = limit
        self.wait = wait
        self._semaphore = anyio.Semaphore(limit)  # tied to the serving event loop at its first use

    def running(self) -> int:
        """The uploads being worked on now."""
        return self.limit - self._semaphore.value

    async def run(self, upload: Callable[[], Result]) -> Result:
        """``upload()`` on a worker thread, in one of the slots."""
        try:
            with anyio.fail_after(self.wait):
                await self._semaphore.acquire()
        except TimeoutError:
            raise HTTPException(
                status.HTTP_503_SERVICE_UNAVAILABLE,
                f"the server is working on as many uploads at once as it may ({self.limit}, "
                f"NARXWATCH_MAX_CONCURRENT_UPLOADS) and none ended within {self.wait:g} s "
                f"(NARXWATCH_UPLOAD_WAIT_SECONDS); retry in {RETRY_AFTER_SECONDS} s",
                headers={"Retry-After": str(RETRY_AFTER_SECONDS)},
            ) from None
        try:
            return await run_in_threadpool(upload)
        finally:  # after the thread has ended, even if the request was cancelled meanwhile
            self._semaphore.release()


def slot(request: Request, principal: Principal) -> Any:
    """``with slot(request, principal):`` around the expensive part of a request."""
    return request.app.state.expensive.held(principal.organisation_id)


def queued(request: Request, session: Session, principal: Principal, task: str, **args: Any) -> JSONResponse:
    """Queue ``task`` as the caller and answer 202 with where to follow the job (the request's
    commit writes the job; the worker is woken after it)."""
    token = uuid.uuid4().hex  # marks what the job stores, so that running it twice stores it once
    jobs = request.app.state.jobs
    job_id = jobs.defer(
        session, task, principal.organisation_id, principal=job_principal(principal), token=token, **args
    )
    location = f"{JOBS_PATH}/{job_id}"
    accepted = JobAccepted(
        job_id=job_id,
        location=location,
        detail="too large to run within a request (NARXWATCH_QUEUE_TRAINING_CELLS): queued as a job",
    )
    return JSONResponse(
        accepted.model_dump(),
        status_code=status.HTTP_202_ACCEPTED,
        headers={"Location": location},
        background=BackgroundTask(jobs.wake),
    )


def run_or_queue(
    request: Request,
    session: Session,
    principal: Principal,
    cells: int,
    work: Callable[[], Result],
    task: str,
    **args: Any,
) -> Result | JSONResponse:
    """``work()`` within the request in one of the organisation's slots or, where its ``cells``
    exceed ``queue_training_cells``, ``task(**args)`` queued as a job (:func:`queued`)."""
    if cells > request.app.state.settings.queue_training_cells:
        return queued(request, session, principal, task, **args)
    with slot(request, principal):
        return work()


BUSY: dict[int | str, dict[str, Any]] = {
    429: {
        "description": "The organisation runs as many expensive requests as it may: retry after Retry-After"
    }
}
UPLOADS_BUSY: dict[int | str, dict[str, Any]] = {
    503: {"description": "The server works on as many uploads as it may at once: retry after Retry-After"}
}
ACCEPTED = BUSY | {
    202: {"model": JobAccepted, "description": "Queued as a job: too large to run within a request"}
}
