"""a refinement may start from no baseline: the linear orders the loop chooses

Revision ID: 0020
Revises: 0019
Create Date: 2026-11-27 02:50:00.000000

``POST /structures/{id}/refinements`` without ``base_model_id`` refines from the linear model whose
orders simulate best (issue 14, deliverable 5, as ``narxwatch refine`` without ``--declared``):
``refinements.base_model_id`` becomes nullable. Downgrading is refused while such refinements are
stored, since the schema before this revision cannot hold them.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0020"
down_revision = "0019"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("refinements") as batch:
        batch.alter_column("base_model_id", existing_type=sa.Integer(), nullable=True)


def downgrade() -> None:
    without = (
        op.get_bind()
        .execute(sa.text("SELECT COUNT(*) FROM refinements WHERE base_model_id IS NULL"))
        .scalar()
    )
    if without:
        raise RuntimeError(
            f"{without} refinement(s) without a base model are stored, which the schema before revision "
            "0020 cannot hold: delete them before downgrading"
        )
    with op.batch_alter_table("refinements") as batch:
        batch.alter_column("base_model_id", existing_type=sa.Integer(), nullable=False)
