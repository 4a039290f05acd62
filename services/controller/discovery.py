"""Replica discovery by DNS: one replica per address a stage's host name resolves to.

Under ``docker compose up --scale renderer=3`` the name ``renderer`` resolves to every replica's
address; turning ``http://renderer:8001`` into one URL per address lets the broker see (and
balance over) each of them. Names that do not resolve are kept as they are.
"""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Sequence
from urllib.parse import urlsplit, urlunsplit

__all__ = ["expand_urls"]


async def expand_urls(urls: Sequence[str]) -> list[str]:
    """Each URL once per IPv4/IPv6 address of its host (sorted, duplicates dropped)."""
    loop = asyncio.get_running_loop()
    expanded: list[str] = []
    for url in urls:
        parts = urlsplit(url)
        host, port = parts.hostname, parts.port
        if host is None:
            expanded.append(url)
            continue
        try:
            infos = await loop.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        except OSError:
            expanded.append(url)
            continue
        addresses = sorted({str(info[4][0]) for info in infos})
        for address in addresses:
            netloc = f"[{address}]" if ":" in address else address
            if port is not None:
                netloc += f":{port}"
            expanded.append(urlunsplit((parts.scheme, netloc, parts.path, "", "")))
    return list(dict.fromkeys(expanded))
