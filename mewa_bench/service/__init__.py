"""`mewa-bench serve`: the benchmark as a web service.

An ASGI app (FastAPI, served by uvicorn) over one database layer (SQLAlchemy + Alembic migrations;
SQLite in the data dir by default, PostgreSQL by URL), with:
- `settings`: data dir, database URL and every limit; `db`, `models`, `migrations/`: the schema;
- `tokens`, `limits`: API tokens (stored hashed), rate limits, quotas and upload sizes;
- `uploads`: schema checks and storage of results files, agent files and checkpoint archives;
- `jobs`: the job queue persisted in the database (states, leases, retries);
- `worker`, `scoring`, `evaluation`: worker processes re-scoring results files and evaluating agents
  (in the sandbox of `sandbox`, on public suites and on the hidden suites of `hidden`);
- `boards`: leaderboards; `routes/`: the HTTP API; `web/`: the HTML pages; `app`, `server`: the app
  factory and the process that runs the API and its workers; `client`: `submit`, `status`, downloads;
- `storage`, `outages`: what a full disk (507) and a database outage (503, workers waiting it out) are
  answered with; `readiness`, `metrics`: `/api/ready` and the Prometheus metrics at `/metrics`.

Imported only by the CLI; FastAPI, SQLAlchemy and uvicorn are imported inside these modules, which the
CLI imports lazily (the `service` extra).
"""
