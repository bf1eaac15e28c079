"""Vehicles that drive in the synthetic street: what a learned confidence has to learn to ignore.

Each vehicle is a rigid mesh in its own frame (boxes: body, glass, and for trucks a cab) with one
pose per frame, placed on the street by arc length s along the driven path and a lateral offset:
a lead car at the ego speed, vehicles overtaking and being overtaken in the next lane, oncoming
traffic in the leftmost lane, and crossing traffic over the road ahead. The camera and the LiDAR
see the static world and the vehicles at their poses of the same frame, and the true motion of
every surface point is the vehicle's motion, so motion masks and optical flow come out exact.
Everything is a function of the seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .raycast import RayCaster
from .world import CAR, GLASS, Mesh, Path2D, StreetStyle, add_box

KINDS = ("lead", "overtaking", "overtaken", "oncoming", "crossing")
# the ego car around cam0 on the ground plane, (x0, x1, z0, z1) in metres, x right and z forward:
# KITTI's car (1.8 m wide, 4.8 m long, the cameras on its roof ahead of the middle) rounded up
EGO_FOOTPRINT = (-1.0, 1.0, -3.5, 1.5)
CLEARANCE = 0.3  # m kept between a vehicle and the ego car


@dataclass(frozen=True)
class Vehicle:
    kind: str
    mesh: dict[str, np.ndarray]  # Mesh.arrays() in the vehicle frame (x right, y down, z forward)
    poses: np.ndarray  # (frames, 4, 4) vehicle frame -> world


def vehicle_mesh(rng: np.random.Generator, truck: bool) -> dict[str, np.ndarray]:
    """A car (body + glass cabin) or a truck (cab + box), centred on its footprint, facing +z."""
    mesh = Mesh()
    fwd, up = np.array([0.0, 0.0, 1.0]), np.array([0.0, -1.0, 0.0])
    colour = rng.uniform(0.05, 0.9, 3)
    if truck:
        length, width = float(rng.uniform(6.5, 9.0)), 2.45
        cab = 2.2
        add_box(mesh, up * 0.35 + fwd * (length - cab) / 2, fwd, (cab, width, 2.4), CAR, colour)
        add_box(mesh, up * 0.35 - fwd * cab / 2, fwd, (length - cab, width, float(rng.uniform(2.6, 3.2))), CAR,
                rng.uniform(0.3, 0.9, 3), variant=float(rng.uniform(0.0, 1.0)))
    else:
        body = (float(rng.uniform(3.8, 4.8)), 1.75, float(rng.uniform(0.8, 1.0)))
        add_box(mesh, up * 0.25, fwd, body, CAR, colour)
        add_box(mesh, up * (0.25 + body[2]) - fwd * 0.3, fwd, (body[0] * 0.5, 1.55, 0.5), GLASS,
                (0.1, 0.12, 0.15), top_material=CAR)
    return mesh.arrays()


def on_street(path: Path2D, s: np.ndarray, lateral: np.ndarray, heading: str) -> np.ndarray:
    """(N,4,4) poses at arc lengths s and lateral offsets: facing along the path ("along"), against
    it ("against") or across it to the right ("across")."""
    k = np.clip(s, path.s[0], path.s[-1])
    ground = np.stack([np.interp(k, path.s, path.ground[:, j]) for j in range(3)], -1)
    t = np.stack([np.interp(k, path.s, path.tangent[:, j]) for j in range(3)], -1)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    right = np.stack([t[:, 2], np.zeros(len(t)), -t[:, 0]], -1)
    fwd = {"along": t, "against": -t, "across": right}[heading]
    x = np.stack([fwd[:, 2], np.zeros(len(t)), -fwd[:, 0]], -1)  # vehicle x: its right
    T = np.tile(np.eye(4), (len(s), 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = x, np.array([0.0, 1.0, 0.0]), fwd
    T[:, :3, 3] = ground + right * np.asarray(lateral, np.float64)[:, None]
    return T


def ego_arc_length(path: Path2D, poses: np.ndarray) -> np.ndarray:
    """Arc length of each frame's ground point along the path (the path starts `behind` the first)."""
    g = poses[:, :3, 3][:, [0, 2]]
    d = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(g, axis=0), axis=1))])
    k0 = int(np.argmin(np.linalg.norm(path.ground[:, [0, 2]] - g[0], axis=1)))
    return path.s[k0] + d


