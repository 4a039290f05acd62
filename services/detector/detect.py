"""Detection end to end: image bytes -> letterboxed tensor -> model -> boxes in image pixels.

:func:`detections_from_output` is the pure post-processing of one image;
:class:`Detector` runs requests concurrently (PNG and JPEG decoding and post-processing on worker
threads, inference through the :class:`~services.detector.batching.MicroBatcher`) and bounds how
many are in flight and the memory their decoded images take
(:class:`~services.detector.admission.Admission`).
"""

from __future__ import annotations

import asyncio
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Final

import numpy as np
from numpy.typing import NDArray

from services.common.contracts.detect import Detection, DetectResponse, ModelInfo
from services.common.images import (
    PPM_MEDIA_TYPE,
    checked_header,
    decode_image,
    media_type_of,
    read_header,
)
from services.detector.admission import Admission, DecodeBudget
from services.detector.batching import Finish, MicroBatcher
from services.detector.colour import measure_colour
from services.detector.letterbox import Letterbox, letterbox
from services.detector.model import DetectorModel
from services.detector.postprocess import Candidates, decode_output, nms
from services.detector.settings import DetectorSettings
from services.detector.tiles import Tile, merged, tile_grid, wants_tiles

__all__ = [
    "SCENE_CROSS_CLASS_IOU",
    "DetectOptions",
    "Detector",
    "detections_from_output",
    "detections_of",
    "image_candidates",
    "tile_inputs",
]


SCENE_CROSS_CLASS_IOU: Final = 0.7
"""A scene's own model has one class per object, so two of its classes on nearly the same box
(IoU above this) are one object labelled twice, not two objects: a real object hidden behind
another has a visible box far smaller than its occluder's. The general model's shape classes
keep per-class NMS only: there the optimizer explains such pairs (one object, two shapes)."""


@dataclass(frozen=True)
class DetectOptions:
    """Post-processing knobs (see :class:`~services.detector.settings.DetectorSettings`)."""

    conf: float = 0.25
    iou: float = 0.5
    max_detections: int = 100
    max_candidates: int = 5000
    colour: bool = True
    cross_class_iou: float | None = None
    """Boxes of different classes overlapping more than this are one object: the less
    confident goes (None: classes never suppress each other)."""

    @classmethod
    def from_settings(
        cls, settings: DetectorSettings, *, scene_model: bool = False
    ) -> DetectOptions:
        """The settings' knobs; a scene's own model also suppresses across classes
        (:data:`SCENE_CROSS_CLASS_IOU`)."""
        return cls(
            conf=settings.detector_conf,
            iou=settings.detector_iou,
            max_detections=settings.detector_max_detections,
            max_candidates=settings.detector_max_candidates,
            colour=settings.detector_colour,
            cross_class_iou=SCENE_CROSS_CLASS_IOU if scene_model else None,
        )


