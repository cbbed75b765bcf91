"""the operating conditions of records

Revision ID: 0011
Revises: 0010
Create Date: 2026-11-25 21:50:00.000000

A record may state the conditions it was acquired under (temperature, excitation level, speed;
``recordfiles.conditions``). They are rows of a child table, one per record and name, rather than a
JSON column of the record: a structure's records are to be selected and ordered by a condition's
value (k̂ against temperature, the records of a model's training range), which the index on
(structure_id, name, value) answers in both databases, where a JSON document would be read
whole for every record or need an expression index of each dialect's own. The structure is
repeated from the record for that index. Records stored before this revision have no conditions.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0011"
down_revision = "0010"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "record_conditions",
        sa.Column("record_id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=32), nullable=False),
        sa.Column("structure_id", sa.Integer(), nullable=False),
        sa.Column("value", sa.Float(), nullable=False),
        sa.Column("unit", sa.String(length=16), nullable=True),
        sa.ForeignKeyConstraint(["record_id"], ["records.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["structure_id"], ["structures.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("record_id", "name"),
    )
    op.create_index("ix_record_conditions_value", "record_conditions", ["structure_id", "name", "value"])


def downgrade() -> None:
    op.drop_index("ix_record_conditions_value", table_name="record_conditions")
    op.drop_table("record_conditions")
