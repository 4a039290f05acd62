"""The scene catalog: finds scene files in the scenes directories and keeps them validated.

Directories are searched in order and the first file with a given id wins, so directories named in
``COSMOS_SCENES_DIR`` (searched first) can override a built-in scene. A file that fails validation
does not stop the service: it is listed as invalid and asking for it answers with its error.
"""

from __future__ import annotations

import logging
import re
import threading
from collections.abc import Sequence
from pathlib import Path

from services.common.errors import NotFoundError, UnprocessableError
from services.common.geometry.scene import SCENE_ID_PATTERN, LoadedScene, SceneFileError, load_scene

__all__ = ["BUILTIN_SCENES_DIR", "SceneCatalog"]

BUILTIN_SCENES_DIR = Path(__file__).resolve().parents[2] / "scenes"
_SUFFIXES = (".yaml", ".yml")
_log = logging.getLogger("cosmos.renderer")


class SceneCatalog:
    """Validated scenes by id, re-read when a file changes and rescanned for unknown ids."""

    def __init__(self, directories: Sequence[Path]) -> None:
        self.directories = tuple(directories)
        self._lock = threading.Lock()
        self._files: dict[str, Path] = {}
        self._scenes: dict[str, LoadedScene] = {}
        self._errors: dict[str, SceneFileError] = {}
        self.rescan()

    def rescan(self) -> None:
        """Find every scene file again and (re)validate the ones that changed."""
        files: dict[str, Path] = {}
        for directory in self.directories:
            if not directory.is_dir():
                _log.warning("scenes directory %s does not exist", directory)
                continue
            for path in sorted(directory.iterdir()):
                if path.suffix in _SUFFIXES and path.is_file() and path.stem not in files:
                    files[path.stem] = path
        with self._lock:
            self._files = files
            self._scenes = {k: v for k, v in self._scenes.items() if files.get(k) == v.path}
            self._errors = {k: v for k, v in self._errors.items() if k in files}
        for scene_id in files:
            self._load(scene_id)

    def _load(self, scene_id: str) -> LoadedScene | SceneFileError:
        path = self._files[scene_id]
        cached = self._scenes.get(scene_id)
        try:
            mtime = path.stat().st_mtime_ns
        except OSError as exc:
            return SceneFileError(path, None, f"cannot read the file ({exc})")
        if cached is not None and cached.version == mtime:
            return cached
        try:
            scene = load_scene(path)
        except SceneFileError as exc:
            _log.warning("invalid scene file: %s", exc)
            with self._lock:
                self._errors[scene_id] = exc
                self._scenes.pop(scene_id, None)
            return exc
        with self._lock:
            self._scenes[scene_id] = scene
            self._errors.pop(scene_id, None)
        return scene

    def ids(self) -> list[str]:
        """Ids of the valid scenes, sorted."""
        return sorted(self._scenes)

    def invalid(self) -> dict[str, str]:
        """Invalid scene files: id -> error message."""
        return {scene_id: str(error) for scene_id, error in sorted(self._errors.items())}

    def get(self, scene_id: str) -> LoadedScene:
        """The scene ``scene_id``; :class:`NotFoundError` if there is no such file,
        :class:`UnprocessableError` if its file is invalid."""
        valid_id = re.match(SCENE_ID_PATTERN, scene_id) is not None
        if valid_id and (scene_id not in self._files or not self._files[scene_id].is_file()):
            self.rescan()  # a new file, or a deleted one that another directory may still hold
        if scene_id not in self._files:
            known = ", ".join(self.ids()) or "none"
            raise NotFoundError(
                f"unknown scene {scene_id!r} (known: {known})",
                field="scene",
                slug="unknown-scene",
                title="Unknown scene",
            )
        result = self._load(scene_id)
        if isinstance(result, SceneFileError):
            raise UnprocessableError(
                str(result), field="scene", slug="invalid-scene-file", title="Invalid scene file"
            )
        return result
