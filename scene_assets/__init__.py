"""Scene asset files made and read outside the services: PLY meshes and procedural noise.

The tools (``tools.make_assets``), the bench's random scenes (``cosmos.bench.scenes``), the
training set (``training.dataset``) and the simulator (``simulation``) share this one copy. No
service needs it (the renderer reads PLY through Mitsuba), so it sits above ``services/``.
"""

from scene_assets.noise import value_noise
from scene_assets.ply import PlyMesh, encode_ply, read_ply, read_ply_vertices, write_ply

__all__ = ["PlyMesh", "encode_ply", "read_ply", "read_ply_vertices", "value_noise", "write_ply"]
