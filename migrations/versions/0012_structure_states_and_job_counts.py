"""each structure's state, kept on write; the jobs that ended, counted

Revision ID: 0012
Revises: 0011
Create Date: 2026-11-25 22:00:00.000000

``structure_states`` holds, per structure, its latest verdict, since when its status holds, and
how many records and verdicts of each status it has; ``job_counts`` how many embedded jobs
ended done and failed. Both are written in the transaction of each change from now on
(``service.domain.fleet``, ``service.jobs.embedded``) and filled here from the rows already stored.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0012"
down_revision = "0011"
branch_labels = None
depends_on = None

STATUSES = ("healthy", "faulty", "unknown_fault")


def upgrade() -> None:
    op.create_table(
        "structure_states",
        sa.Column("structure_id", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("organisation_id", sa.Integer(), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=True),
        sa.Column("since", sa.DateTime(timezone=True), nullable=True),
        sa.Column("latest_verdict_id", sa.Integer(), nullable=True),
        sa.Column("latest_acquired_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("records", sa.BigInteger(), nullable=False),
        sa.Column("healthy", sa.BigInteger(), nullable=False),
        sa.Column("faulty", sa.BigInteger(), nullable=False),
        sa.Column("unknown_fault", sa.BigInteger(), nullable=False),
        sa.ForeignKeyConstraint(["latest_verdict_id"], ["verdicts.id"], ondelete="SET NULL"),
        sa.ForeignKeyConstraint(["organisation_id"], ["organisations.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["structure_id"], ["structures.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("structure_id"),
    )
    op.create_index("ix_structure_states_fleet", "structure_states", ["organisation_id", "structure_id"])
    op.create_index(
        "ix_structure_states_fleet_status", "structure_states", ["organisation_id", "status", "structure_id"]
    )
    op.create_table(
        "job_counts",
        sa.Column("state", sa.String(length=16), nullable=False),
        sa.Column("count", sa.BigInteger(), nullable=False),
        sa.PrimaryKeyConstraint("state"),
    )
    _fill_structure_states()
    for state in ("done", "failed"):
        op.execute(
            sa.text(
                "INSERT INTO job_counts (state, count) "
                "SELECT :state, count(*) FROM jobs WHERE status = :state"
            ).bindparams(state=state)
        )


def _fill_structure_states() -> None:
    counts = ", ".join(
        f"(SELECT count(*) FROM verdicts v WHERE v.structure_id = s.id AND v.status = '{status}')"
        for status in STATUSES
    )
    op.execute(
        "INSERT INTO structure_states "
        "(structure_id, organisation_id, records, healthy, faulty, unknown_fault) "
        "SELECT s.id, s.organisation_id, "
        f"(SELECT count(*) FROM records r WHERE r.structure_id = s.id), {counts} FROM structures s"
    )
    op.execute(
        "UPDATE structure_states SET latest_verdict_id = (SELECT v.id FROM verdicts v "
        "WHERE v.structure_id = structure_states.structure_id ORDER BY v.acquired_at DESC, v.id DESC LIMIT 1)"
    )
    op.execute(
        "UPDATE structure_states SET "
        "status = (SELECT v.status FROM verdicts v WHERE v.id = structure_states.latest_verdict_id), "
        "latest_acquired_at = "
        "(SELECT v.acquired_at FROM verdicts v WHERE v.id = structure_states.latest_verdict_id)"
    )
    # Since when: the first verdict after the last one of another status, found per structure with
    # two reads of its history index (one correlated statement would compare each verdict of a
    # run with every later one).
    connection = op.get_bind()
    standing = connection.execute(
        sa.text("SELECT structure_id, status FROM structure_states WHERE status IS NOT NULL")
    ).all()
    for structure_id, status in standing:
        other = connection.execute(
            sa.text(
                "SELECT acquired_at, id FROM verdicts WHERE structure_id = :s AND status != :status "
                "ORDER BY acquired_at DESC, id DESC LIMIT 1"
            ),
            {"s": structure_id, "status": status},
        ).first()
        after = "" if other is None else "AND (acquired_at > :at OR (acquired_at = :at AND id > :id))"
        bounds = {} if other is None else {"at": other[0], "id": other[1]}
        connection.execute(
            sa.text(
                "UPDATE structure_states SET since = (SELECT min(acquired_at) FROM verdicts "
                f"WHERE structure_id = :s {after}) WHERE structure_id = :s"
            ),
            {"s": structure_id, **bounds},
        )


def downgrade() -> None:
    op.drop_table("job_counts")
    op.drop_index("ix_structure_states_fleet_status", table_name="structure_states")
    op.drop_index("ix_structure_states_fleet", table_name="structure_states")
    op.drop_table("structure_states")
