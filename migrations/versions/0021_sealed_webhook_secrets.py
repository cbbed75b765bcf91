"""webhooks' signing secrets sealed at rest

Revision ID: 0021
Revises: 0020
Create Date: 2026-11-29 00:30:00.000000

A webhook's secret was stored as given, so a copy of the database let anyone sign events its
organisation's systems act on. It is now stored sealed under the server's keys
(``service.sealing``: NARXWATCH_SECRET_KEYS, or the key file), read from the environment this
revision runs in; the column grows to hold the seal (356 characters for a secret of 200).
Downgrading unseals them, with the same keys.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0021"
down_revision = "0020"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("webhooks") as batch:
        batch.alter_column("secret", existing_type=sa.String(200), type_=sa.String(400))
    _rewrite_secrets(sealed=True)


def downgrade() -> None:
    _rewrite_secrets(sealed=False)
    with op.batch_alter_table("webhooks") as batch:
        batch.alter_column("secret", existing_type=sa.String(400), type_=sa.String(200))


def _rewrite_secrets(sealed: bool) -> None:
    # Imported here: every command but serve loads the revisions to check the schema.
    from service import sealing
    from service.config import Settings

    settings = Settings()
    bind = op.get_bind()
    change = sealing.seal if sealed else sealing.unseal
    for webhook_id, secret in bind.execute(sa.text("SELECT id, secret FROM webhooks")).all():
        bind.execute(
            sa.text("UPDATE webhooks SET secret = :secret WHERE id = :id"),
            {"secret": change(secret, settings), "id": webhook_id},
        )
