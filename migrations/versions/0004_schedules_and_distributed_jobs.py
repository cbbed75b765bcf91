"""schedules, jobs with task arguments, and Procrastinate's schema on PostgreSQL

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-21 16:05:00.000000

The distributed job backend (PostgreSQL) runs on Procrastinate, whose tables, functions and
triggers are created here from the SQL the pinned Procrastinate release ships, so that one
``narxwatch db upgrade`` prepares everything. A later Procrastinate release brings its own
migration scripts (``procrastinate.schema.SchemaManager.get_migrations_path()``), to be applied
by a revision of ours when the pin moves.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None

Document = sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql")

# Procrastinate declares no "drop" script: every object it creates is named procrastinate_*.
DROP_PROCRASTINATE = """
DO $$
DECLARE item record;
BEGIN
    FOR item IN SELECT event_object_table AS t, trigger_name AS name
                FROM information_schema.triggers WHERE trigger_name LIKE 'procrastinate%' LOOP
        EXECUTE format('DROP TRIGGER IF EXISTS %I ON %I', item.name, item.t);
    END LOOP;
    FOR item IN SELECT tablename AS name FROM pg_tables
                WHERE schemaname = current_schema() AND tablename LIKE 'procrastinate%' LOOP
        EXECUTE format('DROP TABLE IF EXISTS %I CASCADE', item.name);
    END LOOP;
    FOR item IN SELECT p.oid::regprocedure AS name FROM pg_proc p
                JOIN pg_namespace n ON n.oid = p.pronamespace
                WHERE n.nspname = current_schema() AND p.proname LIKE 'procrastinate%' LOOP
        EXECUTE format('DROP FUNCTION IF EXISTS %s CASCADE', item.name);
    END LOOP;
    FOR item IN SELECT t.typname AS name FROM pg_type t
                JOIN pg_namespace n ON n.oid = t.typnamespace
                WHERE n.nspname = current_schema() AND t.typname LIKE 'procrastinate%'
                  AND t.typtype IN ('e', 'c') LOOP
        EXECUTE format('DROP TYPE IF EXISTS %I CASCADE', item.name);
    END LOOP;
END $$;
"""


def upgrade() -> None:
    op.create_table(
        "schedules",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("structure_id", sa.Integer(), nullable=False),
        sa.Column("action", sa.String(length=32), nullable=False),
        sa.Column("interval_seconds", sa.Integer(), nullable=True),
        sa.Column("cron", sa.String(length=100), nullable=True),
        sa.Column("next_run_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("last_run_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["structure_id"], ["structures.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
    )
    with op.batch_alter_table("schedules", schema=None) as batch_op:
        batch_op.create_index("ix_schedules_next_run_at", ["next_run_at"], unique=False)
        batch_op.create_index("ix_schedules_structure_id", ["structure_id"], unique=False)

    # A job now names its task's keyword arguments instead of a record: schedules run as jobs too.
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.add_column(sa.Column("args", Document, nullable=True))
    jobs = sa.table("jobs", sa.column("record_id", sa.Integer()), sa.column("args", Document))
    build = sa.func.json_object if op.get_bind().dialect.name == "sqlite" else sa.func.jsonb_build_object
    op.execute(jobs.update().values(args=build("record_id", jobs.c.record_id)))
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.alter_column("args", existing_type=Document, nullable=False)
        batch_op.drop_column("record_id")

    if op.get_bind().dialect.name == "postgresql":
        # Imported here: every command loads the revision scripts to check the schema's revision,
        # and Procrastinate took a quarter of a second of `narxwatch keys list`.
        from procrastinate.schema import SchemaManager

        # The driver's own execute: the script holds many statements and literal '%' signs.
        op.get_bind().connection.driver_connection.execute(SchemaManager.get_schema())


def downgrade() -> None:
    if op.get_bind().dialect.name == "postgresql":
        op.get_bind().connection.driver_connection.execute(DROP_PROCRASTINATE)
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.add_column(sa.Column("record_id", sa.Integer(), nullable=True))
    op.execute("DELETE FROM jobs WHERE task <> 'inspect_record'")
    jobs = sa.table("jobs", sa.column("record_id", sa.Integer()), sa.column("args", Document))
    record = (
        sa.func.json_extract(jobs.c.args, "$.record_id")
        if op.get_bind().dialect.name == "sqlite"
        else jobs.c.args["record_id"].astext.cast(sa.Integer)
    )
    op.execute(jobs.update().values(record_id=record))
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.alter_column("record_id", existing_type=sa.Integer(), nullable=False)
        batch_op.create_foreign_key(
            "jobs_record_id_fkey", "records", ["record_id"], ["id"], ondelete="CASCADE"
        )
        batch_op.drop_column("args")
    with op.batch_alter_table("schedules", schema=None) as batch_op:
        batch_op.drop_index("ix_schedules_structure_id")
        batch_op.drop_index("ix_schedules_next_run_at")
    op.drop_table("schedules")
