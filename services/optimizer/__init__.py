"""COSMOS 3D Search: optimizer — object mapping and next-best-pose strategies.

The domain code is importable without FastAPI: :func:`~.mapping.map_exact` and
:func:`~.mapping.map_paper` (paper §3.2), :func:`~.longitude.solve_rotation` (the longitude
solve), :data:`~.strategies.STRATEGIES` and :func:`~.strategies.plan_next` (§3.3 and ours).
The offline simulator that plays them without renderer or detector is :mod:`simulation`.
The service is :mod:`services.optimizer.app`.
"""
