"""Which model detects for a scene: the scene's own model when it has a valid one, else the general.

A scene ``<dir>/<id>.yaml`` found through the scene catalog (``COSMOS_SCENES_DIR``, then the
built-in ``scenes/``) may have its own model in ``<dir>/<id>.detector/`` (see
:mod:`services.common.scene_models`). It serves only when it passes every check of
:func:`load_scene_model`; a refused model is logged and listed with its error, and the scene's
previous model (if one was serving and its classes still fit the scene) goes on serving, else
the general model does.

Scene models are loaded at start-up and looked at again when a request names their scene (at most
once per ``detector_scene_check_s``): a cheap stat of the files, and a load on a worker thread
only when they changed. The request that finds the change waits for the load; requests meanwhile
are served by the model already serving. Each serving model has its own onnxruntime session and
batcher (about 13 MB and one inference thread each, measured with the shipped model).
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from services.common.catalog import SceneCatalog
from services.common.contracts.detect import (
    DetectorModels,
    DetectResponse,
    SceneModelState,
    SceneModelStatus,
)
from services.common.errors import ServiceError
from services.common.geometry.scene import LoadedScene
from services.common.scene_models import MODEL_FILE_NAME, SIDECAR_NAME, model_dir, object_classes
from services.detector.detect import Detector
from services.detector.model import DetectorModel, ModelError
from services.detector.settings import DetectorSettings

__all__ = ["ModelRegistry", "load_scene_model"]

_log = logging.getLogger("cosmos.detector")

_Stat = tuple[int, int, int]  # mtime in ns, size, inode: a rename into place changes the inode


def _stat(path: Path) -> _Stat | None:
    try:
        found = path.stat()
    except OSError:
        return None
    return (found.st_mtime_ns, found.st_size, found.st_ino)


@dataclass(frozen=True)
class _Files:
    """What a scene's model looks like on disk; any change is a new model to try."""

    scene_path: Path
    scene_version: int
    model: _Stat | None
    sidecar: _Stat | None

    @classmethod
    def of(cls, scene: LoadedScene) -> _Files:
        directory = model_dir(scene)
        return cls(
            scene.path,
            scene.version,
            _stat(directory / MODEL_FILE_NAME),
            _stat(directory / SIDECAR_NAME),
        )


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as file:
        while chunk := file.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


def load_scene_model(scene: LoadedScene, *, threads: int = 0) -> DetectorModel:
    """``scene``'s own model, loaded and checked; :class:`ModelError` says why it is refused.

    Checked: the sidecar's ``sha256`` is the ONNX file's (otherwise the model is being written,
    or was replaced without its sidecar), its ``scene`` is ``scene.id``, the model passes every
    check of :class:`DetectorModel`, and its classes are the scene's object classes in order (a
    scene file edited after onboarding can change them).
    """
    directory = model_dir(scene)
    onnx, sidecar = directory / MODEL_FILE_NAME, directory / SIDECAR_NAME
    try:
        claims = json.loads(sidecar.read_text(encoding="utf-8"))
        actual = _sha256(onnx)
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ModelError(
            f"scene model {onnx} or its {SIDECAR_NAME} is not readable: {exc}"
        ) from exc
    claimed = claims.get("sha256") if isinstance(claims, dict) else None
    if claimed != actual:
        raise ModelError(
            f"scene model {onnx}: its {SIDECAR_NAME} gives sha256 {str(claimed)[:12]}, the file's "
            f"is {actual[:12]} (still being written, or replaced without its sidecar); not loaded"
        )
    if claims.get("scene") != scene.id:
        raise ModelError(
            f"scene model {onnx}: its {SIDECAR_NAME} is for scene {claims.get('scene')!r}, "
            f"not {scene.id!r}"
        )
    model = DetectorModel(onnx, threads=threads, scene=scene.id)
    if model.info.sha256 != actual or model.info.provenance.get("sha256") != actual:
        raise ModelError(f"scene model {onnx} changed while it was loaded; not loaded")
    expected = [c.label for c in object_classes(scene.spec)]
    if list(model.classes) != expected:
        raise ModelError(
            f"scene model {onnx}: its classes {list(model.classes)} are not the object classes "
            f"{expected} of scene {scene.id!r} (was the scene file edited after onboarding?)"
        )
    return model


