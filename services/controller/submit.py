"""Accepting a search: admission (no stage down, the key within its quotas), then validating the
target image and the options, picking the start pose, recording it and queueing it."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import re
import uuid
import weakref

from services.common.contracts.optimize import GridPose, UnsupportedGridError, searchable_grid
from services.common.contracts.search import (
    MAX_ITERATIONS,
    TERMINAL_STATUSES,
    Search,
    SearchOptions,
)
from services.common.errors import NotFoundError, ServiceUnavailableError, UnprocessableError
from services.common.geometry.pose import Pose
from services.common.geometry.scene import SCENE_ID_PATTERN
from services.common.images import checked_header, decode_image
from services.controller.broker import Broker
from services.controller.form import photo_attitude, photo_intrinsics
from services.controller.keys import ApiKey
from services.controller.photo_exif import exif_intrinsics
from services.controller.photo_metadata import PhotoMetadata, read_metadata
from services.controller.photo_xmp import xmp_attitude, xmp_intrinsics
from services.controller.quotas import Quotas
from services.controller.runner import NotRetryable, SearchRunner
from services.controller.settings import ControllerSettings
from services.controller.stages import StageError, Stages
from services.controller.store import Lease, Leases, SearchStore, utcnow

__all__ = ["INLINE_WRITE_BYTES", "RETRY_AFTER_S", "Admission", "create_search"]

INLINE_WRITE_BYTES = 1 << 20
"""A target image up to this size is stored on the event loop (a 230 KB one takes ~0.4 ms, less
than a thread's round trip); a larger one on a thread, one at a time. Under 50 maximal uploads
at once, the inserts of their 20 MB images on the loop took 4.4 s of its time (sampled; the
uploads run in docs/HISTORY.md) and stalled it for seconds: the broker's calls timed out meanwhile.
One at a time, because the store has one lock: with several inserts queued on it, the loop's
next store call waited behind all of them (1.6 s, sampled). On PostgreSQL every image is stored
on a thread: a write there crosses the network, and a database that hangs must not hold the
loop."""

RETRY_AFTER_S = 5
"""``Retry-After`` of a 503 while a stage is unavailable (the broker probes it more often)."""

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


async def _store_large(
    store: SearchStore,
    record: Search,
    image: bytes,
    owner: str | None,
    leases: Leases | None,
) -> Lease | None:
    """Record ``record`` with its large ``image`` on a thread, one such write at a time.

    A thread cannot be stopped: when the caller is cancelled meanwhile (its client went away,
    the server shuts down), the write goes on and commits a search nobody hands to the runner,
    queued until the next restart. So the write is undone once it has ended
    (:func:`_undo_write`): a submission that was not answered took nothing, neither a search
    its client never learnt the id of nor a share of the key's quotas.
    """
    async with _large_writes(store):
        write = asyncio.ensure_future(
            asyncio.to_thread(store.create, record, image, owner=owner, leases=leases)
        )
        try:
            return await asyncio.shield(write)
        except asyncio.CancelledError:
            undo = asyncio.create_task(_undo_write(store, write, record.id))
            _UNDOING.add(undo)  # the loop keeps only a weak reference to a task
            undo.add_done_callback(_UNDOING.discard)
            raise


async def _undo_write(
    store: SearchStore, write: asyncio.Future[Lease | None], search_id: str
) -> None:
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
    image: bytes,
    options: SearchOptions,
    settings: ControllerSettings,
    *,
    start_early: bool = False,
    owner: str | None = None,
    leases: Leases | None = None,
) -> Search:
    """Validate a new search and record it as queued (the caller queues it); without
    ``max_iterations`` in ``options``, it takes the controller's default.

    The image must decode (PNG, JPEG or binary PPM within the size caps; its header is checked
    first, its pixels decoded off the event loop); the scene must be known to the renderers. A
    start pose given by angles is snapped to the nearest grid pose; without one, a grid pose is
    drawn from ``seed`` (itself drawn when absent, and recorded), which a hemisphere search
    starts from only when the pose predicted from its target cannot be used (:mod:`.start`);
    a free search (``mode=free``) records it too but starts from the pose the optimizer
    solves for, with the photo's intrinsics when given
    (:func:`~services.controller.form.photo_intrinsics`), else those its metadata states unless
    ``exif`` is false: a drone's calibration in its XMP
    (:func:`~services.controller.photo_xmp.xmp_intrinsics`), else its EXIF focal length
    (:func:`~services.controller.photo_exif.exif_intrinsics`); and its camera's pitch and roll
    when given (:func:`~services.controller.form.photo_attitude`), else when its XMP states them
    (:func:`~services.controller.photo_xmp.xmp_attitude`). With
    ``start_early`` a given start view's render is under way while the pixels are decoded and
    the search stored (:meth:`Stages.render_early`; dropped again if the image turns out
    broken); a predicted start needs the target's detections first, so nothing is rendered
    early for it.
    ``owner`` is the id of the API key that submits it. A large image is written to the store
    off the event loop (:data:`INLINE_WRITE_BYTES`), and the search deleted again if the caller
    is cancelled meanwhile (:func:`_store_large`): stored means answered and handed to the
    runner. With ``leases`` (PostgreSQL), their controller takes the search's lease as it
    records it, so that no other controller claims it first. The search records the
    controller's current view settings
    (:attr:`Stages.view_settings`): all its views are rendered with them.
    """
    max_image_pixels = settings.controller_max_image_pixels
    max_image_side = settings.controller_max_image_side
    max_iterations = options.max_iterations or settings.controller_default_max_iterations
    header = checked_header(image, max_pixels=max_image_pixels, max_side=max_image_side)
    if not 1 <= max_iterations <= MAX_ITERATIONS:
        raise UnprocessableError(
            f"max_iterations must be within 1..{MAX_ITERATIONS}", field="max_iterations"
        )
    if (options.start_theta_deg is None) != (options.start_phi_deg is None):
        raise UnprocessableError(
            "give start_theta_deg and start_phi_deg together", field="start_theta_deg"
        )
    intrinsics = photo_intrinsics(options)
    metadata = read_metadata(image) if options.mode == "free" and options.exif else PhotoMetadata()
    if intrinsics is None:
        size = (header.width, header.height)
        intrinsics = xmp_intrinsics(metadata, size) or exif_intrinsics(metadata, size)
    attitude = photo_attitude(options) or xmp_attitude(metadata)
    if re.match(SCENE_ID_PATTERN, options.scene) is None:
        raise NotFoundError(
            f"unknown scene {options.scene!r}",
            field="scene",
            slug="unknown-scene",
            title="Unknown scene",
        )
    try:
        scene = await stages.scene(options.scene)
    except StageError as exc:
        if exc.problem.status == 404:
            raise NotFoundError(
                f"unknown scene {options.scene!r}",
                field="scene",
                slug="unknown-scene",
                title="Unknown scene",
            ) from exc
        raise UnprocessableError(
            f"scene {options.scene!r}: {exc.problem.detail}", field="scene"
        ) from exc
    try:
        grid = searchable_grid(scene.spec.search).grid()
    except UnsupportedGridError as exc:
        raise UnprocessableError(
            f"scene {options.scene!r}'s grid cannot be searched: {exc}",
            field=exc.field,
            slug="unsupported-grid",
            title="Grid not supported",
        ) from exc
    seed = options.seed if options.seed is not None else random.SystemRandom().randrange(2**31)
    start_given = options.start_theta_deg is not None and options.start_phi_deg is not None
    if options.start_theta_deg is not None and options.start_phi_deg is not None:
        try:
            asked = Pose(theta_deg=options.start_theta_deg, phi_deg=options.start_phi_deg)
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
    if start_early and start_given and options.mode == "hemisphere":  # else solved for
        stages.render_early(options.scene, index, search_id, view_settings)
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
            scene=options.scene,
            strategy=options.strategy,
            start=GridPose(index=index, theta_deg=pose.theta_deg, phi_deg=pose.phi_deg),
            start_given=start_given,
            seed=seed,
            max_iterations=max_iterations,
            created_at=now,
            updated_at=now,
            target_size=(header.width, header.height),
            view_settings=view_settings,
            mode=options.mode,
            intrinsics=intrinsics,
            attitude=attitude,
        )
        if len(image) <= INLINE_WRITE_BYTES and store.database.dialect == "sqlite":
            store.create(record, image, owner=owner, leases=leases)
        else:
            await _store_large(store, record, image, owner, leases)
    except BaseException:
        stages.forget_early(search_id)
        raise
    return record


class Admission:
    """Takes searches in, new (:meth:`submit`) or again (:meth:`retry`): none while a stage has no
    replica available, and a key's only within its quotas (an admin key, or none when auth is
    off, has no quotas)."""

    def __init__(
        self,
        settings: ControllerSettings,
        store: SearchStore,
        stages: Stages,
        broker: Broker,
        runner: SearchRunner,
        quotas: Quotas,
    ) -> None:
        self.settings = settings
        self.store = store
        self.stages = stages
        self.broker = broker
        self.runner = runner
        self.quotas = quotas

    def dismiss(self, search: Search) -> Search | None:
        """Cancel a queued or running search (it is kept: the cancelled search), or delete a
        finished, failed or cancelled one with its image and iterations (None), so its bytes no
        longer count towards its key's quota. Raises :class:`~.runner.StillStopping` while a search
        cancelled a moment ago still winds down, and :class:`KeyError` when it expired
        meanwhile."""
        if search.status not in TERMINAL_STATUSES:
            return self.runner.cancel(search.id)
        deleted = self.runner.delete(search.id)
        if deleted is None:
            raise KeyError(search.id)
        owner, created_at = deleted
        if owner is not None:
            self.quotas.deleted(owner, created_at)
        return None

    def refuse_while_unavailable(self) -> None:
        """503 with ``Retry-After`` while a stage no replica serves: a search taken now would
        only wait for it (and fail after the outage budget), so it is not taken."""
        down = self.broker.unavailable()
        if down:
            raise ServiceUnavailableError(
                f"the {' and the '.join(down)} {'is' if len(down) == 1 else 'are'} unavailable "
                "(no replica answers); try again once GET /health no longer lists "
                f"{'it' if len(down) == 1 else 'them'}",
                slug="stage-unavailable",
                title="Stage unavailable",
                headers={"Retry-After": str(RETRY_AFTER_S)},
            )

    async def submit(self, image: bytes, options: SearchOptions, key: ApiKey | None) -> Search:
        """Record a new search for ``key`` (:func:`create_search`) and queue it. The caller
        has called :meth:`refuse_while_unavailable` before it read ``image``. Raises
        :class:`~services.controller.broker.BrokerError` and
        :class:`~services.controller.stages.StageError` when the renderer cannot tell the
        scene, the errors of :func:`create_search` and the quotas' otherwise."""
        admitted: contextlib.AbstractContextManager[None] = (
            self.quotas.admit(key.id, len(image))
            if key is not None and not key.admin
            else contextlib.nullcontext()
        )
        idle = self.runner.idle
        with admitted:
            search = await create_search(
                self.store,
                self.stages,
                image,
                options,
                self.settings,
                start_early=idle,
                owner=None if key is None else key.id,
                leases=self.runner.leases if idle else None,  # busy: whoever is free runs it
            )
        # The runner keeps the image of a search that starts now, or a small one; a large image
        # of a queued search is read back when it starts (50 maximal uploads queued would hold
        # 1 GB).
        keep = idle or len(image) <= INLINE_WRITE_BYTES
        self.runner.submit(search.id, recorded=(search, image) if keep else None, leased=idle)
        return search

    def retry(self, search: Search, key: ApiKey | None) -> Search:
        """Queue ``search`` again (:meth:`SearchRunner.retry`); raises :class:`NotRetryable`
        for a search that did not fail for an outage, 503 while a stage is still unavailable,
        and the quota of searches queued or running."""
        why = self.runner.why_not_retryable(search)
        if why is not None:
            raise NotRetryable(why)
        self.refuse_while_unavailable()
        if key is not None and not key.admin:
            self.quotas.check(key.id, 0)  # its image is stored already
        return self.runner.retry(search.id)  # nothing ran since the check: it takes the search
