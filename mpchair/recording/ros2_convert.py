"""Our arrays as ROS 2 messages: plain dicts shaped like the definitions in :mod:`mpchair.recording.ros2_msgs`, which
the CDR encoder of mcap-ros2-support takes as they are.

Frames and units are ROS's (REP 103: x forward, y left, z up, metres, radians), which our sensor frame already is, so
nothing is converted: a scan's bytes go into a PointCloud2 unchanged and a box ``[x, y, z, l, w, h, yaw]`` (geometric
centre, ``l`` along the heading, yaw CCW about +z) becomes a centre pose and a size ``(l, w, h)`` along the box's own
axes. Stamps are integer microseconds (``times.txt``), written as ``sec`` + ``nanosec``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mpchair.geometry import BOX_EDGES, box_corners

#: sensor_msgs/PointField.FLOAT32
_FLOAT32 = 7
_POINT_FIELDS = ("x", "y", "z", "intensity")
#: visualization_msgs/Marker types and actions
_LINE_LIST, _TEXT_VIEW_FACING, _ADD, _DELETEALL = 5, 9, 0, 3
LINE_WIDTH_M = 0.02
TEXT_HEIGHT_M = 0.15

Color = tuple[int, int, int]


def stamp(time_us: int) -> dict:
    """builtin_interfaces/Time of a time in integer microseconds."""
    t = int(time_us)
    return {"sec": t // 1_000_000, "nanosec": (t % 1_000_000) * 1000}


def header(time_us: int, frame_id: str) -> dict:
    """std_msgs/Header."""
    return {"stamp": stamp(time_us), "frame_id": frame_id}


def _point(p) -> dict:
    return {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])}


def _yaw_quaternion(yaw: float) -> dict:
    """geometry_msgs/Quaternion of a rotation by ``yaw`` radians CCW about +z."""
    return {"x": 0.0, "y": 0.0, "z": float(np.sin(yaw / 2)), "w": float(np.cos(yaw / 2))}


def quaternion(R: np.ndarray) -> dict:
    """geometry_msgs/Quaternion of a (3,3) rotation matrix (Shepperd's method: the largest diagonal term first, so
    no branch divides by a small number); ``w >= 0``."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    k = int(np.argmax([tr, R[0, 0], R[1, 1], R[2, 2]]))
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + tr)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, s / 4]
    elif k == 1:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [s / 4, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif k == 2:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 1] + R[1, 0]) / s, s / 4, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, s / 4, (R[1, 0] - R[0, 1]) / s]
    q = np.array(q) * (1.0 if q[3] >= 0 else -1.0)
    return {"x": float(q[0]), "y": float(q[1]), "z": float(q[2]), "w": float(q[3])}


def point_cloud(points: np.ndarray, time_us: int, frame_id: str) -> dict:
    """sensor_msgs/PointCloud2 of (N,4) points ``x, y, z, intensity`` (a velodyne file's rows): one row of N
    little-endian float32 points, 16 bytes each; ``data`` is the velodyne file's bytes."""
    data = np.ascontiguousarray(points, dtype="<f4").reshape(-1, 4)
    return {"header": header(time_us, frame_id), "height": 1, "width": len(data),
            "fields": [{"name": n, "offset": 4 * i, "datatype": _FLOAT32, "count": 1}
                       for i, n in enumerate(_POINT_FIELDS)],
            "is_bigendian": False, "point_step": 16, "row_step": 16 * len(data), "data": data.tobytes(),
            "is_dense": bool(np.isfinite(data).all())}


def transform(T: np.ndarray, time_us: int, parent: str, child: str) -> dict:
    """geometry_msgs/TransformStamped of a (4,4) rigid transform child → parent (tf's ``parent`` → ``child``)."""
    T = np.asarray(T, dtype=np.float64)
    return {"header": header(time_us, parent), "child_frame_id": child,
            "transform": {"translation": _point(T[:3, 3]), "rotation": quaternion(T[:3, :3])}}


