"""verdicts of a pooled baseline alone

Revision ID: 0013
Revises: 0012
Create Date: 2026-11-25 23:00:00.000000

A structure monitored by a pooled baseline and no fault-mode model has verdicts from the
baseline's residual-variance and whiteness tests at each record's conditions; they have no
magnitude test, so no critical |k̂|/σ̂_k. Downgrading deletes those verdicts: the schema before
this revision cannot hold them.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0013"
down_revision = "0012"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("verdicts", schema=None) as batch_op:
        batch_op.alter_column("z_critical", existing_type=sa.Float(), nullable=True)


def downgrade() -> None:
    op.execute("DELETE FROM verdicts WHERE z_critical IS NULL")
    with op.batch_alter_table("verdicts", schema=None) as batch_op:
        batch_op.alter_column("z_critical", existing_type=sa.Float(), nullable=False)
