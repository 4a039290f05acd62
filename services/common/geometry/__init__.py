"""Geometry every stage shares: poses, the hemisphere grid, the pinhole camera, the scene file.

========================  =================================================================
Module                    What it holds
========================  =================================================================
:mod:`.pose`              :class:`~.pose.Pose`, :class:`~.pose.GridIndex`, :class:`~.pose.PoseQuery`
:mod:`.sphere`            camera positions of poses and back, angles between poses
:mod:`.grid`              :class:`~.grid.GridSpec` (the one grid type) and
                          :class:`~.grid.HemisphereGrid` (its rings, indices and neighbours)
:mod:`.camera`            :class:`~.camera.PinholeCamera` and projection to and from pixels
:mod:`.scene`             the scene file: :class:`~.scene.SceneSpec` and its loader
========================  =================================================================
"""
