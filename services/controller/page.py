"""The web page's files, served from memory: ``index.html`` and its bundled assets.

The sources are in ``web/`` at the repository root; ``npm run build`` there bundles them (three.js
included: nothing is fetched at run time) into ``services/controller/web/``, whose asset names
carry a hash of their content. So ``index.html`` is revalidated on every load (``no-cache``, an
ETag) while an asset is cached for a year (``immutable``): a new build has new names. Each file
is gzipped once, when loaded, for clients that accept it.
"""

from __future__ import annotations

import gzip
import hashlib
import mimetypes
from dataclasses import dataclass
from pathlib import Path

__all__ = [
    "INDEX",
    "SECURITY_HEADERS",
    "WEB_DIR",
    "Asset",
    "PageAssets",
    "accepts_gzip",
    "not_modified",
]

WEB_DIR = Path(__file__).with_name("web")
"""Where the built page lies (package data)."""

INDEX = "index.html"
_MEDIA_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".svg": "image/svg+xml",
    ".png": "image/png",
    ".map": "application/json",
}
_COMPRESSIBLE = {".html", ".js", ".css", ".svg", ".map"}
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


@dataclass(frozen=True)
class Asset:
    """One file of the page, as served."""

    body: bytes
    gzipped: bytes | None
    media_type: str
    etag: str
    cache_control: str

    def headers(self, *, gzip_ok: bool) -> dict[str, str]:
        headers = {
            "ETag": self.etag,
            "Cache-Control": self.cache_control,
            "Vary": "Accept-Encoding",
        }
        if gzip_ok and self.gzipped is not None:
            headers["Content-Encoding"] = "gzip"
        return headers


def _asset(path: Path, *, index: bool) -> Asset:
    body = path.read_bytes()
    suffix = path.suffix.lower()
    media_type = _MEDIA_TYPES.get(suffix) or mimetypes.guess_type(path.name)[0]
    gzipped = gzip.compress(body, compresslevel=9, mtime=0) if suffix in _COMPRESSIBLE else None
    return Asset(
        body=body,
        gzipped=gzipped if gzipped is not None and len(gzipped) < len(body) else None,
        media_type=media_type or "application/octet-stream",
        etag=f'"{hashlib.sha256(body).hexdigest()[:32]}"',
        cache_control=_REVALIDATE if index else _FOREVER,
    )


class PageAssets:
    """The built page in ``directory``: ``index.html`` and the files of ``assets/``."""

    def __init__(self, directory: Path = WEB_DIR) -> None:
        self.directory = directory
        index = directory / INDEX
        self.index: Asset | None = _asset(index, index=True) if index.is_file() else None
        assets = directory / "assets"
        self.assets: dict[str, Asset] = (
            {p.name: _asset(p, index=False) for p in sorted(assets.iterdir()) if p.is_file()}
            if assets.is_dir()
            else {}
        )

    def asset(self, name: str) -> Asset | None:
        """The asset called ``name`` (a bare file name), or None."""
        return self.assets.get(name)


def accepts_gzip(accept_encoding: str) -> bool:
    """Whether an ``Accept-Encoding`` header value takes gzip (not refused with ``q=0``)."""
    for part in accept_encoding.split(","):
        coding, _, params = part.strip().partition(";")
        if coding.strip().lower() in {"gzip", "*"}:
            q = params.strip().removeprefix("q=").strip() if params.strip().startswith("q=") else ""
            try:
                return not q or float(q) > 0
            except ValueError:
                return True
    return False


def not_modified(asset: Asset, if_none_match: str) -> bool:
    """Whether an ``If-None-Match`` header value names ``asset``'s ETag (or ``*``)."""
    tags = {tag.strip().removeprefix("W/") for tag in if_none_match.split(",")}
    return asset.etag in tags or "*" in tags
