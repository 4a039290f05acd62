"""Whether the controller can run searches now: its database answers, no stage is in an outage
as its broker sees it, and every stage has at least one replica that says it is ready
(``GET /readyz``), asked afresh each time.

Both are asked. The broker's outage state (:meth:`~services.controller.broker.Broker.outages`:
no replica, every replica out, or a task none could serve) is what refuses new searches with
503, so while it lasts the controller is not ready, whatever a probe says. But the broker learns
that a replica died only after a few failed calls or health probes, and nothing of one it has not
called yet, hence the fresh probes. The reasons name stages, never addresses.
"""

from __future__ import annotations

import asyncio
import logging

from services.controller.broker import Broker
from services.controller.store import DatabaseUnavailable, SearchStore
from services.controller.transport import StageRequest, Transport, TransportError

__all__ = ["PROBE_TIMEOUT_S", "STAGES", "ControllerReadiness"]

PROBE_TIMEOUT_S = 1.0
STAGES = ("renderer", "detector", "optimizer")

_log = logging.getLogger("cosmos.controller")


class ControllerReadiness:
    """The controller's answer to ``GET /readyz``."""

    def __init__(self, store: SearchStore, broker: Broker, transport: Transport) -> None:
        self.store = store
        self.broker = broker
        self.transport = transport

    async def unready(self) -> list[str]:
        """Why the controller cannot run a search now, in words for its operators (nothing
        when it can)."""
        database, *stages = await asyncio.gather(
            self._database(), *(self._stage(stage) for stage in STAGES)
        )
        return [reason for reason in (database, *stages) if reason]

    async def _database(self) -> str:
        """A database that does not answer within :data:`PROBE_TIMEOUT_S` (a partition: the
        ping's thread waits for it longer) is not ready, as one that refuses is."""
        try:
            await asyncio.wait_for(
                asyncio.to_thread(self.store.database.ping), timeout=PROBE_TIMEOUT_S
            )
        except (DatabaseUnavailable, TimeoutError) as exc:
            _log.warning("readiness: the database does not answer (%s)", exc or "timed out")
            return "the search database does not answer"
        return ""

    async def _stage(self, stage: str) -> str:
        outage = self.broker.outages().get(stage)
        if outage is not None:
            return f"the {stage} is unavailable: {outage}"
        urls = [replica.url for replica in self.broker.replicas(stage)]
        answers = await asyncio.gather(*(self._ready(url) for url in urls))
        if any(answers):
            return ""
        return f"no {stage} is ready ({len(urls)} replica{'' if len(urls) == 1 else 's'} asked)"

    async def _ready(self, url: str) -> bool:
        try:
            answer = await self.transport.send(url, StageRequest("GET", "/readyz"), PROBE_TIMEOUT_S)
        except TransportError:
            return False
        return answer.status_code == 200
