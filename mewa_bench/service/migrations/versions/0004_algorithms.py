"""Runs know their algorithm: a submission may name it, and a board entry keeps its per-pair curves, so the
boards can show statistics over an algorithm's runs.

Revision ID: 0004
Revises: 0003
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    """Add submissions.algorithm, entries.algorithm and entries.pair_curves (entries made before have none)."""
    with op.batch_alter_table("submissions") as batch:
        batch.add_column(sa.Column("algorithm", sa.String(100), nullable=True))
    with op.batch_alter_table("entries") as batch:
        batch.add_column(sa.Column("algorithm", sa.String(100), nullable=True))
        batch.add_column(sa.Column("pair_curves", sa.Text, nullable=True))


def downgrade() -> None:
    """Drop them."""
    with op.batch_alter_table("entries") as batch:
        batch.drop_column("pair_curves")
        batch.drop_column("algorithm")
    with op.batch_alter_table("submissions") as batch:
        batch.drop_column("algorithm")
