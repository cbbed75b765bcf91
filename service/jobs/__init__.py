"""Inspections and schedules as jobs, on one of two backends behind one interface.

- ``embedded`` (the default on SQLite): jobs in the database's ``jobs`` table, run by a thread
  of each service process, which also sweeps the schedules. Nothing else to start.
- ``distributed`` (the default on PostgreSQL): Procrastinate, run by ``narxwatch worker``
  processes on any number of machines.

Either way a job is deferred in the transaction of the request that asks for it, so an
acknowledged upload always has its job; every job runs at least once, and its task is
idempotent, so a redelivered job changes nothing. A job that fails is retried with backoff,
unless its error says that running it again cannot succeed (``FINAL_ERRORS``): it then fails at
once, its reason stored for ``GET /jobs``. Every job belongs to an organisation, which alone
sees it.

Fair share: no organisation's backlog holds up another's jobs. A job is queued with priority
−n, n being its organisation's jobs waiting at that moment, and workers take the highest
priority first, then the oldest. Organisations' waiting jobs are thus taken in turn (the first of
each, then the second of each, …): a job queued behind a thousand of another organisation's
waits for one of them, not a thousand.
"""
