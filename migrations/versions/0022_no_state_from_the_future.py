"""structures' states read again without the verdicts acquired in the future

Revision ID: 0022
Revises: 0021
Create Date: 2026-12-06 08:00:00.000000

Uploads' acquisition times had no upper bound, so a record dated 9999 (a clock set wrong, a
typing error) became its structure's latest verdict, and every fault acquired after it read as
the status it had, "since 9999-12-31". Such times are now refused (NARXWATCH_MAX_CLOCK_SKEW_SECONDS
past the server's clock), and no verdict acquired later than that stands for its structure
(``service.domain.fleet.count_verdict``). The structures already holding one have their latest
verdict and since-when read again here from the verdicts acquired up to the server's clock plus
that skew (in the environment this revision runs in); the counts, of every verdict stored, stay.
The verdicts themselves are kept: the history lists them as they were uploaded.
Downgrading changes nothing: the earlier code keeps the state as it is left.
"""

from __future__ import annotations

import datetime as dt

import sqlalchemy as sa
from alembic import op

revision = "0022"
down_revision = "0021"
branch_labels = None
depends_on = None


def upgrade() -> None:
    # Imported here: every command but serve loads the revisions to check the schema.
    from service.config import Settings

    skew = dt.timedelta(seconds=Settings().max_clock_skew_seconds)
    limit = sa.bindparam("limit", dt.datetime.now(dt.UTC) + skew, type_=sa.DateTime(timezone=True))
    connection = op.get_bind()
    structures = connection.execute(
        sa.text("SELECT DISTINCT structure_id FROM verdicts WHERE acquired_at > :limit").bindparams(limit)
    ).scalars()
    for structure_id in list(structures):
        newest = connection.execute(
            sa.text(
                "SELECT id, status FROM verdicts WHERE structure_id = :s AND acquired_at <= :limit "
                "ORDER BY acquired_at DESC, id DESC LIMIT 1"
            ).bindparams(limit),
            {"s": structure_id},
        ).first()
        if newest is None:  # uninspected, as far as the present knows
            connection.execute(
                sa.text(
                    "UPDATE structure_states SET status = NULL, since = NULL, latest_verdict_id = NULL, "
                    "latest_acquired_at = NULL WHERE structure_id = :s"
                ),
                {"s": structure_id},
            )
        else:
            _stand_on(connection, structure_id, *newest, limit)


def _stand_on(
    connection: sa.Connection, structure_id: int, verdict_id: int, status: str, limit: sa.BindParameter
) -> None:
    """The state's latest verdict, and the start of its run: the first verdict after the last one
    of another status acquired up to ``limit`` (as 0012 reads it, less the verdicts after it)."""
    other = connection.execute(
        sa.text(
            "SELECT id FROM verdicts WHERE structure_id = :s AND status != :status AND acquired_at <= :limit "
            "ORDER BY acquired_at DESC, id DESC LIMIT 1"
        ).bindparams(limit),
        {"s": structure_id, "status": status},
    ).scalar()
    first = (
        "SELECT min(acquired_at) FROM verdicts WHERE structure_id = :s"
        if other is None
        else "SELECT min(v.acquired_at) FROM verdicts v JOIN verdicts o ON o.id = :other "
        "WHERE v.structure_id = :s "
        "AND (v.acquired_at > o.acquired_at OR (v.acquired_at = o.acquired_at AND v.id > o.id))"
    )
    connection.execute(
        sa.text(
            "UPDATE structure_states SET status = :status, latest_verdict_id = :latest, "
            f"latest_acquired_at = (SELECT acquired_at FROM verdicts WHERE id = :latest), since = ({first}) "
            "WHERE structure_id = :s"
        ),
        {"s": structure_id, "status": status, "latest": verdict_id, "other": other},
    )


def downgrade() -> None:
    pass
