"""records of one response: their channels SQL NULL, not JSON's null

Revision ID: 0017
Revises: 0016
Create Date: 2026-11-26 15:00:00.000000

Until this revision a record of one response was stored with ``channels`` holding JSON's null
(the JSON type's default for None), so that ``channels IS NULL`` found none of them, and the
downgrade of 0015 counted every record as one of several channels and refused. The column now
stores None as SQL NULL (``service.tables.OptionalDocument``); the records stored before are
brought in line. Downgrading leaves them NULL, which reads as None all the same.
"""

from __future__ import annotations

from alembic import op

revision = "0017"
down_revision = "0016"
branch_labels = None
depends_on = None


def upgrade() -> None:
    # A JSON null is the text 'null' in SQLite and the jsonb value null in PostgreSQL; the literal
    # compares as either (and as nothing with SQL NULL).
    op.execute("UPDATE records SET channels = NULL WHERE channels = 'null'")


def downgrade() -> None:
    pass
