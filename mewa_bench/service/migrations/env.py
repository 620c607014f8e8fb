"""Alembic's entry point for the service schema: runs the migrations on the connection `db.migrate` passes.

Batch mode (`render_as_batch`) lets later migrations alter tables on SQLite too, so one set of
migrations serves both databases.
"""

from __future__ import annotations

from alembic import context

from mewa_bench.service.models import Base

connection = context.config.attributes.get("connection")
if connection is None:
    raise RuntimeError("run the service migrations through mewa_bench.service.db.migrate (it passes the connection)")
context.configure(connection=connection, target_metadata=Base.metadata, render_as_batch=True)
with context.begin_transaction():
    context.run_migrations()