def pose(T: np.ndarray) -> dict:
    """geometry_msgs/Pose of a (4,4) rigid transform."""
    T = np.asarray(T, dtype=np.float64)
    return {"position": _point(T[:3, 3]), "orientation": quaternion(T[:3, :3])}


def path(poses: np.ndarray, times_us: Sequence[int], frame_id: str) -> dict:
    """nav_msgs/Path through (K,4,4) poses in ``frame_id`` captured at ``times_us``, stamped at the first."""
    return {"header": header(times_us[0], frame_id),
            "poses": [{"header": header(t, frame_id), "pose": pose(T)} for T, t in zip(poses, times_us)]}


def _box_pose(box: np.ndarray) -> dict:
    return {"position": _point(box[:3]), "orientation": _yaw_quaternion(float(box[6]))}


def detections(boxes: np.ndarray, names: Sequence[str], scores: Sequence[float], time_us: int,
               frame_id: str) -> dict:
    """vision_msgs/Detection3DArray of (N,7) boxes in ``frame_id``: per box one hypothesis (class ``names[i]``,
    ``scores[i]``) posed at the box centre, and the box (centre pose, size ``l, w, h`` along its own axes)."""
    h = header(time_us, frame_id)
    out = []
    for b, n, s in zip(np.asarray(boxes, dtype=np.float64).reshape(-1, 7), names, scores):
        centre = _box_pose(b)
        out.append({"header": h, "id": "",
                    "results": [{"hypothesis": {"class_id": str(n), "score": float(s)},
                                 "pose": {"pose": centre, "covariance": [0.0] * 36}}],
                    "bbox": {"center": centre, "size": {"x": float(b[3]), "y": float(b[4]), "z": float(b[5])}}})
    return {"header": h, "detections": out}


def _rgba(color: Color, alpha: float = 1.0) -> dict:
    return {"r": color[0] / 255, "g": color[1] / 255, "b": color[2] / 255, "a": alpha}


def markers(boxes: np.ndarray, colors: Sequence[Color], texts: Sequence[str] | None, time_us: int,
            frame_id: str) -> dict:
    """visualization_msgs/MarkerArray drawing (N,7) boxes in ``frame_id`` as wireframes in ``colors[i]`` (one
    LINE_LIST of the 12 edges each, namespace ``boxes``) with an optional text above each (``labels``; an empty text
    draws none). It starts with a DELETEALL, so a viewer shows exactly this frame's boxes."""
    h = header(time_us, frame_id)
    identity = {"position": _point((0, 0, 0)), "orientation": _yaw_quaternion(0.0)}
    out = [{"header": h, "ns": "", "id": 0, "action": _DELETEALL, "pose": identity}]
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    edges = box_corners(b)[:, BOX_EDGES].reshape(len(b), -1, 3) if len(b) else np.zeros((0, 24, 3))
    for i, (seg, color) in enumerate(zip(edges, colors)):
        out.append({"header": h, "ns": "boxes", "id": i, "type": _LINE_LIST, "action": _ADD, "pose": identity,
                    "scale": {"x": LINE_WIDTH_M, "y": 0.0, "z": 0.0}, "color": _rgba(color),
                    "points": [_point(p) for p in seg]})
    for i, text in enumerate(texts or []):
        if not text:
            continue
        top = {"position": _point(b[i, :3] + [0.0, 0.0, b[i, 5] / 2 + TEXT_HEIGHT_M]),
               "orientation": _yaw_quaternion(0.0)}
        out.append({"header": h, "ns": "labels", "id": i, "type": _TEXT_VIEW_FACING, "action": _ADD, "pose": top,
                    "scale": {"x": 0.0, "y": 0.0, "z": TEXT_HEIGHT_M}, "color": _rgba(colors[i]),
                    "text": str(text)})
    return {"markers": out}