@dataclass
class _Entry:
    """One known scene: its serving model and what the last look found."""

    classes: int
    detector: Detector | None = None
    state: SceneModelState = "none"
    error: str | None = None
    files: _Files | None = None
    looked_at: float = 0.0


class ModelRegistry:
    """The general detector and every scene's own, kept current with the files on disk.

    Use on one event loop: :meth:`start`, then :meth:`detect` and :meth:`models` from any number
    of tasks, then :meth:`close` (which leaves the general detector to its owner).
    """

    def __init__(
        self, general: Detector, catalog: SceneCatalog, settings: DetectorSettings
    ) -> None:
        self.general = general
        self.catalog = catalog
        self.settings = settings
        self._interval_s = settings.detector_scene_check_s
        # Looks run on worker threads, and the catalog is not safe to rescan from two at once.
        self._catalog_lock = threading.Lock()
        self._entries: dict[str, _Entry] = {}
        self._looks: dict[str, asyncio.Task[None]] = {}
        self._scanned_at = time.monotonic()  # the catalog scanned itself when it was made
        self._retiring: set[asyncio.Task[None]] = set()

    # -- serving -----------------------------------------------------------------------------

    def serving(self) -> int:
        """How many scenes' own models are serving."""
        return sum(1 for entry in self._entries.values() if entry.detector is not None)

    async def detector_for(self, scene_id: str | None) -> Detector:
        """The detector for ``scene_id``: its own model if one serves, else the general one."""
        if scene_id is None:
            return self.general
        look = self._start_look(scene_id)
        if look is not None:
            await asyncio.shield(look)  # a cancelled request leaves the look to finish
        entry = self._entries.get(scene_id)
        return entry.detector if entry is not None and entry.detector is not None else self.general

    async def detect(
        self,
        data: bytes,
        *,
        scene: str | None = None,
        conf: float | None = None,
        max_detections: int | None = None,
    ) -> DetectResponse:
        """:meth:`Detector.detect` with the model for ``scene``."""
        detector = await self.detector_for(scene)
        # No await between choosing the detector and its detect() counting this request in:
        # a detector being retired waits for the requests it counts, and only those.
        return await detector.detect(data, conf=conf, max_detections=max_detections)

    async def models(self) -> DetectorModels:
        """Every known scene's model status, after looking at the files of those due a look."""
        rescan = time.monotonic() - self._scanned_at >= self._interval_s
        if rescan:
            self._scanned_at = time.monotonic()
        try:
            scene_ids = await asyncio.to_thread(self._scene_ids, rescan)
        except Exception:  # a listing never fails: it shows what is known
            _log.exception("rescanning the scenes directories failed")
            scene_ids = list(self._entries)
        for scene_id in {*scene_ids, *self._entries}:  # entries of scenes gone are dropped
            self._start_look(scene_id, rescan=False)
        await asyncio.gather(*(asyncio.shield(look) for look in list(self._looks.values())))
        return DetectorModels(
            general=self.general.info,
            scenes=tuple(
                SceneModelStatus(
                    scene=scene_id,
                    state=entry.state,
                    model=entry.detector.info if entry.detector is not None else None,
                    error=entry.error,
                    classes=entry.classes,
                )
                for scene_id, entry in sorted(self._entries.items())
            ),
        )

    async def start(self) -> None:
        """Load every scene's model now, so a refused one is logged at start-up."""
        for scene_id in await asyncio.to_thread(self._scene_ids, False):
            await self._look(scene_id, rescan=False)

    async def close(self) -> None:
        """Stop looking and close every scene model (not the general one)."""
        for look in list(self._looks.values()):
            look.cancel()
        await asyncio.gather(*self._looks.values(), return_exceptions=True)
        await asyncio.gather(*self._retiring, return_exceptions=True)
        for entry in self._entries.values():
            if entry.detector is not None:
                await entry.detector.close()
        self._entries.clear()

    # -- looking at the files ----------------------------------------------------------------

    def _start_look(self, scene_id: str, *, rescan: bool = True) -> asyncio.Task[None] | None:
        """A look at ``scene_id``'s files started now, or None when it is not due (looked at
        lately, or being looked at). An unknown id rescans the scenes directories, at most once
        per interval for all unknown ids together, so made-up ids cost nothing."""
        if scene_id in self._looks:
            return None
        now = time.monotonic()
        entry = self._entries.get(scene_id)
        if entry is not None:
            if now - entry.looked_at < self._interval_s:
                return None
            entry.looked_at = now
        elif rescan:
            if now - self._scanned_at < self._interval_s:
                return None
            self._scanned_at = now
        look = asyncio.create_task(self._look(scene_id, rescan=entry is None and rescan))
        self._looks[scene_id] = look
        look.add_done_callback(lambda _: self._looks.pop(scene_id, None))
        return look

    def _scene_ids(self, rescan: bool) -> list[str]:
        """On a worker thread: the valid scenes' ids, after a rescan if ``rescan``."""
        with self._catalog_lock:
            if rescan:
                self.catalog.rescan()
            return self.catalog.ids()

    def _find(self, scene_id: str, rescan: bool) -> tuple[LoadedScene, _Files, int] | None:
        """On a worker thread: the scene (None if unknown or invalid), its model files and class
        count."""
        with self._catalog_lock:
            if rescan:
                self.catalog.rescan()
            if scene_id not in self.catalog.ids():
                return None
            try:
                scene = self.catalog.get(scene_id)  # re-read if its file changed
            except ServiceError:  # deleted or made invalid since
                return None
        return scene, _Files.of(scene), len(object_classes(scene.spec))

    async def _look(self, scene_id: str, *, rescan: bool) -> None:
        """Bring ``scene_id``'s entry up to date with its files; never raises."""
        try:
            found = await asyncio.to_thread(self._find, scene_id, rescan)
            if found is None:
                entry = self._entries.pop(scene_id, None)
                if entry is not None and entry.detector is not None:
                    _log.info("scene %s is gone: its model no longer serves", scene_id)
                    self._retire(entry.detector)
                return
            scene, files, classes = found
            entry = self._entries.setdefault(scene_id, _Entry(classes, looked_at=time.monotonic()))
            entry.classes = classes
            if files == entry.files:
                return
            entry.files = files
            if files.model is None:
                if entry.detector is not None:
                    _log.info(
                        "scene %s has no model any more: the general model serves it", scene_id
                    )
                    self._retire(entry.detector)
                entry.detector, entry.state, entry.error = None, "none", None
                return
            await self._load(entry, scene)
        except asyncio.CancelledError:
            raise
        except Exception:  # a look must never fail a request: the model serving goes on
            _log.exception("looking for scene %s's model failed", scene_id)

    async def _load(self, entry: _Entry, scene: LoadedScene) -> None:
        threads = self.settings.detector_threads
        try:
            model = await asyncio.to_thread(load_scene_model, scene, threads=threads)
        except Exception as exc:  # ModelError, or onnxruntime's own untyped errors
            message = str(exc) if isinstance(exc, ModelError) else f"{type(exc).__name__}: {exc}"
            previous = entry.detector
            if previous is not None and list(previous.model.classes) != [
                c.label for c in object_classes(scene.spec)
            ]:
                # The scene file was edited: the previous model's classes no longer fit it
                # either, and the general model at least labels what it sees truthfully.
                self._retire(previous)
                entry.detector = previous = None
            keeps = (
                f"its previous model {previous.info.sha256[:12]} keeps serving"
                if previous is not None
                else "the general model serves it"
            )
            _log.warning("refused scene %s's model: %s; %s", scene.id, message, keeps)
            entry.state, entry.error = "refused", message
            return
        detector = Detector(model, self.settings, self.general.admission)
        await detector.start()
        previous, entry.detector = entry.detector, detector
        entry.state, entry.error = "serving", None
        _log.info(
            "serving scene %s's model %s (%s, classes %s)",
            scene.id,
            model.path,
            model.info.sha256[:12],
            ", ".join(model.classes),
        )
        if previous is not None:
            self._retire(previous)

    def _retire(self, detector: Detector) -> None:
        task = asyncio.create_task(detector.retire())
        self._retiring.add(task)
        task.add_done_callback(self._retiring.discard)
