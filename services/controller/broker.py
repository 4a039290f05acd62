"""The COSMOS Broker: spreads render, detect and optimize tasks over service replicas.

Each stage (renderer, detector, optimizer) has a pool of replica URLs. For every task the broker
picks a replica with a configurable heuristic (:mod:`~services.controller.placement`, pure, which
``benchmarks.broker_sim`` runs too):

* ``least-loaded``: fewest tasks ahead (this controller's in flight, plus those the replica's
  last ``/health`` counted beyond this controller's own at that moment);
* ``shortest-expected-completion``: smallest ``(load + 1) · expected duration``, where the expected
  duration is an exponential moving average of that replica's recent durations for that kind of
  task (a replica with no history is assumed as fast as the pool's mean);
* ``round-robin``: the next replica in turn.

A connect error, a timeout or a 5xx answer sends the task to another replica after a short
backoff; a replica that fails ``failure_threshold`` times in a row is taken out for
``cooldown_s`` and then probed back through ``/health``. A timeout that this process's event
loop noticed long after it was due (:attr:`TransportError.loop_was_late`: the loop was busy, and
the replica's answer may have sat unread) is retried without counting against the replica, and
never by itself makes the stage unavailable. A task fails, with the reasons, only when
no replica could serve it. 4xx answers are the caller's problem and are returned as they are.

A task may carry an ``affinity`` key (the free search's id, for the optimizer's target and
refinement tasks): the broker remembers, for :data:`AFFINITY_TTL_S`, the replica that last served
that key, and the next task of the key prefers it when it has no more tasks ahead than the
heuristic's choice (:func:`~services.controller.placement.choose`): there its data is kept.

A stage is *unavailable* (:meth:`Broker.unavailable`, and why: :meth:`Broker.outages`) while it
has no replica, while every replica is out, or from a task that no replica could serve until a
replica serves a task or answers ``/health`` again. Who wants to wait for it to come back calls
:meth:`Broker.wait_for_replica`: one prober per stage then asks its replicas' ``/health`` every
``recovery_probe_s`` (more often than the background probe) until one answers.

Each replica has a public name, its stage and a number (``renderer-1``, ``renderer-2``, in the
order the broker first met them; a number is never given to another address): what the
controller's answers show. Its address goes to the log only, once, with its name.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from typing import Any, Final

from cachetools import TTLCache

from services.common.contracts.search import ReplicaHealth
from services.controller.placement import Heuristic, Replica, choose
from services.controller.transport import (
    AiohttpTransport,
    StageAnswer,
    StageRequest,
    Transport,
    TransportError,
)

__all__ = ["Broker", "BrokerError", "Heuristic", "Replica"]

_log = logging.getLogger("cosmos.broker")
HEALTH_TIMEOUT_S = 2.0
AFFINITY_TTL_S: Final = 600.0
"""How long the replica that served an affinity key is remembered: longer than a search."""
AFFINITY_KEYS: Final = 4096
"""At most this many keys are remembered (the least recently used go first)."""


class BrokerError(RuntimeError):
    """No replica of a stage could serve a task; ``reasons`` says what each attempt met."""

    def __init__(self, stage: str, kind: str, reasons: Sequence[str]) -> None:
        self.stage, self.kind, self.reasons = stage, kind, list(reasons)
        summary = "; ".join(self.reasons) or "no replica configured"
        super().__init__(f"no {stage} replica could {kind}: {summary}")


class Broker:
    """Replica pools per stage, task placement, retries and health probing."""

    def __init__(
        self,
        pools: Mapping[str, Sequence[str]],
        *,
        heuristic: Heuristic = Heuristic.SHORTEST_EXPECTED,
        timeouts_s: Mapping[str, float] | None = None,
        connect_timeout_s: float = 2.0,
        max_attempts: int = 4,
        backoff_s: float = 0.05,
        failure_threshold: int = 3,
        cooldown_s: float = 5.0,
        health_interval_s: float = 2.0,
        recovery_probe_s: float = 0.5,
        transport: Transport | None = None,
    ) -> None:
        if max_attempts < 1 or failure_threshold < 1:
            raise ValueError("max_attempts and failure_threshold must be at least 1")
        self.heuristic = heuristic
        self.max_attempts = max_attempts
        self.backoff_s = backoff_s
        self.failure_threshold = failure_threshold
        self.cooldown_s = cooldown_s
        self.health_interval_s = health_interval_s
        self.recovery_probe_s = recovery_probe_s
        self._timeouts = dict(timeouts_s or {})
        self._transport = transport or AiohttpTransport(connect_timeout_s)
        self._replicas: dict[str, list[Replica]] = {}
        self._turns: dict[str, itertools.count[int]] = {}
        self._numbers: dict[str, itertools.count[int]] = {}  # the next replica name per stage
        for stage, urls in pools.items():
            self._replicas[stage] = [self._replica(stage, url) for url in urls]
            self._turns[stage] = itertools.count()
        self._health_task: asyncio.Task[None] | None = None
        # stage -> when its task last failed on every attempt (none served or answered since)
        self._outages: dict[str, float] = {}
        self._back: dict[str, asyncio.Event] = {}  # set when a replica of the stage answers
        self._recoveries: dict[str, asyncio.Task[None]] = {}
        self._waiting: Counter[str] = Counter()  # callers in wait_for_replica, per stage
        # (stage, affinity key) -> the url of the replica that last served it
        self._held: TTLCache[tuple[str, str], str] = TTLCache(AFFINITY_KEYS, AFFINITY_TTL_S)

    def _replica(self, stage: str, url: str) -> Replica:
        number = next(self._numbers.setdefault(stage, itertools.count(1)))
        replica = Replica(stage=stage, url=url.rstrip("/"), name=f"{stage}-{number}")
        _log.info("%s is %s", replica.name, replica.url)
        return replica

    async def set_pool(self, stage: str, urls: Sequence[str]) -> None:
        """Replace a stage's replicas (keeping what is known of those that stay)."""
        wanted = [url.rstrip("/") for url in urls]
        current = {r.url: r for r in self._replicas.get(stage, [])}
        self._replicas[stage] = [current.get(url) or self._replica(stage, url) for url in wanted]
        self._turns.setdefault(stage, itertools.count())

    # -- life cycle ---------------------------------------------------------------------------

    async def start(self) -> None:
        """Begin probing replica health in the background."""
        if self._health_task is None and self.health_interval_s > 0:
            self._health_task = asyncio.create_task(self._probe_forever(), name="broker-health")

    async def close(self) -> None:
        tasks = [*self._recoveries.values()]
        if self._health_task is not None:
            tasks.append(self._health_task)
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._health_task = None
        self._recoveries.clear()
        await self._transport.close()

    # -- introspection ------------------------------------------------------------------------

    def replicas(self, stage: str | None = None) -> list[Replica]:
        if stage is not None:
            return list(self._replicas.get(stage, []))
        return [r for pool in self._replicas.values() for r in pool]

    def stats(self) -> list[ReplicaHealth]:
        """What is known of every replica, as the controller's ``/health`` reports it: by
        name, never by address."""
        now = time.monotonic()
        return [
            ReplicaHealth(
                name=r.name,
                stage=r.stage,
                state=r.state(now),
                up=r.available(now),
                in_flight=r.in_flight,
                reported_load=r.reported_load,
                expected_ms=dict(r.expected_ms),
                served=r.served,
                failed=r.failed,
            )
            for r in self.replicas()
        ]

    def unavailable(self) -> list[str]:
        """The stages no replica serves now (:meth:`outages`)."""
        return list(self.outages())

    def outages(self) -> dict[str, str]:
        """Why each stage no replica serves now cannot be served, in public words: it has no
        replica, every replica is out, or its last task no replica could serve (until a replica
        serves a task or answers ``/health`` again)."""
        now = time.monotonic()
        why: dict[str, str] = {}
        for stage, pool in self._replicas.items():
            if not pool:
                why[stage] = "it has no replica"
            elif not any(r.available(now) for r in pool):
                why[stage] = "every replica failed repeatedly and is out until it answers again"
            elif stage in self._outages:
                why[stage] = "no replica could serve its last task, and none has answered since"
        return why

    # -- placement ----------------------------------------------------------------------------

    def choose(
        self, stage: str, kind: str, exclude: set[str] | None = None, affinity: str | None = None
    ) -> Replica:
        """The replica for the next ``kind`` task of ``stage`` (never one in ``exclude`` or out
        for cooldown, unless every replica is), the one that served ``affinity`` last if it is
        no busier: :func:`~services.controller.placement.choose`."""
        pool = self._replicas.get(stage, [])
        if not pool:
            self._outages.setdefault(stage, time.monotonic())
            raise BrokerError(stage, kind, [])
        turn = next(self._turns[stage])
        prefer = None if affinity is None else self._held.get((stage, affinity))
        return choose(
            self.heuristic,
            pool,
            kind,
            turn=turn,
            now=time.monotonic(),
            exclude=exclude or (),
            prefer=prefer,
        )

    # -- calls --------------------------------------------------------------------------------

    async def call(
        self, stage: str, kind: str, request: StageRequest, affinity: str | None = None
    ) -> StageAnswer:
        """Send ``request`` to a replica of ``stage``, retrying elsewhere on failure; with an
        ``affinity`` key, to the replica that served it last when that one is no busier, and
        the replica that answers is remembered for it (module docstring).

        Returns the first answer below 500; raises :class:`BrokerError` when every attempt met
        a connect error, a timeout or a 5xx.
        """
        reasons: list[str] = []
        tried: set[str] = set()
        replicas_failed = False
        for attempt in range(self.max_attempts):
            if attempt:
                await asyncio.sleep(self.backoff_s * 2 ** (attempt - 1))
            if len(tried) == len(self._replicas.get(stage, [])):
                tried.clear()  # every replica failed once: try them again after the backoff
            replica = self.choose(stage, kind, tried, affinity)
            replica.in_flight += 1
            started = time.perf_counter()
            try:
                response = await self._transport.send(
                    replica.url, request, self._timeouts.get(stage, 60.0)
                )
            except TransportError as exc:
                reason = f"{replica.url}: {exc}"
                if exc.loop_was_late:
                    # Our loop stalled past the timeout: the replica is not to blame. Sent
                    # again (to the same replica, if it is the best), not counted against it.
                    _log.warning("%s (noticed %.1f s late: this loop was busy)", reason, exc.late_s)
                    reasons.append(f"{reason}, noticed {exc.late_s:.1f} s late")
                    continue
            else:
                elapsed_ms = (time.perf_counter() - started) * 1000.0
                if response.status_code < 500:
                    self._succeeded(replica, kind, elapsed_ms)
                    if affinity is not None:
                        self._held[(stage, affinity)] = replica.url
                    return response
                reason = f"{replica.url}: HTTP {response.status_code}"
            finally:
                replica.in_flight -= 1
            self._failed(replica, reason)
            replicas_failed = True
            reasons.append(reason)
            tried.add(replica.url)
        if replicas_failed:  # not when every attempt only met a stall of this loop
            self._outages.setdefault(stage, time.monotonic())
        raise BrokerError(stage, kind, reasons)

    def _succeeded(self, replica: Replica, kind: str, elapsed_ms: float) -> None:
        replica.succeeded(kind, elapsed_ms)
        self._answered(replica.stage)

    def _failed(self, replica: Replica, reason: str) -> None:
        if replica.failed_at(time.monotonic(), self.failure_threshold, self.cooldown_s):
            _log.warning(
                "taking %s (%s) out for %.1f s (%s)",
                replica.name,
                replica.url,
                self.cooldown_s,
                reason,
            )

    # -- health -------------------------------------------------------------------------------

    async def probe(self) -> None:
        """Ask every replica's ``/health`` once: refresh reported loads, bring replicas back."""
        await asyncio.gather(*(self._probe(r) for r in self.replicas()))

    async def _probe(self, replica: Replica) -> None:
        try:
            response = await self._transport.send(
                replica.url, StageRequest("GET", "/health"), HEALTH_TIMEOUT_S
            )
            body: Any = response.json() if response.status_code == 200 else None
        except TransportError as exc:
            if exc.loop_was_late:
                return  # this loop stalled, the replica may well have answered: no verdict
            body = None
        except ValueError:
            body = None
        if not isinstance(body, dict):
            if replica.available(time.monotonic()):
                self._failed(replica, "health probe failed")
            return
        load = body.get("in_flight")
        if not replica.available(time.monotonic()):
            _log.info("%s (%s) answers /health again", replica.name, replica.url)
        replica.answered_health(float(load) if isinstance(load, int | float) else 0.0)
        self._answered(replica.stage)

    def _answered(self, stage: str) -> None:
        """A replica of ``stage`` served a task or answered ``/health``: the stage is back."""
        if self._outages.pop(stage, None) is not None:
            _log.info("the %s is available again", stage)
        back = self._back.pop(stage, None)
        if back is not None:
            back.set()

    async def wait_for_replica(self, stage: str, timeout_s: float) -> bool:
        """Wait until a replica of ``stage`` serves a task or answers ``/health`` (meanwhile the
        stage's replicas are probed every ``recovery_probe_s``); False if none did within
        ``timeout_s``.

        For a caller whose task no replica could serve: it calls again once this is true.
        """
        if stage not in self.unavailable():
            return True  # one answered since the caller's task failed
        back = self._back.setdefault(stage, asyncio.Event())
        self._waiting[stage] += 1
        recovery = self._recoveries.get(stage)
        if recovery is None or recovery.done():
            self._recoveries[stage] = asyncio.create_task(
                self._recover(stage), name=f"broker-recover-{stage}"
            )
        try:
            await asyncio.wait_for(back.wait(), timeout_s)
        except TimeoutError:
            return False
        finally:
            self._waiting[stage] -= 1
            if not self._waiting[stage]:
                del self._waiting[stage]
                if self._back.get(stage) is back:
                    del self._back[stage]
        return True

    async def _recover(self, stage: str) -> None:
        """Probe ``stage``'s replicas until one answers, while anyone waits for one."""
        while self._waiting[stage]:
            await asyncio.sleep(self.recovery_probe_s)
            try:
                await asyncio.gather(*(self._probe(r) for r in self.replicas(stage)))
            except Exception:  # a probe must never end the recovery
                _log.exception("probing the %s failed", stage)

    async def _probe_forever(self) -> None:
        while True:
            await asyncio.sleep(self.health_interval_s)
            try:
                await self.probe()
            except Exception:  # a probe must never kill the loop
                _log.exception("health probe failed")
