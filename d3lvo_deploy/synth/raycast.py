"""The one ray engine behind the synthetic camera and LiDAR (Intel Embree through embreex)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MISS = 1e30


@dataclass
class Hits:
    t: np.ndarray  # distance along the (not necessarily unit) direction; inf on a miss
    prim: np.ndarray  # triangle index, -1 on a miss
    u: np.ndarray  # barycentric weights of vertices 1 and 2
    v: np.ndarray
    normal: np.ndarray  # (N,3) geometric normal, unnormalised

    @property
    def hit(self) -> np.ndarray:
        return self.prim >= 0


class RayCaster:
    """Embree scene over one triangle mesh; `cast` takes (N,3) origins and directions."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        from ..extras import require

        require("embreex", what="the synthetic world (d3lvo synth, d3lvo demo)")
        from embreex.mesh_construction import TriangleMesh  # imported here: only the generator needs it
        from embreex.rtcore_scene import EmbreeScene

        self._scene = EmbreeScene()
        self._mesh = TriangleMesh(self._scene, np.ascontiguousarray(vertices, dtype=np.float32),
                                  np.ascontiguousarray(faces, dtype=np.int32))

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        o = np.ascontiguousarray(np.broadcast_to(origins, directions.shape), dtype=np.float32)
        d = np.ascontiguousarray(directions, dtype=np.float32)
        r = self._scene.run(o, d, output=1)
        prim = r["primID"].astype(np.int64)
        t = r["tfar"].astype(np.float64)
        t[prim < 0] = np.inf
        return Hits(t, prim, r["u"], r["v"], r["Ng"])

    def occluded(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        o = np.ascontiguousarray(origins, dtype=np.float32)
        d = np.ascontiguousarray(directions, dtype=np.float32)
        return self._scene.run(o, d, query="OCCLUDED") >= 0  # embreex: -1 means the ray got through
