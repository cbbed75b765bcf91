"""alarm rules per structure, alarms and their transitions

Revision ID: 0009
Revises: 0008
Create Date: 2026-11-23 22:40:00.000000

At most one alarm per structure, rule kind and fault mode is unresolved: two partial unique
indexes say so (a persistence alarm has no fault mode, and a unique index treats NULLs as
distinct). Structures stored before this revision have no rule: they are watched by the defaults.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision = "0009"
down_revision = "0008"
branch_labels = None
depends_on = None

UNRESOLVED = sa.text("state != 'resolved'")
UNRESOLVED_WITHOUT_MODE = sa.text("state != 'resolved' AND fault_mode IS NULL")
JSON = sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql")


def upgrade() -> None:
    op.create_table(
        "alarm_rules",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("structure_id", sa.Integer(), nullable=False),
        sa.Column("kind", sa.String(length=16), nullable=False),
        sa.Column("parameters", JSON, nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["structure_id"], ["structures.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("structure_id", "kind"),
    )
    with op.batch_alter_table("alarm_rules", schema=None) as batch_op:
        batch_op.create_index("ix_alarm_rules_structure_id", ["structure_id"], unique=False)
    op.create_table(
        "alarms",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("structure_id", sa.Integer(), nullable=False),
        sa.Column("rule_kind", sa.String(length=16), nullable=False),
        sa.Column("rule", JSON, nullable=False),
        sa.Column("fault_mode", sa.String(length=100), nullable=True),
        sa.Column("state", sa.String(length=16), nullable=False),
        sa.Column("opened_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("record_id", sa.Integer(), nullable=True),
        sa.Column("triggered_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("drift_started_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("evaluated_through", sa.DateTime(timezone=True), nullable=False),
        sa.Column("acknowledged_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("acknowledged_by", sa.Integer(), nullable=True),
        sa.Column("acknowledgement_note", sa.Text(), nullable=True),
        sa.Column("resolved_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("resolved_by", sa.Integer(), nullable=True),
        sa.Column("resolution", sa.String(length=16), nullable=True),
        sa.Column("resolution_note", sa.Text(), nullable=True),
        sa.ForeignKeyConstraint(["structure_id"], ["structures.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["record_id"], ["records.id"], ondelete="SET NULL"),
        sa.ForeignKeyConstraint(["acknowledged_by"], ["api_keys.id"], ondelete="SET NULL"),
        sa.ForeignKeyConstraint(["resolved_by"], ["api_keys.id"], ondelete="SET NULL"),
        sa.PrimaryKeyConstraint("id"),
    )
    op.create_index("ix_alarms_listing", "alarms", ["structure_id", "opened_at", "id"], unique=False)
    op.create_index(
        "uq_alarms_unresolved",
        "alarms",
        ["structure_id", "rule_kind", "fault_mode"],
        unique=True,
        sqlite_where=UNRESOLVED,
        postgresql_where=UNRESOLVED,
    )
    op.create_index(
        "uq_alarms_unresolved_without_mode",
        "alarms",
        ["structure_id", "rule_kind"],
        unique=True,
        sqlite_where=UNRESOLVED_WITHOUT_MODE,
        postgresql_where=UNRESOLVED_WITHOUT_MODE,
    )
    op.create_table(
        "alarm_transitions",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("alarm_id", sa.Integer(), nullable=False),
        sa.Column("from_state", sa.String(length=16), nullable=True),
        sa.Column("to_state", sa.String(length=16), nullable=False),
        sa.Column("at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("key_id", sa.Integer(), nullable=True),
        sa.Column("note", sa.Text(), nullable=True),
        sa.ForeignKeyConstraint(["alarm_id"], ["alarms.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["key_id"], ["api_keys.id"], ondelete="SET NULL"),
        sa.PrimaryKeyConstraint("id"),
    )
    op.create_index("ix_alarm_transitions_alarm_id", "alarm_transitions", ["alarm_id"], unique=False)


def downgrade() -> None:
    op.drop_index("ix_alarm_transitions_alarm_id", table_name="alarm_transitions")
    op.drop_table("alarm_transitions")
    op.drop_index("uq_alarms_unresolved_without_mode", table_name="alarms")
    op.drop_index("uq_alarms_unresolved", table_name="alarms")
    op.drop_index("ix_alarms_listing", table_name="alarms")
    op.drop_table("alarms")
    with op.batch_alter_table("alarm_rules", schema=None) as batch_op:
        batch_op.drop_index("ix_alarm_rules_structure_id")
    op.drop_table("alarm_rules")
