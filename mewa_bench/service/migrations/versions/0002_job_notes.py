"""Job notes: what the service did to a job on its way (a lease that expired and the job re-queued).

Revision ID: 0002
Revises: 0001
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    """Add jobs.note."""
    op.add_column("jobs", sa.Column("note", sa.Text, nullable=True))


def downgrade() -> None:
    """Drop jobs.note."""
    with op.batch_alter_table("jobs") as batch:
        batch.drop_column("note")
