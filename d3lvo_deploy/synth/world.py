"""A procedural street built around a camera trajectory, as one triangle mesh.

The road follows the path the camera drives (so any trajectory, real or synthetic, stays on a
road): a cross-section profile (lanes, kerbs, sidewalks, verges) swept along the path, with
facades, trees, poles and parked cars placed beside it and kept off the driven path.
Every triangle carries a material and every vertex metric texture coordinates, so shading is a
function of world position and stays put from frame to frame (what optical flow needs).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

CAMERA_HEIGHT = 1.65  # m, KITTI cam0 above the road

# materials
SKY, ASPHALT, KERB, SIDEWALK, VERGE, FACADE, CAR, GLASS, POLE, FOLIAGE, TRUNK, ROOF = range(12)


@dataclass
class Mesh:
    vertices: list[np.ndarray] = field(default_factory=list)
    faces: list[np.ndarray] = field(default_factory=list)
    uv: list[np.ndarray] = field(default_factory=list)
    material: list[np.ndarray] = field(default_factory=list)
    colour: list[np.ndarray] = field(default_factory=list)
    variant: list[np.ndarray] = field(default_factory=list)
    _count: int = 0

    def add(self, v: np.ndarray, f: np.ndarray, uv: np.ndarray, material: int | np.ndarray,
            colour: np.ndarray, variant: float = 0.0) -> None:
        f = np.asarray(f, dtype=np.int64)
        self.vertices.append(np.asarray(v, dtype=np.float64))
        self.faces.append(f + self._count)
        self.uv.append(np.asarray(uv, dtype=np.float64))
        self.material.append(np.broadcast_to(np.asarray(material, dtype=np.int32), (len(f),)).copy())
        self.colour.append(np.broadcast_to(np.asarray(colour, dtype=np.float32), (len(f), 3)).copy())
        self.variant.append(np.full(len(f), variant, dtype=np.float32))
        self._count += len(v)

    def arrays(self) -> dict[str, np.ndarray]:
        return {
            "vertices": np.concatenate(self.vertices).astype(np.float32),
            "faces": np.concatenate(self.faces).astype(np.int32),
            "uv": np.concatenate(self.uv).astype(np.float32),
            "material": np.concatenate(self.material),
            "colour": np.concatenate(self.colour),
            "variant": np.concatenate(self.variant),
        }


@dataclass(frozen=True)
class Path2D:
    """The driven path resampled every metre: ground points, unit tangents and right vectors."""

    s: np.ndarray  # arc length (m)
    ground: np.ndarray  # (K,3) road surface under the camera
    tangent: np.ndarray  # (K,3) horizontal
    right: np.ndarray  # (K,3) horizontal, pointing to the camera's right
    curvature: np.ndarray  # (K,) signed, 1/m, positive turning right


def build_path(poses: np.ndarray, ahead: float = 90.0, behind: float = 25.0, step: float = 1.0) -> Path2D:
    """Resample the camera path by arc length and extend it so the camera always sees road ahead."""
    cam = poses[:, :3, 3]
    fwd = poses[:, :3, 2]
    ground = cam + np.array([0.0, CAMERA_HEIGHT, 0.0])
    seg = np.linalg.norm(np.diff(ground[:, [0, 2]], axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-3])
    g = ground[keep]
    head0 = _flat(fwd[0])
    head1 = _flat(fwd[-1])
    pre = g[0] - head0 * np.arange(behind, 0, -step)[:, None]
    post = g[-1] + head1 * np.arange(step, ahead + step, step)[:, None]
    g = np.concatenate([pre, g, post])
    d = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(g[:, [0, 2]], axis=0), axis=1))])
    s = np.arange(0.0, d[-1], step)
    pts = np.stack([np.interp(s, d, g[:, k]) for k in range(3)], -1)
    # smooth heights (GT has centimetre jitter) and headings
    pts[:, 1] = _smooth(pts[:, 1], 9)
    tan = np.gradient(pts, axis=0)
    tan[:, 1] = 0.0
    tan = np.stack([_smooth(tan[:, 0], 5), tan[:, 1], _smooth(tan[:, 2], 5)], -1)
    tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-9)
    right = np.stack([tan[:, 2], np.zeros(len(tan)), -tan[:, 0]], -1)
    heading = np.unwrap(np.arctan2(tan[:, 0], tan[:, 2]))
    curvature = np.gradient(heading) / step
    return Path2D(s, pts, tan, right, curvature)


def _flat(v: np.ndarray) -> np.ndarray:
    v = np.array([v[0], 0.0, v[2]])
    n = np.linalg.norm(v)
    return v / n if n > 1e-9 else np.array([0.0, 0.0, 1.0])


def _smooth(x: np.ndarray, w: int) -> np.ndarray:
    if len(x) < w:
        return x
    k = np.ones(w) / w
    pad = np.pad(x, w // 2, mode="edge")
    return np.convolve(pad, k, mode="valid")


@dataclass(frozen=True)
class StreetStyle:
    lane: float = 3.5
    left_lanes: int = 1  # lanes left of the ego lane
    park_left: float = 2.2
    park_right: float = 2.2
    kerb: float = 0.14
    sidewalk: float = 3.0
    verge: float = 30.0

    @classmethod
    def random(cls, rng: np.random.Generator) -> "StreetStyle":
        return cls(
            lane=float(rng.uniform(3.2, 3.7)),
            left_lanes=int(rng.integers(1, 3)),
            park_left=float(rng.choice([0.0, 2.2])),
            park_right=float(rng.choice([0.0, 2.2, 2.2])),
            sidewalk=float(rng.uniform(2.0, 4.0)),
        )

    @property
    def road_right(self) -> float:
        return self.lane / 2 + self.park_right

    @property
    def road_left(self) -> float:
        return -(self.lane / 2 + self.lane * self.left_lanes + self.park_left)


def _profile(st: StreetStyle) -> list[tuple[float, float, int]]:
    """Cross-section (lateral offset, height, material of the strip starting here), left to right."""
    rl, rr, k = st.road_left, st.road_right, st.kerb
    return [
        (rl - st.sidewalk - st.verge, k - 0.1, VERGE),
        (rl - st.sidewalk, k, SIDEWALK),
        (rl, k, KERB),
        (rl, 0.0, ASPHALT),
        (rr, 0.0, KERB),
        (rr, k, SIDEWALK),
        (rr + st.sidewalk, k, VERGE),
        (rr + st.sidewalk + st.verge, k - 0.1, -1),
    ]


def add_street(mesh: Mesh, path: Path2D, st: StreetStyle) -> None:
    prof = _profile(st)
    lat = np.array([p[0] for p in prof])
    hgt = np.array([p[1] for p in prof])
    # keep the inner side of tight turns from folding over: clamp offsets to the local radius
    radius = 1.0 / np.maximum(np.abs(path.curvature), 1e-6)
    radius = _running_min(radius, 15)
    inner_right = path.curvature > 0
    K, P = len(path.s), len(prof)
    L = np.broadcast_to(lat, (K, P)).copy()
    lim = 0.85 * radius
    L[inner_right] = np.minimum(L[inner_right], lim[inner_right, None])
    L[~inner_right] = np.maximum(L[~inner_right], -lim[~inner_right, None])
    up = np.array([0.0, -1.0, 0.0])
    V = path.ground[:, None, :] + path.right[:, None, :] * L[..., None] + up * hgt[None, :, None]
    # texture coords: (arc length, lateral offset); kerb faces use height across
    U = np.broadcast_to(path.s[:, None], (K, P))
    idx = np.arange(K * P).reshape(K, P)
    for j in range(P - 1):
        mat = prof[j][2]
        a, b, c, d = idx[:-1, j], idx[:-1, j + 1], idx[1:, j], idx[1:, j + 1]
        faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
        colour = {ASPHALT: (0.32, 0.32, 0.33), KERB: (0.62, 0.61, 0.58), SIDEWALK: (0.55, 0.52, 0.50),
                  VERGE: (0.30, 0.36, 0.20)}[mat]
        # one vertex set per strip so uv can differ at shared edges (kerb faces use height as v)
        sub_idx = np.unique(faces)
        remap = np.full(K * P, -1)
        remap[sub_idx] = np.arange(len(sub_idx))
        verts = V.reshape(-1, 3)[sub_idx]
        is_face = np.isclose(lat[j], lat[j + 1])
        across = np.broadcast_to(hgt, (K, P)) if is_face else L
        uvs = np.stack([U.reshape(-1)[sub_idx], across.reshape(-1)[sub_idx]], 1)
        mesh.add(verts, remap[faces], uvs, KERB if is_face else mat, colour)


def _running_min(x: np.ndarray, half: int) -> np.ndarray:
    pad = np.pad(x, half, mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(pad, 2 * half + 1)
    return windows.min(axis=1)


def add_box(mesh: Mesh, centre: np.ndarray, tangent: np.ndarray, size: tuple[float, float, float],
            material: int, colour, variant: float = 0.0, top_material: int | None = None) -> None:
    """Axis = (along tangent, across, up); `centre` is the middle of the footprint on the ground."""
    t = np.asarray(tangent, dtype=np.float64)
    r = np.array([t[2], 0.0, -t[0]])
    up = np.array([0.0, -1.0, 0.0])
    lx, ly, lz = size
    corners = []
    for sx, sy, sz in [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0), (-1, -1, 1), (1, -1, 1), (1, 1, 1), (-1, 1, 1)]:
        corners.append(centre + t * sx * lx / 2 + r * sy * ly / 2 + up * sz * lz)
    c = np.array(corners)
    # each face gets its own 4 vertices: (a, b, c, d) counter-clockwise, uv in metres
    quads = [((0, 1, 5, 4), lx), ((1, 2, 6, 5), ly), ((2, 3, 7, 6), lx), ((3, 0, 4, 7), ly)]
    for q, w in quads:
        v = c[list(q)]
        uv = np.array([[0, 0], [w, 0], [w, lz], [0, lz]], dtype=np.float64)
        mesh.add(v, [[0, 1, 2], [0, 2, 3]], uv, material, colour, variant)
    v = c[[4, 5, 6, 7]]
    uv = np.array([[0, 0], [lx, 0], [lx, ly], [0, ly]], dtype=np.float64)
    mesh.add(v, [[0, 1, 2], [0, 2, 3]], uv, ROOF if top_material is None else top_material, colour, variant)


def _clear_of_path(path: Path2D, centre: np.ndarray, tangent: np.ndarray, size: tuple[float, float, float],
                   clearance: float) -> bool:
    """True if the box footprint stays `clearance` metres away from every path point."""
    t = np.asarray(tangent)
    r = np.array([t[2], 0.0, -t[0]])
    gx = np.linspace(-0.5, 0.5, 5)
    pts = np.array([centre + t * a * size[0] + r * b * size[1] for a in gx for b in gx])
    d = np.linalg.norm((path.ground[None, :, [0, 2]] - pts[:, None, [0, 2]]), axis=2)
    return bool(d.min() > clearance)


def build_world(poses: np.ndarray, seed: int) -> tuple[dict[str, np.ndarray], Path2D, StreetStyle]:
    rng = np.random.default_rng(seed)
    path = build_path(poses)
    st = StreetStyle.random(rng)
    mesh = Mesh()
    add_street(mesh, path, st)
    keep_road = st.lane / 2 + 0.3  # nothing may come closer to the driven line than this

    def place(s: float, lateral: float) -> tuple[np.ndarray, np.ndarray]:
        k = min(int(s), len(path.s) - 1)
        return path.ground[k] + path.right[k] * lateral, path.tangent[k]

    up = np.array([0.0, -1.0, 0.0])
    for side in (-1.0, 1.0):
        kerb_lat = st.road_right if side > 0 else st.road_left
        outer = kerb_lat + side * st.sidewalk
        # facades
        s = float(rng.uniform(0, 8))
        while s < path.s[-1]:
            width = float(rng.uniform(8, 24))
            depth = float(rng.uniform(8, 14))
            height = float(rng.uniform(5, 20))
            setback = float(rng.choice([0.0, rng.uniform(0.5, 6.0)]))
            c, t = place(s + width / 2, outer + side * (setback + depth / 2))
            c = c + up * st.kerb
            size = (width, depth, height)
            if _clear_of_path(path, c, t, size, keep_road + st.sidewalk):
                colour = rng.uniform([0.45, 0.35, 0.3], [0.85, 0.8, 0.75])
                add_box(mesh, c, t, size, FACADE, colour, variant=float(rng.uniform(2.2, 3.6)))
            s += width + float(rng.choice([0.0, rng.uniform(2, 10)]))
        # trees and poles on the sidewalk
        s = float(rng.uniform(0, 10))
        while s < path.s[-1]:
            lat = kerb_lat + side * float(rng.uniform(0.6, max(0.7, st.sidewalk - 0.8)))
            c, t = place(s, lat)
            c = c + up * st.kerb
            if rng.uniform() < 0.5:
                size = (0.22, 0.22, float(rng.uniform(4, 8)))
                if _clear_of_path(path, c, t, size, keep_road):
                    add_box(mesh, c, t, size, POLE, (0.5, 0.5, 0.52))
                    plate = c + up * (size[2] - 0.9)
                    add_box(mesh, plate, t, (0.05, 0.7, 0.7), POLE, rng.uniform(0.2, 0.9, 3), 0.0)
            else:
                trunk_h = float(rng.uniform(1.8, 3.0))
                crown = float(rng.uniform(2.0, 4.0))
                if _clear_of_path(path, c, t, (crown, crown, 1.0), keep_road):
                    add_box(mesh, c, t, (0.3, 0.3, trunk_h), TRUNK, (0.35, 0.25, 0.18))
                    add_box(mesh, c + up * trunk_h, t, (crown, crown, crown * 0.8), FOLIAGE,
                            rng.uniform([0.15, 0.3, 0.1], [0.3, 0.5, 0.2]), top_material=FOLIAGE)
            s += float(rng.uniform(8, 30))
        # parked cars along the kerb
        park = st.park_right if side > 0 else st.park_left
        s = float(rng.uniform(0, 10))
        while s < path.s[-1]:
            if park > 0 or rng.uniform() < 0.3:
                lat = kerb_lat - side * 1.05
                c, t = place(s, lat)
                body = (float(rng.uniform(3.8, 4.8)), 1.75, float(rng.uniform(0.8, 1.0)))
                if _clear_of_path(path, c, t, body, 1.9):
                    colour = rng.uniform(0.05, 0.9, 3)
                    lift = c + up * 0.25
                    add_box(mesh, lift, t, body, CAR, colour)
                    add_box(mesh, lift + up * body[2] - t * 0.3, t, (body[0] * 0.5, 1.55, 0.5), GLASS,
                            (0.1, 0.12, 0.15), top_material=CAR)
            s += float(rng.uniform(5.5, 14))
    return mesh.arrays(), path, st
