"""The service's web pages, server-rendered (plain HTML and a little CSS, no JavaScript).

- `/`: every board (public and hidden) and the latest submissions with their status;
- `/leaderboards/<board>`: one board's ranked table (the static leaderboard's columns) and its
  adaptation-curve figure, `/leaderboards/<board>/curves.png` (drawn by `leaderboard.plot`);
- `/submissions/<id>`: a submission's status, each job's progress and the reason of a rejection,
  reloading itself every few seconds until the submission is done, rejected or failed.

The pages read what the JSON API serves (`service.boards`, `routes.submissions.describe`); the app
includes `router` beside the API's routers. Imported only by the app factory (FastAPI at import).
"""

from mewa_bench.service.web.routes import router

__all__ = ["router"]
