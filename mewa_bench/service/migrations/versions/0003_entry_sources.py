"""Board entries say what was verified (their source) and which run they are (one row per run and board).

Revision ID: 0003
Revises: 0002
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    """Add entries.source (filled from the submission's kind) and entries.run_digest, unique per board."""
    with op.batch_alter_table("entries") as batch:
        batch.add_column(sa.Column("source", sa.String(20), nullable=False, server_default="server-evaluated"))
        batch.add_column(sa.Column("run_digest", sa.String(64), nullable=True))
        batch.create_unique_constraint("uq_entries_board_run", ["board", "run_digest"])
    op.execute("UPDATE entries SET source = 'self-reported' WHERE submission_id IN "
               "(SELECT id FROM submissions WHERE kind = 'results')")


def downgrade() -> None:
    """Drop them."""
    with op.batch_alter_table("entries") as batch:
        batch.drop_constraint("uq_entries_board_run", type_="unique")
        batch.drop_column("run_digest")
        batch.drop_column("source")