def plan_traffic(path: Path2D, st: StreetStyle, poses: np.ndarray, density: float,
                 rng: np.random.Generator, clear_ego: bool = True) -> list[Vehicle]:
    """About `density` moving vehicles per 100 m of the street (the driven road and the stretches
    seen behind and ahead of it), the kinds in turn; schedules put every vehicle beside or in front
    of the camera at some time during the drive. With `clear_ego`, none that runs into the camera's
    own car (`meets_ego`)."""
    s_ego = ego_arc_length(path, poses)
    n = len(poses)
    t = np.arange(n) * 0.1
    count = int(round(density * float(path.s[-1] - path.s[0]) / 100.0))
    kinds = [KINDS[i % len(KINDS)] for i in range(count)]
    rng.shuffle(kinds)
    leads = kinds.count("lead")
    if leads:  # one lead car: a second would sit on the first
        kinds = ["lead"] + [k for k in kinds if k != "lead"] + ["overtaken"] * (leads - 1)
    next_lane = -st.lane
    far_lane = -st.lane * st.left_lanes
    out = []
    for kind in kinds:
        mesh = vehicle_mesh(rng, truck=bool(rng.uniform() < 0.3))
        when = float(rng.uniform(0.1, 0.9)) * t[-1]  # when it is beside or in front of the camera
        if kind == "lead":
            s, lat, heading = s_ego + float(rng.uniform(9.0, 18.0)), np.zeros(n), "along"
        elif kind == "overtaking":  # faster, in the next lane, level with the camera at `when`
            dv = float(rng.uniform(2.0, 5.0))
            s, lat, heading = s_ego + dv * (t - when), np.full(n, next_lane), "along"
        elif kind == "overtaken":  # slower, in the next lane, ahead until the camera passes it
            dv = float(rng.uniform(1.5, 4.0))
            s, lat, heading = s_ego + 12.0 - dv * (t - when), np.full(n, next_lane), "along"
        elif kind == "oncoming":
            v = float(rng.uniform(7.0, 13.0))
            meet = np.interp(when, t, s_ego)
            s, lat, heading = meet - v * (t - when), np.full(n, far_lane), "against"
        else:  # crossing the road 20-35 m ahead of where the camera is at `when`
            v = float(rng.uniform(4.0, 8.0))
            s = np.full(n, np.interp(when, t, s_ego) + float(rng.uniform(20.0, 35.0)))
            lat, heading = v * (t - when), "across"
        vehicle = Vehicle(kind, mesh, on_street(path, s, lat, heading))
        # a schedule that runs the vehicle into the camera's own car (the driven path can pass a
        # stretch of street twice, or an oncoming lane cut a corner) is dropped, after its draws,
        # so that the vehicles after it are those of the same seed
        if not (clear_ego and meets_ego(vehicle, poses)):
            out.append(vehicle)
    return out


def _rectangles(poses: np.ndarray, footprint: tuple[float, float, float, float]) -> tuple[np.ndarray, ...]:
    """Per frame, on the ground plane (world x, z): the centre (n,2) of the footprint (x0, x1, z0,
    z1) of a frame whose x is right and z forward, its unit right and forward axes (n,2), and its
    half extents (2,)."""
    x0, x1, z0, z1 = footprint
    right, fwd = poses[:, [0, 2], 0], poses[:, [0, 2], 2]
    right = right / np.linalg.norm(right, axis=1, keepdims=True)
    fwd = fwd / np.linalg.norm(fwd, axis=1, keepdims=True)
    centre = poses[:, [0, 2], 3] + right * (x0 + x1) / 2 + fwd * (z0 + z1) / 2
    return centre, right, fwd, np.array([(x1 - x0) / 2, (z1 - z0) / 2])


def meets_ego(vehicle: Vehicle, poses: np.ndarray, clearance: float = CLEARANCE) -> bool:
    """Whether the vehicle's footprint, grown by `clearance`, overlaps the ego car's
    (`EGO_FOOTPRINT` around the camera poses, (n,4,4)) in any frame: two rectangles on the ground
    plane overlap unless one of their four axes separates them."""
    v = vehicle.mesh["vertices"]
    lo, hi = v.min(0), v.max(0)
    grown = (lo[0] - clearance, hi[0] + clearance, lo[2] - clearance, hi[2] + clearance)
    ca, ua, wa, ha = _rectangles(poses, EGO_FOOTPRINT)
    cb, ub, wb, hb = _rectangles(vehicle.poses, grown)
    d = cb - ca
    apart = np.zeros(len(poses), bool)
    for axis in (ua, wa, ub, wb):
        apart |= np.abs((d * axis).sum(1)) > _reach(ua, wa, ha, axis) + _reach(ub, wb, hb, axis)
    return bool((~apart).any())


