"""retention: per-organisation policies, records whose signals were pruned

Revision ID: 0014
Revises: 0013
Create Date: 2026-11-25 23:00:00.000000

``retention_policies`` holds how long an organisation keeps its records' signals and its
verdicts (``service.domain.retention``); organisations without a row keep the defaults. A record
whose signals were pruned keeps its row, with ``signals_pruned_at`` set and empty blobs, for its
verdicts. The signal pass reads records through ``ix_records_signals_kept``, partial on the
records still holding their signals, so each run reads only those newly past the horizon.
Nothing stored before this revision is pruned by it.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0014"
down_revision = "0013"
branch_labels = None
depends_on = None

SIGNALS_KEPT = sa.text("signals_pruned_at IS NULL")


def upgrade() -> None:
    op.add_column("records", sa.Column("signals_pruned_at", sa.DateTime(timezone=True), nullable=True))
    op.create_index(
        "ix_records_signals_kept",
        "records",
        ["structure_id", "acquired_at"],
        sqlite_where=SIGNALS_KEPT,
        postgresql_where=SIGNALS_KEPT,
    )
    op.create_table(
        "retention_policies",
        sa.Column("organisation_id", sa.Integer(), nullable=False),
        sa.Column("signal_days", sa.Integer(), nullable=True),
        sa.Column("verdict_days", sa.Integer(), nullable=True),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("last_pruned_at", sa.DateTime(timezone=True), nullable=True),
        sa.ForeignKeyConstraint(["organisation_id"], ["organisations.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("organisation_id"),
    )


def downgrade() -> None:
    op.drop_table("retention_policies")
    op.drop_index("ix_records_signals_kept", table_name="records")
    with op.batch_alter_table("records") as batch:
        batch.drop_column("signals_pruned_at")
