"""Errors the API answers with: an HTTP status and a JSON body `{"error": code, "detail": message}`.

Every 4xx says what was wrong and where (the field, the unit, the limit), never just "bad request".
"""

from __future__ import annotations


class ApiError(Exception):
    """An error answer; `headers` (e.g. Retry-After) go with it."""

    def __init__(self, status: int, code: str, detail: str, headers: dict[str, str] | None = None) -> None:
        super().__init__(detail)
        self.status, self.code, self.detail, self.headers = status, code, detail, headers or {}

    def body(self) -> dict[str, str]:
        """The JSON body."""
        return {"error": self.code, "detail": self.detail}


def bad_request(code: str, detail: str) -> ApiError:
    """400: the request itself is malformed (not JSON, a missing form field)."""
    return ApiError(400, code, detail)


def unprocessable(code: str, detail: str) -> ApiError:
    """422: well-formed, but its content does not pass the checks."""
    return ApiError(422, code, detail)


def not_found(what: str) -> ApiError:
    """404 naming what does not exist."""
    return ApiError(404, "not_found", f"{what} does not exist")