def _reach(right: np.ndarray, fwd: np.ndarray, half: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """How far a rectangle (axes (n,2), half extents (2,)) reaches from its centre along `axis` (n,2)."""
    return half[0] * np.abs((right * axis).sum(1)) + half[1] * np.abs((fwd * axis).sum(1))


def world_at(static: dict[str, np.ndarray], vehicles: list[Vehicle], frame: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The static mesh plus every vehicle at `frame`, and each triangle's owner (-1 static, k vehicle k)."""
    parts, owner = [static], [np.full(len(static["faces"]), -1)]
    base = len(static["vertices"])
    for k, v in enumerate(vehicles):
        T = v.poses[frame]
        m = dict(v.mesh)
        m["vertices"] = (m["vertices"].astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
        m["faces"] = m["faces"] + base
        base += len(m["vertices"])
        parts.append(m)
        owner.append(np.full(len(m["faces"]), k))
    world = {key: np.concatenate([p[key] for p in parts]) for key in static}
    return world, np.concatenate(owner)


def point_motion(vehicles: list[Vehicle], owner: np.ndarray, points: np.ndarray, frame: int,
                 to_frame: int) -> np.ndarray:
    """Where world points on their owners at `frame` are at `to_frame` (static points stay)."""
    out = np.array(points, dtype=np.float64)
    for k, v in enumerate(vehicles):
        sel = owner == k
        if sel.any():
            M = v.poses[to_frame] @ np.linalg.inv(v.poses[frame])
            out[sel] = out[sel] @ M[:3, :3].T + M[:3, 3]
    return out


def movers_mesh(vehicles: list[Vehicle], moving: np.ndarray, frame: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of the vehicles flagged in `moving`, at `frame`."""
    verts, faces, base = [np.zeros((0, 3), np.float32)], [np.zeros((0, 3), np.int64)], 0
    for v, m in zip(vehicles, moving):
        if m:
            T = v.poses[frame]
            verts.append((v.mesh["vertices"].astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(np.float32))
            faces.append(v.mesh["faces"] + base)
            base += len(v.mesh["vertices"])
    return np.concatenate(verts), np.concatenate(faces)


def shadow_change(hits: dict, pixel_moves: np.ndarray, vehicles: list[Vehicle], moving: np.ndarray,
                  sun: np.ndarray, frame: int, static: RayCaster | None = None) -> np.ndarray:
    """(H,W) True where a surface that stays put changes its shading between `frame` and the next
    because a moving vehicle's shadow moves over it. Such a pixel moves in the image with the vehicle,
    not with the camera, though no geometry there moves: the solver must not trust it either.
    `hits`: `sensors.render_camera`'s for `frame`; pixel_moves (H,W): the pixel sees a moving vehicle;
    `static`: the world without vehicles, whose shadow (like a vehicle's that stands still) keeps
    a surface dark whatever passes between it and the sun."""
    shape = pixel_moves.shape
    out = np.zeros(shape[0] * shape[1], bool)
    sel = np.isfinite(hits["shadow_origin"][:, 0]) & (hits["lit"] > 0) & ~pixel_moves.reshape(-1)
    if not sel.any() or not np.any(moving):
        return out.reshape(shape)
    rays = np.ascontiguousarray(np.broadcast_to(sun, (int(sel.sum()), 3)))
    standing = [RayCaster(*movers_mesh(vehicles, ~np.asarray(moving, bool), frame))] if not np.all(moving) else []
    for caster in ([static] if static is not None else []) + standing:
        sel[sel] = ~caster.occluded(hits["shadow_origin"][sel], rays)
        rays = rays[: int(sel.sum())]
    if not sel.any():
        return out.reshape(shape)
    origins = hits["shadow_origin"][sel]
    now, then = (RayCaster(*movers_mesh(vehicles, moving, f)).occluded(origins, rays) for f in (frame, frame + 1))
    out[sel] = now != then
    return out.reshape(shape)