def image_candidates(
    output: NDArray[np.floating], box: Letterbox, options: DetectOptions
) -> Candidates:
    """The candidates at or over ``options.conf`` in the model's output ``(4 + C, N)`` for one
    input, best first, their boxes mapped back to image pixels through ``box`` and clipped to
    the image (boxes left empty, i.e. lying in the padding, dropped)."""
    candidates = decode_output(output, options.conf, options.max_candidates)
    boxes = box.to_image(candidates.boxes)
    valid = (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
    return Candidates(boxes[valid], candidates.scores[valid], candidates.class_ids[valid])


def detections_of(
    candidates: Candidates,
    classes: Sequence[str],
    rgb: NDArray[np.uint8] | None,
    image_size: tuple[int, int],
    options: DetectOptions,
) -> tuple[Detection, ...]:
    """NMS (per class, and across classes with ``options.cross_class_iou``) of one image's
    ``candidates`` (best first), keeping at most ``options.max_detections``, with each box's
    mean colour measured in ``rgb`` (the image of ``image_size`` pixels, or the image decoded
    shrunk) unless ``rgb`` is None or colours are off."""
    kept = nms(candidates, options.iou, options.max_detections, options.cross_class_iou)
    detections = []
    shrunk = 1.0 if rgb is None else rgb.shape[1] / image_size[0]  # a shrunk decode's
    for xyxy, score, class_id in zip(kept.boxes, kept.scores, kept.class_ids, strict=True):
        corners = (float(xyxy[0]), float(xyxy[1]), float(xyxy[2]), float(xyxy[3]))
        colour = None
        if options.colour and rgb is not None:
            x1, y1, x2, y2 = (v * shrunk for v in corners)
            colour = measure_colour(rgb, (x1, y1, x2, y2))
        detections.append(
            Detection(
                label=classes[int(class_id)],
                class_id=int(class_id),
                confidence=min(1.0, max(0.0, float(score))),
                box=corners,
                color=colour,
            )
        )
    return tuple(detections)


def detections_from_output(
    output: NDArray[np.floating],
    box: Letterbox,
    classes: Sequence[str],
    rgb: NDArray[np.uint8] | None,
    options: DetectOptions,
) -> tuple[Detection, ...]:
    """The detections in one image from the model's output ``(4 + C, N)`` for it:
    :func:`image_candidates`, then :func:`detections_of`. ``rgb`` (the image, or the image
    decoded shrunk: ``box`` maps to the whole one) is needed for colours."""
    candidates = image_candidates(output, box, options)
    return detections_of(candidates, classes, rgb, box.image_size, options)


def tile_inputs(
    rgb: NDArray[np.uint8], box: Letterbox, n: int
) -> list[tuple[NDArray[np.float32], Letterbox, Tile]]:
    """The network inputs of the ``n x n`` tiles of ``rgb`` (the image ``box`` maps, or the
    image decoded shrunk), each with the letterbox that maps its boxes to the tile in the
    image's pixels and that tile."""
    shrink = box.image_size[0] // rgb.shape[1]  # exact: a shrunk decode divides the sides
    inputs = []
    for x0, y0, x1, y1 in tile_grid((rgb.shape[1], rgb.shape[0]), n):  # decoded pixels
        tensor, tile_box = letterbox(rgb[y0:y1, x0:x1], box.input_size)
        size = ((x1 - x0) * shrink, (y1 - y0) * shrink)
        tile = (x0 * shrink, y0 * shrink, x1 * shrink, y1 * shrink)
        inputs.append((tensor, replace(tile_box, image_size=size), tile))
    return inputs


class Detector:
    """Serves detections with one model: admission, decoding, batching, post-processing.

    Detectors of several models share one :class:`Admission` when it is given.
    """

    def __init__(
        self, model: DetectorModel, settings: DetectorSettings, admission: Admission | None = None
    ) -> None:
        self.model = model
        self.settings = settings
        self.options = DetectOptions.from_settings(
            settings, scene_model=model.info.scene is not None
        )
        fixed = model.max_batch
        self.batcher = MicroBatcher(
            model.run,
            max_batch=settings.detector_max_batch if fixed is None else fixed,
            window_s=settings.detector_batch_window_ms / 1000.0,
        )
        self.admission = admission or Admission(
            settings.detector_max_in_flight,
            DecodeBudget(settings.detector_max_decode_bytes, settings.detector_decode_wait_s),
        )
        self.active = 0
        """This model's requests under way (what :meth:`retire` waits for)."""

    @property
    def info(self) -> ModelInfo:
        return self.model.info

    @property
    def in_flight(self) -> int:
        """Requests under way in the service (every detector sharing the admission)."""
        return self.admission.in_flight

    async def start(self) -> None:
        await self.batcher.start()

    async def close(self) -> None:
        await self.batcher.close()

    async def retire(self, poll_s: float = 0.05) -> None:
        """Close once the requests already handed to this model are answered (a newer model
        serves the rest): closing the batcher earlier would fail them."""
        while self.active:
            await asyncio.sleep(poll_s)
        await self.close()

    def _prepare(self, data: bytes) -> tuple[NDArray[np.uint8], NDArray[np.float32], Letterbox]:
        """The decoded image, the network input and the letterbox that maps boxes back to the
        image's pixels. A JPEG at least twice the input's size (or as many times as the tiles
        across, when the image is tiled: :mod:`~services.detector.tiles`) is decoded already
        shrunk by libjpeg (:func:`~services.common.images.decode_image`: 2, 4 or 8 times,
        exactly): the letterbox of the shrunk image is the whole one's, its boxes scaled to the
        whole image; the array returned is the shrunk one. A 4000 x 3000 photo decoded in 21 ms
        instead of 93 ms, and its input is less aliased (``INTER_LINEAR`` from 1000 x 750, not
        4000 x 3000)."""
        in_w, in_h = self.model.layout.input_size
        header = read_header(data)
        across = 2
        if wants_tiles((header.width, header.height), (in_w, in_h), self.settings.detector_tiles):
            across = max(across, self.settings.detector_tiles)
        rgb = decode_image(
            data,
            max_pixels=self.settings.detector_max_image_pixels,
            max_side=self.settings.detector_max_image_side,
            at_least=(across * in_w, across * in_h),
        )
        tensor, box = letterbox(rgb, (in_w, in_h))
        return rgb, tensor, replace(box, image_size=(header.width, header.height))

    async def detect(
        self, data: bytes, *, conf: float | None = None, max_detections: int | None = None
    ) -> DetectResponse:
        """Detect objects in PNG, JPEG or binary PPM bytes; ``conf`` and ``max_detections``
        override the settings for this call."""
        self.admission.admit()
        self.active += 1  # before any await: see retire()
        try:
            header = checked_header(
                data,
                max_pixels=self.settings.detector_max_image_pixels,
                max_side=self.settings.detector_max_image_side,
            )
            options = replace(
                self.options,
                conf=self.options.conf if conf is None else conf,
                max_detections=max_detections or self.options.max_detections,
            )
            async with self.admission.decode.hold(header):
                detections, box, run_ms = await self._detect(data, options)
        finally:
            self.active -= 1
            self.admission.release()
        return DetectResponse(
            detections=detections,
            image_size=box.image_size,
            model=self.model.info,
            inference_ms=run_ms,
        )

    async def _detect(
        self, data: bytes, options: DetectOptions
    ) -> tuple[tuple[Detection, ...], Letterbox, float]:
        """Decode, infer, post-process; the decoded pixels are gone when this returns. A large
        image is also detected tile by tile (:mod:`~services.detector.tiles`); its run time is
        then the longest of its inputs' runs (they share a batch when the model's is dynamic)."""
        # A binary PPM needs no codec: decoding and letterboxing it here costs less than the
        # thread hop that keeps a PNG or JPEG decode off the event loop.
        rgb, tensor, box = (
            self._prepare(data)
            if media_type_of(data) == PPM_MEDIA_TYPE
            else await asyncio.to_thread(self._prepare, data)
        )
        classes = self.model.classes
        if not wants_tiles(box.image_size, box.input_size, self.settings.detector_tiles):
            detections, run_ms = await self.batcher.submit(
                tensor, lambda output: detections_from_output(output, box, classes, rgb, options)
            )
            return detections, box, run_ms
        tiled = await asyncio.to_thread(tile_inputs, rgb, box, self.settings.detector_tiles)
        inputs = [(tensor, box, (0, 0, *box.image_size)), *tiled]

        def placed(box_: Letterbox, tile: Tile) -> Finish:
            def finish(output: NDArray[np.floating]) -> Candidates:
                found = image_candidates(output, box_, options)
                offset = np.array([tile[0], tile[1], tile[0], tile[1]], dtype=np.float64)
                return Candidates(found.boxes + offset, found.scores, found.class_ids)

            return finish

        runs = await asyncio.gather(*(self.batcher.submit(t, placed(b, at)) for t, b, at in inputs))
        whole, *parts = (candidates for candidates, _ in runs)
        by_tile = [(tile, part) for (_, _, tile), part in zip(inputs[1:], parts, strict=True)]
        candidates = merged(whole, by_tile, box.image_size, box.scale[0])
        detections = await asyncio.to_thread(
            detections_of, candidates, classes, rgb, box.image_size, options
        )
        return detections, box, max(ms for _, ms in runs)
