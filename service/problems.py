"""Errors as RFC 9457 ``application/problem+json``, one handler per kind of failure."""

from __future__ import annotations

import itertools
import logging
import os
import re
import secrets
from http import HTTPStatus

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ValidationError
from starlette.exceptions import HTTPException
from starlette.requests import ClientDisconnect

from service.lanes import DeadlineExceeded, Overloaded
from service.maps import Unprocessable
from service.store import (
    RegionChanged,
    RegionExists,
    RegionNotFound,
    StoreError,
    StoreFull,
    StoreUnavailable,
    UploadConflict,
    UploadNotFound,
)
from service.wire import REQUEST_ID_HEADER

PROBLEM = "application/problem+json"
log = logging.getLogger("bdf.service")


class ProblemBody(BaseModel):
    """An error as RFC 9457 problem details, with the request id of the server's log line."""

    type: str
    title: str
    status: int
    detail: str
    instance: str
    request_id: str


#: how errors are documented on every route (OpenAPI ``responses``)
ERRORS = {
    status: {
        "description": HTTPStatus(status).phrase,
        "content": {PROBLEM: {"schema": ProblemBody.model_json_schema()}},
    }
    for status in (400, 401, 403, 404, 406, 409, 413, 415, 422, 500, 503, 507)
}


class Problem(Exception):
    """An error with its HTTP status, raised anywhere below a route."""

    def __init__(self, status: int, detail: str, headers: dict | None = None):
        super().__init__(detail)
        self.status, self.detail, self.headers = status, detail, headers


def problem(status: int, detail, scope, headers: dict | None = None) -> JSONResponse:
    """The problem response to the request of ASGI ``scope``: its path is the instance, and
    its request id (:mod:`service.telemetry`) is in the body and the headers, so a report
    of any error can be matched to the server's log line."""
    title = HTTPStatus(status).phrase
    request_id = request_id_of(scope)
    body = {
        "type": "about:blank",
        "title": title,
        "status": status,
        "detail": detail,
        "instance": scope["path"],
        "request_id": request_id,
    }
    headers = {**(headers or {}), REQUEST_ID_HEADER: request_id}
    return JSONResponse(body, status_code=status, media_type=PROBLEM, headers=headers)


def request_id_of(scope) -> str:
    """The id :class:`service.telemetry.RequestMiddleware` gave the request (one is made
    here for a request that never reached it)."""
    state = scope.setdefault("state", {})
    if "request_id" not in state:
        state["request_id"] = new_request_id()
    return state["request_id"]


class _RequestIds:
    """Unique request ids without a system call each: a random prefix per process (new in
    a forked child) and a counter; 32 hex digits, like a UUID."""

    def __init__(self):
        self.reset()
        os.register_at_fork(after_in_child=self.reset)

    def reset(self) -> None:
        self.prefix, self.counter = secrets.token_hex(8), itertools.count()

    def __call__(self) -> str:
        return f"{self.prefix}{next(self.counter):016x}"


new_request_id = _RequestIds()


def install(app: FastAPI, patterns: dict[str, str] | None = None) -> None:
    """The handlers; ``patterns``: what each parameter pattern means, said in its 422
    instead of the regular expression."""
    patterns = patterns or {}

    def on(exc_type):
        """Register ``fn(exc) -> (status, detail, headers)`` as the handler of ``exc_type``."""

        def decorator(fn):
            async def handler(request: Request, exc):
                code, detail, headers = fn(exc)
                return problem(code, detail, request.scope, headers)

            app.add_exception_handler(exc_type, handler)
            return fn

        return decorator

    on(Problem)(lambda e: (e.status, e.detail, e.headers))

    async def http_error(request: Request, exc: HTTPException):
        headers = dict(getattr(exc, "headers", None) or {})
        if exc.status_code == 405:  # every method of the path, not only its first route's
            headers["Allow"] = ", ".join(_allowed(request))
        return problem(exc.status_code, exc.detail, request.scope, headers)

    app.add_exception_handler(HTTPException, http_error)
    on(RequestValidationError)(lambda e: (422, _describe(e.errors(), patterns), None))
    on(ValidationError)(lambda e: (422, _describe(e.errors(), patterns), None))
    for exc_type, fn in _ANSWERS.items():
        on(exc_type)(fn)
    # any other error is ours: service.telemetry.RequestMiddleware answers it (500), once


def _gone(exc):
    # the client's fault, and no one reads the answer: a log line, not a traceback
    log.info("the client closed the connection before its request arrived")
    return 400, "the client closed the connection before the request body arrived", None


def _unavailable(exc):
    # the log names the database; the client learns what to do, not where it lives
    log.warning("store unavailable: %s", exc)
    if isinstance(exc, StoreFull):
        detail = "the map store is out of disk space: nothing was stored; retry once an operator freed some"
        return 507, detail, {"Retry-After": str(exc.retry_after_s)}
    detail = f"the map store cannot be reached right now: nothing was stored; retry in {exc.retry_after_s} s"
    return 503, detail, {"Retry-After": str(exc.retry_after_s)}


def _store(exc):
    log.error("store error: %s", exc)
    return 500, f"the map store failed: {exc}", None  # ours (a damaged tile, named), never a driver's


#: the answer to each kind of failure that is not ours or is the store's: exception type ->
#: ``fn(exc) -> (status, detail, headers)`` (any other error is ours: a 500 without details)
_ANSWERS = {
    # the client's: a ValueError anywhere else is ours
    **{
        exc_type: (lambda e, status=status: (status, str(e), None))
        for exc_type, status in (
            (Unprocessable, 422),
            (RegionNotFound, 404),
            (UploadNotFound, 404),
            (RegionExists, 409),
            (RegionChanged, 409),
            (UploadConflict, 409),
        )
    },
    ClientDisconnect: _gone,
    StoreUnavailable: _unavailable,
    StoreError: _store,
    Overloaded: lambda e: (503, str(e), {"Retry-After": str(e.retry_after_s)}),
    DeadlineExceeded: lambda e: (503, str(e), {"Retry-After": str(DEADLINE_RETRY_S), "Connection": "close"}),
}


def public_detail(exc: Exception) -> str:
    """What a client may read of ``exc`` where no HTTP answer carries it (a job's error):
    the detail its answer would have, never a driver's message; ours: no detail."""
    for exc_type in type(exc).__mro__:
        if exc_type in _ANSWERS:
            return _ANSWERS[exc_type](exc)[1]
    if isinstance(exc, Problem):
        return exc.detail
    return "internal error (logged on the server)"


#: what a client whose request ran out of time is told to wait before retrying (s)
DEADLINE_RETRY_S = 5


def _allowed(request: Request) -> list[str]:
    """The methods the API documents at the request's path (its OpenAPI paths)."""
    methods = set()
    for path, operations in request.app.openapi()["paths"].items():
        template = re.sub(r"\\\{[^/]+?\\\}", "[^/]+", re.escape(path))
        if re.fullmatch(template, request.url.path):
            methods |= {m.upper() for m in operations}
    return sorted(methods)


def _describe(errors, patterns: dict[str, str]) -> str:
    parts = []
    for err in errors:
        where = ".".join(str(p) for p in err.get("loc", ()) if p != "body")
        msg = err["msg"]
        meaning = patterns.get(err.get("ctx", {}).get("pattern", ""))
        if err["type"] == "string_pattern_mismatch" and meaning:
            msg = f"must be {meaning}, got {err['input']!r}"
        parts.append(f"{where}: {msg}" if where else msg)
    return "; ".join(parts)
