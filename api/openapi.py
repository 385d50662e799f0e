"""The OpenAPI schema from the routes' own declarations: every status code a route can answer and
the real security of each route.

FastAPI documents 200/201/204 and 422 by itself. The other answers come from what the route
depends on, and are declared here from the same declarations, so the schema cannot drift from the
service: a route that depends on :func:`api.deps.require_write` (or on ``require_read`` when reads
are protected) answers 401/403; a route with path parameters answers 400 (an id outside the rule,
:func:`api.paths.check_take_id`) and 404; a route with a body answers 400 and 413; every route may
answer 404 (no stage session), 503 (a missing rig, driver or processing module) and 507 (a
full disk). Read routes are
open unless ``read_protected``: their security lists "no token" beside the bearer token.
"""

from __future__ import annotations

import re
from typing import Any

from fastapi import FastAPI
from fastapi.routing import APIRoute
from pydantic import BaseModel

from api.deps import require_read, require_write

__all__ = ["ErrorBody", "declare_responses"]


class ErrorBody(BaseModel):
    """Every error answer: ``detail`` says what went wrong (a list of problems for 422)."""

    detail: Any
    errors: list[Any] | None = None


_TEXT = {400: "bad request: an invalid id, parameter or body", 401: "missing API token",
         403: "wrong API token, or no token configured", 404: "no such resource", 409: "conflict",
         413: "request body too large", 415: "unsupported content type", 422: "a required field is missing",
         503: "a component is unavailable",
         507: "not enough free disk space"}


def _access(route: APIRoute) -> str | None:
    """``"write"``, ``"read"`` or None: the access dependency of a route."""
    todo, seen = list(route.dependant.dependencies), set()
    found = None
    while todo:
        d = todo.pop()
        if d.call is require_write:
            return "write"
        if d.call is require_read:
            found = "read"
        if id(d) not in seen:
            seen.add(id(d))
            todo.extend(d.dependencies)
    return found


def _codes(route: APIRoute, access: str | None, read_protected: bool) -> set[int]:
    codes = {404, 503, 507}  # 404 too where the resource is the server's (no stage session, no rig)
    if access == "write" or (access == "read" and read_protected):
        codes |= {401, 403}
    if re.search(r"{\w+}", route.path) or route.dependant.query_params:
        codes |= {400, 404}
    body = route.body_field is not None or "requestBody" in (route.openapi_extra or {})
    if body or route.methods & {"POST", "PUT"}:
        codes |= {400, 404, 409, 413}
    if "requestBody" in (route.openapi_extra or {}):  # a body the route reads itself
        codes |= {415, 422}
    return codes


def declare_responses(app: FastAPI, routers, *, read_protected: bool) -> None:
    """Declare the answers of every route of ``routers`` (and of the app) and patch the schema's
    security; call once the routers are included."""
    routes = [r for rt in routers for r in rt.routes if isinstance(r, APIRoute)]
    access = {}
    for r in routes:
        access[(r.path, frozenset(r.methods))] = a = _access(r)
        for code in sorted(_codes(r, a, read_protected)):
            if code not in r.responses and str(code) not in r.responses:
                r.responses[code] = {"model": ErrorBody, "description": _TEXT[code]}
    original = app.openapi

    def openapi() -> dict:
        if app.openapi_schema:
            return app.openapi_schema
        schema = original()
        for r in routes:
            for m in r.methods:
                op = schema.get("paths", {}).get(r.path_format, {}).get(m.lower())
                if op is None:
                    continue
                a = access[(r.path, frozenset(r.methods))]
                if a is None or (a == "read" and not read_protected):
                    # open to everyone; a token sent anyway is accepted (and checked for writes only)
                    op["security"] = [{}, {"HTTPBearer": []}] if a == "read" else []
        return schema

    app.openapi = openapi
