"""one active version per name (partial unique index); key expiry and last use

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-23 16:40:00.000000

A database may already hold two active versions of one name (concurrent activations could
leave them before this index): of each such name only the newest version stays active, as the
inspections had no way to choose between them anyway.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None

ACTIVE = sa.text("active")


def upgrade() -> None:
    versions = sa.table(
        "model_versions",
        sa.column("structure_id", sa.Integer),
        sa.column("name", sa.String),
        sa.column("version", sa.Integer),
        sa.column("active", sa.Boolean),
    )
    newer = versions.alias("newer")
    op.execute(
        versions.update()
        .where(
            versions.c.active.is_(True),
            sa.exists().where(
                newer.c.structure_id == versions.c.structure_id,
                newer.c.name == versions.c.name,
                newer.c.active.is_(True),
                newer.c.version > versions.c.version,
            ),
        )
        .values(active=False)
    )
    op.create_index(
        "uq_model_versions_active",
        "model_versions",
        ["structure_id", "name"],
        unique=True,
        sqlite_where=ACTIVE,
        postgresql_where=ACTIVE,
    )
    with op.batch_alter_table("api_keys", schema=None) as batch_op:
        batch_op.add_column(sa.Column("expires_at", sa.DateTime(timezone=True), nullable=True))
        batch_op.add_column(sa.Column("last_used_at", sa.DateTime(timezone=True), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("api_keys", schema=None) as batch_op:
        batch_op.drop_column("last_used_at")
        batch_op.drop_column("expires_at")
    op.drop_index("uq_model_versions_active", table_name="model_versions")
