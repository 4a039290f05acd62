"""The web page's files: ``index.html`` and its bundled assets, served by Starlette's
``StaticFiles`` behind ``GZipMiddleware``.

The sources are in ``web/`` at the repository root; ``npm run build`` there bundles them (three.js
included: nothing is fetched at run time) into ``services/controller/web/``, whose asset names
carry a hash of their content. So ``index.html`` is revalidated on every load (``no-cache``, its
ETag) while an asset is cached for a year (``immutable``): a new build has new names.

Gzip is done per response, where the home-made server gzipped each file once when loaded:
measured, the largest file (the 3D view's worker, 557 KB, three.js) takes 29 ms of the event
loop at level 9, the rest together 1 ms. The worker is fetched once per browser (cached for a
year), so the library's simplicity is worth that.
"""

from __future__ import annotations

import os
from pathlib import Path

from starlette.datastructures import Headers
from starlette.middleware.gzip import GZipMiddleware
from starlette.responses import FileResponse, Response
from starlette.routing import BaseRoute, Route
from starlette.staticfiles import NotModifiedResponse, StaticFiles
from starlette.types import Scope

from services.common.errors import NotFoundError

__all__ = ["INDEX", "SECURITY_HEADERS", "WEB_DIR", "PageFiles", "page_routes"]

WEB_DIR = Path(__file__).with_name("web")
"""Where the built page lies (package data)."""

INDEX = "index.html"
_FOREVER = "public, max-age=31536000, immutable"
_REVALIDATE = "no-cache"

SECURITY_HEADERS = {
    # Everything the page loads is its own; images are blob: URLs of fetched views.
    "Content-Security-Policy": (
        "default-src 'self'; img-src 'self' blob: data:; style-src 'self'; "
        "script-src 'self'; connect-src 'self'; object-src 'none'; base-uri 'none'; "
        "frame-ancestors 'none'"
    ),
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
}


class PageFiles(StaticFiles):
    """The built page in ``directory``: ``/`` is its ``index.html`` (revalidated), every other
    file is an asset (cached for good); all with the page's security headers."""

    def __init__(self, directory: Path = WEB_DIR) -> None:
        super().__init__(directory=directory, html=True, check_dir=False)
        self.root = directory

    async def get_response(self, path: str, scope: Scope) -> Response:
        if path == "." and not (self.root / INDEX).is_file():
            raise NotFoundError(
                f"{INDEX} is not built: run `npm ci && npm run build` in web/",
                slug="page-not-built",
                title="Page not built",
            )
        return await super().get_response(path, scope)

    def file_response(
        self,
        full_path: str | os.PathLike[str],
        stat_result: os.stat_result,
        scope: Scope,
        status_code: int = 200,
    ) -> Response:
        index = Path(full_path) == self.root / INDEX
        headers = {"Cache-Control": _REVALIDATE if index else _FOREVER, **SECURITY_HEADERS}
        response = FileResponse(
            full_path, status_code=status_code, headers=headers, stat_result=stat_result
        )
        if self.is_not_modified(response.headers, Headers(scope=scope)):
            return NotModifiedResponse(response.headers)
        return response


def page_routes(directory: Path = WEB_DIR) -> list[BaseRoute]:
    """The page's routes: ``/`` and ``/assets/{name}``, gzipped for clients that take it."""
    files = GZipMiddleware(PageFiles(directory))
    return [
        Route("/", files, methods=["GET", "HEAD"]),
        Route("/assets/{name}", files, methods=["GET", "HEAD"]),
    ]
