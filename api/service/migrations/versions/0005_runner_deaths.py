"""Runner deaths: how many runners a job lost (they stopped heartbeating while running it).

The reaper counts them and fails a job at ``GLINT_MAX_ATTEMPTS``; jobs that exist when
this runs have lost none that anyone counted.

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-29
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.add_column(
            sa.Column("runner_deaths", sa.Integer(), nullable=False, server_default="0")
        )


def downgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.drop_column("runner_deaths")
