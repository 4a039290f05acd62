"""Whether this process's server was asked to stop (SIGTERM, SIGINT).

uvicorn's graceful shutdown waits for every response in flight, and a stream of server-sent
events has no end of its own: each stream ends itself once :data:`STOPPING` is set, so that a
browser left open does not hold a stopping service until it is killed. The server
(:mod:`services.common.server`) sets it; it lives here, apart, because the server module runs as
``__main__`` and the apps would import a second copy of it.
"""

from __future__ import annotations

import threading
from typing import Final

__all__ = ["STOPPING"]

STOPPING: Final = threading.Event()
