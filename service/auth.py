"""Bearer tokens with scopes. Every route declares the scope it needs (``x-scope`` in the
OpenAPI document); tokens are compared in constant time and never logged."""

from __future__ import annotations

import hmac

from fastapi import Depends, Request

from service.problems import Problem
from service.settings import Scope, Settings

PUBLIC = "public"


def require(scope: Scope):
    """A route dependency that admits requests whose token holds ``scope``. A coroutine,
    though it never waits: FastAPI runs a plain function dependency in a worker thread, a
    hand-off per request that costs more CPU than the check."""

    async def check(request: Request) -> None:
        settings: Settings = request.app.state.service.settings
        if settings.open:
            return
        header = request.headers.get("authorization", "")
        kind, _, token = header.partition(" ")
        token = token.strip()
        scopes = _scopes(settings, token) if kind.lower() == "bearer" and token else None
        if scopes is None:
            raise Problem(401, "a valid bearer token is required", {"WWW-Authenticate": "Bearer"})
        if scope not in scopes:
            raise Problem(403, f"this token lacks the {scope!r} scope")

    return Depends(check)


def _scopes(settings: Settings, token: str) -> list[Scope] | None:
    found = None
    given = token.encode()
    for secret, scopes in settings.tokens.items():  # no early exit: constant time in the match
        if hmac.compare_digest(secret.get_secret_value().encode(), given):
            found = scopes
    return found
