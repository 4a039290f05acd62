"""The messages between the stages, one module per stage.

========================  =================================================================
Module                    Messages
========================  =================================================================
:mod:`.render`            the renderer's: render requests, annotations, scene summaries
:mod:`.detect`            the detector's: detections, model descriptions, health
:mod:`.optimize`          the optimizer's: next-pose requests and answers, object mapping
:mod:`.search`            the controller's public API: searches, iterations, results
========================  =================================================================

Poses, the grid, the pinhole camera and the scene file are geometry, shared by all stages:
:mod:`services.common.geometry`. :class:`~services.common.base.FrozenModel` and the constrained
types all messages share are :mod:`services.common.base`, below both. This package re-exports
nothing, so importing one stage's messages never imports another's.
"""
