"""Faults: infrastructure retries counted apart from a job's attempts, idempotency keys of submissions, and the
clock the reapers keep so that a lease that lapsed only during a database outage is not reaped at once.

Revision ID: 0005
Revises: 0004
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    """Add jobs.infra_retries, submissions.idempotency_key (unique per token) and the service_clock table."""
    with op.batch_alter_table("jobs") as batch:
        batch.add_column(sa.Column("infra_retries", sa.Integer, nullable=False, server_default="0"))
    with op.batch_alter_table("submissions") as batch:
        batch.add_column(sa.Column("idempotency_key", sa.String(200), nullable=True))
        batch.create_unique_constraint("uq_submissions_token_key", ["token_id", "idempotency_key"])
    op.create_table(
        "service_clock",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("last_contact", sa.Float, nullable=False),
        sa.Column("gap_start", sa.Float, nullable=False),
        sa.Column("resumed", sa.Float, nullable=False),
    )
    # its one row exists from the start, so that processes starting at once never race to insert it (the first
    # contact then finds a gap since 1970: leases that lapsed before it wait a lease's length, as after an outage)
    op.execute("INSERT INTO service_clock (id, last_contact, gap_start, resumed) VALUES (1, 0, 0, 0)")


def downgrade() -> None:
    """Drop them."""
    op.drop_table("service_clock")
    with op.batch_alter_table("submissions") as batch:
        batch.drop_constraint("uq_submissions_token_key", type_="unique")
        batch.drop_column("idempotency_key")
    with op.batch_alter_table("jobs") as batch:
        batch.drop_column("infra_retries")
