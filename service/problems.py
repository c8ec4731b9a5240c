"""Errors as RFC 9457 ``application/problem+json``, one handler per kind of failure."""

from __future__ import annotations

import logging
from http import HTTPStatus

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import ValidationError
from starlette.exceptions import HTTPException

from service.store import RegionExists, RegionNotFound, StoreError, UploadConflict

PROBLEM = "application/problem+json"
log = logging.getLogger("bdf.service")


class Problem(Exception):
    """An error with its HTTP status, raised anywhere below a route."""

    def __init__(self, status: int, detail: str, headers: dict | None = None):
        super().__init__(detail)
        self.status, self.detail, self.headers = status, detail, headers


def problem(status: int, detail, instance: str = "", headers: dict | None = None) -> JSONResponse:
    title = HTTPStatus(status).phrase
    body = {"type": "about:blank", "title": title, "status": status, "detail": detail}
    if instance:
        body["instance"] = instance
    return JSONResponse(body, status_code=status, media_type=PROBLEM, headers=headers)


def install(app: FastAPI) -> None:
    def on(exc_type):
        """Register ``fn(exc) -> (status, detail, headers)`` as the handler of ``exc_type``."""

        def decorator(fn):
            async def handler(request: Request, exc):
                code, detail, headers = fn(exc)
                return problem(code, detail, request.url.path, headers)

            app.add_exception_handler(exc_type, handler)
            return fn

        return decorator

    on(Problem)(lambda e: (e.status, e.detail, e.headers))
    on(HTTPException)(lambda e: (e.status_code, e.detail, getattr(e, "headers", None)))
    on(RequestValidationError)(lambda e: (422, _describe(e.errors()), None))
    on(ValidationError)(lambda e: (422, _describe(e.errors()), None))
    for exc_type, status in (
        (ValueError, 422),
        (RegionNotFound, 404),
        (RegionExists, 409),
        (UploadConflict, 409),
    ):
        on(exc_type)(lambda e, status=status: (status, str(e), None))

    @on(StoreError)
    def _store(exc):
        log.error("store error: %s", exc)
        return 503, f"the map store failed: {exc}", None

    @on(Exception)
    def _internal(exc):
        log.exception("unhandled error")
        return 500, "internal error (logged on the server)", None


def _describe(errors) -> str:
    parts = []
    for err in errors:
        where = ".".join(str(p) for p in err.get("loc", ()) if p != "body")
        parts.append(f"{where}: {err['msg']}" if where else err["msg"])
    return "; ".join(parts)
