"""The OpenAPI document a service publishes, in the plainest JSON Schema that says the same.

pydantic writes a tuple such as ``tuple[int, int]`` as ``prefixItems: [S, S]`` with
``minItems = maxItems = 2``. Some OpenAPI tools rewrite ``prefixItems`` into draft-4
``items: [...]`` and then validate with a draft 2020-12 validator, which refuses the result
(schemathesis 4: "Invalid Schema Object in response definition"), so they cannot check an answer
that holds an image size or a box at all. When every item shares one schema, ``items: S`` with
the same bounds means the same and every tool reads it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from fastapi import FastAPI

__all__ = ["plain_tuples", "publish_plain_schema"]


def plain_tuples(node: Any) -> Any:
    """``node`` (a JSON document) with every homogeneous tuple schema (``prefixItems: [S, …, S]``
    of ``n`` items with ``minItems = maxItems = n`` and no ``items``) written as ``items: S``."""
    if isinstance(node, list):
        return [plain_tuples(item) for item in node]
    if not isinstance(node, dict):
        return node
    out = {key: plain_tuples(value) for key, value in node.items()}
    prefix = out.get("prefixItems")
    if (
        isinstance(prefix, list)
        and prefix
        and all(item == prefix[0] for item in prefix)
        and out.get("minItems") == out.get("maxItems") == len(prefix)
        and "items" not in out
    ):
        out["items"] = out.pop("prefixItems")[0]
    return out


def publish_plain_schema(app: FastAPI) -> None:
    """Make ``app`` publish its OpenAPI document through :func:`plain_tuples` (built once, as
    FastAPI caches it)."""
    build: Callable[[], dict[str, Any]] = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = plain_tuples(build())
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
