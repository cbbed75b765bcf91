"""structures declare what their excitation and response measure, and in which units

Revision ID: 0025
Revises: 0024
Create Date: 2026-12-06 09:30:00.000000

Charts labelled every structure's response "y [m]" and its residual "e [m]", the units of the
simulated rig. A structure now declares the quantity and unit of x and of y
(``recordfiles.quantities``); the structures stored before declare none, and are drawn with
plain "x", "y" and "e" until they do. Downgrading drops the declarations.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0025"
down_revision = "0024"
branch_labels = None
depends_on = None

COLUMNS = ("excitation_quantity", "excitation_unit", "response_quantity", "response_unit")


def upgrade() -> None:
    with op.batch_alter_table("structures") as batch:
        for name in COLUMNS:
            batch.add_column(sa.Column(name, sa.String(16), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("structures") as batch:
        for name in reversed(COLUMNS):
            batch.drop_column(name)
