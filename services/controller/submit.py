"""Accepting a search: validate the target image and the options, pick the start pose, record it."""

from __future__ import annotations

import asyncio
import logging
import random
import re
import uuid
import weakref

from services.common.contracts.optimize import (
    GridPose,
    StrategyName,
    UnsupportedGridError,
    searchable_grid,
)
from services.common.contracts.search import MAX_ITERATIONS, Search
from services.common.errors import NotFoundError, UnprocessableError
from services.common.geometry.pose import Pose
from services.common.geometry.scene import SCENE_ID_PATTERN
from services.common.images import checked_header, decode_image
from services.controller.stages import StageError, Stages
from services.controller.store import SearchStore, utcnow

__all__ = ["INLINE_WRITE_BYTES", "create_search"]

INLINE_WRITE_BYTES = 1 << 20
"""A target image up to this size is stored on the event loop (a 230 KB one takes ~0.4 ms, less
than a thread's round trip); a larger one on a thread, one at a time. Under 50 maximal uploads
at once, the inserts of their 20 MB images on the loop took 4.4 s of its time (sampled; the
uploads run in docs/HISTORY.md) and stalled it for seconds: the broker's calls timed out meanwhile.
One at a time, because the store has one lock: with several inserts queued on it, the loop's
next store call waited behind all of them (1.6 s, sampled)."""

_log = logging.getLogger("cosmos.controller")
_UNDOING: set[asyncio.Task[None]] = set()
"""Undoing cancelled writes (:func:`_store_large`), kept until done."""
_WRITERS: weakref.WeakKeyDictionary[SearchStore, asyncio.Lock] = weakref.WeakKeyDictionary()


def _large_writes(store: SearchStore) -> asyncio.Lock:
    """The lock one large image insert into ``store`` holds at a time."""
    lock = _WRITERS.get(store)
    if lock is None:
        lock = _WRITERS[store] = asyncio.Lock()
    return lock


async def _store_large(store: SearchStore, record: Search, image: bytes, owner: str | None) -> None:
    """Record ``record`` with its large ``image`` on a thread, one such write at a time.

    A thread cannot be stopped: when the caller is cancelled meanwhile (its client went away,
    the server shuts down), the write goes on and commits a search nobody hands to the runner,
    queued until the next restart. So the write is undone once it has ended
    (:func:`_undo_write`): a submission that was not answered took nothing, neither a search
    its client never learnt the id of nor a share of the key's quotas.
    """
    async with _large_writes(store):
        write = asyncio.ensure_future(asyncio.to_thread(store.create, record, image, owner=owner))
        try:
            await asyncio.shield(write)
        except asyncio.CancelledError:
            undo = asyncio.create_task(_undo_write(store, write, record.id))
            _UNDOING.add(undo)  # the loop keeps only a weak reference to a task
            undo.add_done_callback(_UNDOING.discard)
            raise


async def _undo_write(store: SearchStore, write: asyncio.Future[None], search_id: str) -> None:
    """Once ``write`` has ended, delete the search it recorded (nothing if it failed)."""
    try:
        await write
    except Exception:  # not recorded: nothing to undo
        return
    try:
        await asyncio.to_thread(store.discard, search_id)
    except Exception:  # left queued: the next start runs it, as before
        _log.exception("could not discard search %s, whose submission was cancelled", search_id)
        return
    _log.info("discarded search %s: its submission was cancelled while it was stored", search_id)


