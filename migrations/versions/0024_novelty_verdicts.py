"""verdicts of a healthy baseline alone: healthy or anomaly

Revision ID: 0024
Revises: 0023
Create Date: 2026-12-06 09:30:00.000000

A structure with a healthy baseline and no fault-mode model has its records judged against the
baseline's free-run error (``models.novelty``): ``healthy`` or ``anomaly``. Such a verdict keeps
its figures in ``verdicts.novelty`` (null for every other verdict) and has no Ljung–Box test, so
no ``lags``; ``structure_states.anomaly`` counts a structure's anomalies, 0 for every structure
judged before. Downgrading is refused while such verdicts are stored, since the schema before this
revision cannot hold them: deleting them here would leave their alarms and counts behind.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects.postgresql import JSONB

revision = "0024"
down_revision = "0023"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column(
        "verdicts", sa.Column("novelty", sa.JSON().with_variant(JSONB(), "postgresql"), nullable=True)
    )
    with op.batch_alter_table("verdicts", schema=None) as batch_op:
        batch_op.alter_column("lags", existing_type=sa.Integer(), nullable=True)
    op.add_column(
        "structure_states", sa.Column("anomaly", sa.BigInteger(), nullable=False, server_default="0")
    )


def downgrade() -> None:
    # Neither SQL NULL nor JSON's null compares as different from 'null'.
    judged = op.get_bind().execute(sa.text("SELECT COUNT(*) FROM verdicts WHERE novelty <> 'null'")).scalar()
    if judged:
        raise RuntimeError(
            f"{judged} verdict(s) of a healthy baseline alone are stored, which the schema before revision "
            "0024 cannot hold: delete them (and their structures' alarms) before downgrading"
        )
    with op.batch_alter_table("structure_states") as batch:
        batch.drop_column("anomaly")
    with op.batch_alter_table("verdicts", schema=None) as batch_op:
        batch_op.alter_column("lags", existing_type=sa.Integer(), nullable=False)
        batch_op.drop_column("novelty")
