"""ROS 1 bags, ROS 2 bags (sqlite3 or MCAP): Image or CompressedImage + PointCloud2 topics,
CameraInfo for the intrinsics and /tf_static (or a calib file) for the LiDAR's extrinsics.

Read with `rosbags` (the `[sensors]` extra), which parses every bag format and message encoding
without a ROS install; nothing here parses bytes by hand except PointCloud2's point layout, which
the message itself describes. Images pair with the scan nearest in header stamp, within
`max_dt`. Poses are written in the image's own frame (its header's frame_id).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import cv2
import numpy as np

from ..calib import Calib, parse_calib
from ..errors import D3LVOInputError
from ..extras import require
from ..geometry import make_se3, quat_to_rot, se3_inv
from .base import SensorSequence, as_scan

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
TF_TYPE = "tf2_msgs/msg/TFMessage"
# PointCloud2 PointField datatypes -> numpy
FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
INTENSITY_NAMES = ("intensity", "reflectance", "i", "remission")


@dataclass
class BagOptions:
    image_topic: str | None = None
    cloud_topic: str | None = None
    info_topic: str | None = None
    calib: Path | None = None  # KITTI-style or K + T_cam_lidar; replaces CameraInfo and /tf_static
    max_dt: float = 0.05  # s: an image and a scan further apart than this are not a frame


def is_bag(path: Path) -> bool:
    if path.is_file():
        return path.suffix in (".bag", ".mcap", ".db3")
    return path.is_dir() and (path / "metadata.yaml").is_file()


def stamp(msg) -> float:
    s = msg.header.stamp
    return s.sec + s.nanosec * 1e-9


def frame_id(msg) -> str:
    return msg.header.frame_id.lstrip("/")


def cloud_to_scan(path: Path, msg) -> np.ndarray:
    """PointCloud2 -> (N,4) float32, read through the layout the message declares."""
    fields = {f.name: f for f in msg.fields}
    if not {"x", "y", "z"} <= set(fields):
        raise D3LVOInputError(path, f"PointCloud2 fields {list(fields)} lack x, y, z")
    inten = next((n for n in INTENSITY_NAMES if n in fields), None)
    names = ["x", "y", "z"] + ([inten] if inten else [])
    bad = [n for n in names if fields[n].datatype not in FIELD_TYPES]
    if bad:
        raise D3LVOInputError(path, f"PointCloud2 field {bad[0]} has datatype {fields[bad[0]].datatype}, not one of "
                                    "ROS's numeric types 1-8")
    order = ">" if msg.is_bigendian else "<"
    dtype = np.dtype({"names": names, "formats": [order + FIELD_TYPES[fields[n].datatype] for n in names],
                      "offsets": [fields[n].offset for n in names], "itemsize": msg.point_step})
    data = np.asarray(msg.data, np.uint8)
    if data.size < msg.height * msg.row_step or msg.row_step < msg.width * msg.point_step:
        raise D3LVOInputError(path, f"a PointCloud2 of {msg.height}x{msg.width} points holds {data.size} bytes "
                                    f"(row_step {msg.row_step}, point_step {msg.point_step}): truncated")
    rows = data[: msg.height * msg.row_step].reshape(msg.height, msg.row_step)
    pts = np.frombuffer(rows[:, : msg.width * msg.point_step].tobytes(), dtype)
    xyz = np.stack([pts["x"], pts["y"], pts["z"]], -1)
    return as_scan(path, xyz, pts[inten] if inten else None)


def static_transforms(reader, connections) -> tuple[dict[tuple[str, str], np.ndarray], dict[tuple[str, str], str]]:
    """({(parent, child): T_parent_child}, {(parent, child): what is wrong}) from every /tf_static
    message: a transform with a zero or non-finite quaternion or translation is set aside, so that
    one on another branch of the tree (an IMU's) does not stop the run, and named where the chain
    the run needs is missing."""
    out, bad = {}, {}
    for conn, _, raw in reader.messages(connections=connections):
        for tf in reader.deserialize(raw, conn.msgtype).transforms:
            t, q = tf.transform.translation, tf.transform.rotation
            key = (tf.header.frame_id.lstrip("/"), tf.child_frame_id.lstrip("/"))
            quat, trans = np.array([q.w, q.x, q.y, q.z], np.float64), np.array([t.x, t.y, t.z], np.float64)
            if not (np.isfinite(quat).all() and np.isfinite(trans).all()):
                bad[key] = "a NaN or inf in its rotation or translation"
            elif not np.linalg.norm(quat) > 1e-9:
                bad[key] = "a zero-length rotation quaternion"
            else:
                out[key] = make_se3(quat_to_rot(quat), trans)
    return out, bad


def chain(transforms: dict[tuple[str, str], np.ndarray], target: str, source: str) -> np.ndarray | None:
    """T_target_source through the tree of static transforms (either direction), None if unlinked."""
    edges: dict[str, list[tuple[str, np.ndarray]]] = {}
    for (p, c), T in transforms.items():
        edges.setdefault(p, []).append((c, T))  # T_p_c: c -> p, so walking p->c multiplies by T_p_c
        edges.setdefault(c, []).append((p, se3_inv(T)))
    seen, todo = {target: np.eye(4)}, [target]
    while todo:
        a = todo.pop()
        for b, T in edges.get(a, []):
            if b not in seen:
                seen[b] = seen[a] @ T
                todo.append(b)
    return seen.get(source)


def _pick(path: Path, conns, kinds: tuple[str, ...], wanted: str | None, what: str, option: str) -> list:
    """Every connection of the one topic of these kinds (a restarted publisher is a second
    connection on the same topic); [] where there is none."""
    found = [c for c in conns if c.msgtype in kinds]
    if wanted is not None:
        hit = [c for c in conns if c.topic == wanted]
        if not hit:
            raise D3LVOInputError(path, f"no topic {wanted!r}; {what} topics here: {_topics(found)}")
        if hit[0].msgtype not in kinds:
            raise D3LVOInputError(path, f"{wanted} holds {hit[0].msgtype}, not {' or '.join(kinds)}")
        return hit
    topics = sorted({c.topic for c in found})
    if len(topics) > 1:
        raise D3LVOInputError(path, f"several {what} topics: {_topics(found)}; choose one with {option}")
    return [c for c in found if topics and c.topic == topics[0]]


def _topics(conns) -> str:
    return ", ".join(f"{c.topic} ({c.msgtype.rsplit('/', 1)[-1]}, {c.msgcount} msgs)" for c in conns) or "none"


def _nearest(sorted_t: np.ndarray, t: float) -> int:
    k = int(np.searchsorted(sorted_t, t))
    return min((j for j in (k - 1, k) if 0 <= j < len(sorted_t)), key=lambda j: abs(sorted_t[j] - t))


def pair_stamps(image_t: np.ndarray, cloud_t: np.ndarray, max_dt: float) -> list[tuple[int, int]]:
    """(image, scan) pairs that are each other's nearest in time and within max_dt: a camera
    faster than the LiDAR keeps the image closest to each scan, not the first one near it."""
    if not len(cloud_t) or not len(image_t):
        return []
    c_order, i_order = np.argsort(cloud_t), np.argsort(image_t)
    c_sorted, i_sorted = cloud_t[c_order], image_t[i_order]
    pairs = []
    for i, t in enumerate(image_t):
        j = int(c_order[_nearest(c_sorted, t)])
        back = int(i_order[_nearest(i_sorted, cloud_t[j])])
        if back == i and abs(cloud_t[j] - t) <= max_dt:
            pairs.append((i, j))
    return pairs


@dataclass
class BagSequence(SensorSequence):
    format_name: ClassVar[str] = "rosbag"
    options: BagOptions = field(default_factory=BagOptions)
    _reader: object = field(default=None, repr=False)
    _conns: tuple = field(default=(), repr=False)
    _log_times: list[tuple[int, int]] = field(default_factory=list, repr=False)  # (image, cloud) bag times, ns
    _rectify: tuple | None = field(default=None, repr=False)
    _info_size: tuple[int, int] | None = field(default=None, repr=False)  # CameraInfo's (width, height), where set

    @classmethod
    def open(cls, path: str | Path, options: BagOptions = BagOptions()) -> "BagSequence":
        require("rosbags", "rosbags.image", what="reading ROS bags")
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        path = Path(path)
        if not path.exists():
            raise D3LVOInputError(path, "bag not found")
        try:  # a path that is no bag fails already here (no metadata.yaml, an unknown suffix)
            reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            reader.open()
        except Exception as e:  # noqa: BLE001 - rosbags raises a different type per bag format
            raise D3LVOInputError(path, f"cannot be read as a ROS 1 / ROS 2 bag ({e})") from None
        conns = reader.connections
        imgs = _pick(path, conns, IMAGE_TYPES, options.image_topic, "image", "--image-topic")
        clouds = _pick(path, conns, (CLOUD_TYPE,), options.cloud_topic, "PointCloud2", "--cloud-topic")
        if not imgs or not clouds:
            missing = "Image or CompressedImage topic" if not imgs else "PointCloud2 topic"
            raise D3LVOInputError(path, f"has no {missing}; its topics: {_topics(conns)}")
        img, cloud = imgs[0], clouds[0]

        stamps: dict[str, list[tuple[int, float, str]]] = {img.topic: [], cloud.topic: []}
        for conn, t, raw in reader.messages(connections=imgs + clouds):
            msg = reader.deserialize(raw, conn.msgtype)
            stamps[conn.topic].append((t, stamp(msg), frame_id(msg)))
        im, cl = stamps[img.topic], stamps[cloud.topic]
        if not im or not cl:
            raise D3LVOInputError(path, f"{img.topic if not im else cloud.topic} holds no messages")
        im_t, cl_t = np.array([s for _, s, _ in im]), np.array([s for _, s, _ in cl])
        pairs = pair_stamps(im_t, cl_t, options.max_dt)
        if len(pairs) < 2:
            gap = min((abs(cl_t - t).min() for t in im_t), default=float("nan")) if len(cl_t) else float("nan")
            raise D3LVOInputError(path, f"{len(pairs)} of {len(im)} images on {img.topic} have a scan on "
                                        f"{cloud.topic} within {options.max_dt} s (closest: {gap:.3f} s); "
                                        "odometry needs two frames at least (--max-dt widens the tolerance)")
        cam_frame, lidar_frame = im[0][2], cl[0][2]
        calib, rectify, info_size = cls._calibration(path, reader, conns, img, options, cam_frame, lidar_frame)
        times = np.array([im_t[i] for i, _ in pairs])
        seq = cls(root=path, calib=calib, frame_names=[f"{k:06d}" for k in range(len(pairs))], times=times - times[0],
                  frame_label=f"camera frame '{cam_frame}' of {img.topic} (x right, y down, z forward)",
                  options=options, calib_path=options.calib)
        seq._reader, seq._conns = reader, (imgs, clouds)
        seq._log_times = [(im[i][0], cl[j][0]) for i, j in pairs]
        seq._rectify, seq._info_size = rectify, info_size
        return seq

    @staticmethod
    def _calibration(path, reader, conns, img, options: BagOptions, cam_frame: str, lidar_frame: str):
        if options.calib is not None:
            return parse_calib(options.calib), None, None
        infos = _pick(path, conns, (INFO_TYPE,), options.info_topic or _info_topic(conns, img.topic), "CameraInfo",
                      "--info-topic")
        first = next(iter(reader.messages(connections=infos)), None) if infos else None
        if first is None:
            raise D3LVOInputError(path, f"no CameraInfo message for {img.topic}: give the intrinsics and extrinsics "
                                        "with --calib FILE (K and T_cam_lidar, or KITTI's P2 and Tr)")
        msg = reader.deserialize(first[2], first[0].msgtype)
        K, P = np.asarray(_field(msg, "k"), float).reshape(3, 3), np.asarray(_field(msg, "p"), float).reshape(3, 4)
        if not P[:, :3].any():
            P = np.hstack([K, np.zeros((3, 1))])
        R = np.asarray(_field(msg, "r"), float).reshape(3, 3)
        R = R if R.any() else np.eye(3)  # the rectifying rotation: raw optical frame -> rectified
        rectify = None
        D = np.asarray(_field(msg, "d"), float)
        size = (int(msg.width), int(msg.height))
        if D.size and np.abs(D).max() > 0 and "rect" not in img.topic:
            # a raw image: undistort (and rectify) to P's pinhole before the network sees it
            model = msg.distortion_model
            if model in ("plumb_bob", "rational_polynomial"):
                rectify = cv2.initUndistortRectifyMap(K, D, R, P[:, :3], size, cv2.CV_32FC1)
            elif model == "equidistant":
                rectify = cv2.fisheye.initUndistortRectifyMap(K, D[:4], R, P[:, :3], size, cv2.CV_32FC1)
            else:
                raise D3LVOInputError(path, f"CameraInfo's distortion model {model!r} is not plumb_bob, "
                                            "rational_polynomial or equidistant: give a rectified image topic")
        tf_conns = [c for c in conns if c.msgtype == TF_TYPE and c.topic.endswith("tf_static")]
        tfs, bad = static_transforms(reader, tf_conns) if tf_conns else ({}, {})
        Tr = chain(tfs, cam_frame, lidar_frame) if cam_frame != lidar_frame else np.eye(4)
        if Tr is not None:  # into the rectified frame P projects from
            Tr = make_se3(R, np.zeros(3)) @ Tr
        if Tr is None:
            frames = sorted({f for pc in tfs for f in pc})
            where = f"/tf_static links no chain from '{lidar_frame}' to '{cam_frame}' (its frames: {frames}" + \
                "".join(f"; '{p}' to '{c}' set aside: {why}" for (p, c), why in bad.items()) + ")" \
                if tf_conns else "has no /tf_static"
            raise D3LVOInputError(path, f"no LiDAR-camera extrinsics: the bag {where}; give them with --calib FILE "
                                        "(K and T_cam_lidar, or KITTI's P2 and Tr)")
        return Calib(P2=P, Tr=Tr), rectify, (size if min(size) > 0 else None)

    def _message(self, k: int, i: int):
        conns, t = self._conns[k], self._log_times[i][k]
        for c, _, raw in self._reader.messages(connections=conns, start=t, stop=t + 1):
            return self._reader.deserialize(raw, c.msgtype)
        raise D3LVOInputError(self.root, f"message of frame {i} on {conns[0].topic} vanished from the bag")

    def image(self, i: int) -> np.ndarray:
        from rosbags.image import message_to_cvimage

        msg = self._message(0, i)
        try:
            rgb = message_to_cvimage(msg, "rgb8")
        except Exception as e:  # noqa: BLE001
            raise D3LVOInputError(self.root, f"frame {i}'s image on {self._conns[0][0].topic} cannot be decoded "
                                             f"({e})") from None
        if rgb.ndim == 2:
            rgb = cv2.cvtColor(rgb, cv2.COLOR_GRAY2RGB)
        if self._info_size is not None and (rgb.shape[1], rgb.shape[0]) != self._info_size:
            w, h = self._info_size
            raise D3LVOInputError(self.root, f"the CameraInfo gives {w}x{h} images, but frame {i}'s image on "
                                             f"{self._conns[0][0].topic} is {rgb.shape[1]}x{rgb.shape[0]}: its "
                                             "intrinsics are for another resolution (--calib FILE gives the right ones)")
        if self._rectify is not None:
            rgb = cv2.remap(rgb, *self._rectify, cv2.INTER_LINEAR)
        return np.ascontiguousarray(rgb)

    def scan(self, i: int) -> np.ndarray:
        return cloud_to_scan(self.root, self._message(1, i))


def _field(msg, name: str):
    """CameraInfo's matrices: k, d, r, p in ROS 2, K, D, R, P in ROS 1."""
    return getattr(msg, name) if hasattr(msg, name) else getattr(msg, name.upper())


def _info_topic(conns, image_topic: str) -> str | None:
    """The CameraInfo beside the image topic (`/cam/image_raw` -> `/cam/camera_info`, also from an
    image_transport topic `/cam/image_raw/compressed`), if there is one."""
    for transport in ("/compressed", "/compressedDepth", "/theora", "/zstd"):
        if image_topic.endswith(transport):
            image_topic = image_topic[: -len(transport)]
            break
    ns = image_topic.rsplit("/", 1)[0]
    infos = [c.topic for c in conns if c.msgtype == INFO_TYPE]
    near = [t for t in infos if t.rsplit("/", 1)[0] == ns]
    return near[0] if len(near) == 1 else None