async def create_search(
    store: SearchStore,
    stages: Stages,
    *,
    image: bytes,
    scene_id: str,
    strategy: StrategyName,
    start_theta_deg: float | None,
    start_phi_deg: float | None,
    seed: int | None,
    max_iterations: int,
    max_image_pixels: int,
    max_image_side: int,
    start_early: bool = False,
    owner: str | None = None,
) -> Search:
    """Validate a new search and record it as queued (the caller queues it).

    The image must decode (PNG, JPEG or binary PPM within the size caps; its header is checked
    first, its pixels decoded off the event loop); the scene must be known to the renderers. A
    start pose given by angles is snapped to the nearest grid pose; without one, a grid pose is
    drawn from ``seed`` (itself drawn when absent, and recorded). With ``start_early`` the start
    view's render is under way while the pixels are decoded and the search stored
    (:meth:`Stages.render_early`; dropped again if the image turns out broken). ``owner`` is
    the id of the API key that submits it. A large image is written to the store off the event
    loop (:data:`INLINE_WRITE_BYTES`), and the search deleted again if the caller is cancelled
    meanwhile (:func:`_store_large`): stored means answered and handed to the runner. The search
    records the controller's current view settings (:attr:`Stages.view_settings`): all its views
    are rendered with them.
    """
    header = checked_header(image, max_pixels=max_image_pixels, max_side=max_image_side)
    if not 1 <= max_iterations <= MAX_ITERATIONS:
        raise UnprocessableError(
            f"max_iterations must be within 1..{MAX_ITERATIONS}", field="max_iterations"
        )
    if (start_theta_deg is None) != (start_phi_deg is None):
        raise UnprocessableError(
            "give start_theta_deg and start_phi_deg together", field="start_theta_deg"
        )
    if re.match(SCENE_ID_PATTERN, scene_id) is None:
        raise NotFoundError(
            f"unknown scene {scene_id!r}",
            field="scene",
            slug="unknown-scene",
            title="Unknown scene",
        )
    try:
        scene = await stages.scene(scene_id)
    except StageError as exc:
        if exc.problem.status == 404:
            raise NotFoundError(
                f"unknown scene {scene_id!r}",
                field="scene",
                slug="unknown-scene",
                title="Unknown scene",
            ) from exc
        raise UnprocessableError(
            f"scene {scene_id!r}: {exc.problem.detail}", field="scene"
        ) from exc
    try:
        grid = searchable_grid(scene.spec.search).grid()
    except UnsupportedGridError as exc:
        raise UnprocessableError(
            f"scene {scene_id!r}'s grid cannot be searched: {exc}",
            field=exc.field,
            slug="unsupported-grid",
            title="Grid not supported",
        ) from exc
    seed = seed if seed is not None else random.SystemRandom().randrange(2**31)
    if start_theta_deg is not None and start_phi_deg is not None:
        try:
            asked = Pose(theta_deg=start_theta_deg, phi_deg=start_phi_deg)
        except ValueError as exc:
            raise UnprocessableError(
                "start_theta_deg must be within [0, 90] and both angles finite",
                field="start_theta_deg",
            ) from exc
        index = grid.nearest(asked)
    else:
        index = grid.unflat(random.Random(seed).randrange(grid.size))
    pose = grid.pose(index)
    search_id = uuid.uuid4().hex
    view_settings = stages.view_settings  # its views are rendered so from now on, always
    if start_early:
        stages.render_early(scene_id, index, search_id, view_settings)
        # One turn of the loop puts the render request on the wire (on a kept-alive connection
        # that is the task's first step) before the decode's thread hop: ~0.5 ms sooner.
        await asyncio.sleep(0)
    try:
        await asyncio.to_thread(
            decode_image, image, max_pixels=max_image_pixels, max_side=max_image_side
        )
        now = utcnow()
        record = Search(
            id=search_id,
            status="queued",
            scene=scene_id,
            strategy=strategy,
            start=GridPose(index=index, theta_deg=pose.theta_deg, phi_deg=pose.phi_deg),
            seed=seed,
            max_iterations=max_iterations,
            created_at=now,
            updated_at=now,
            target_size=(header.width, header.height),
            view_settings=view_settings,
        )
        if len(image) <= INLINE_WRITE_BYTES:
            store.create(record, image, owner=owner)
        else:
            await _store_large(store, record, image, owner)
    except BaseException:
        stages.forget_early(search_id)
        raise
    return record
