"""The ROS 2 message definitions an MCAP bag of ours needs, as ``.msg`` text (``ros2msg`` schema encoding), so that no
ROS install is needed to write one and vision_msgs (in no standard type set) travels with the file.

Each definition is one type's own fields, comments and default values left out; :func:`schema_text` appends the
definitions it depends on the way rosbag2's mcap storage writes a schema (a line of 80 ``=``, then ``MSG: pkg/Type``
and that type's fields). Field types are always fully qualified (``pkg/Type``), which every reader resolves alike.

Sources: ``common_interfaces``, ``geometry2`` (tf2_msgs) and ``rcl_interfaces`` (builtin_interfaces) as of ROS 2
Jazzy (Humble to Kilted share this wire layout; Humble's Marker lacks only the constant ``ARROW_STRIP``), and
vision_msgs 4.x (Humble and later: ``ObjectHypothesis.class_id`` a string, ``Detection3D.id``, no ``source_cloud``).
A field out of order would still encode, and decode as nonsense in ROS: change these only against the upstream files.
"""

from __future__ import annotations

#: Own fields of each type, keyed by the full type name (``pkg/msg/Type``) a schema record carries.
DEFINITIONS: dict[str, str] = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "builtin_interfaces/msg/Duration": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "std_msgs/msg/ColorRGBA": "float32 r\nfloat32 g\nfloat32 b\nfloat32 a\n",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Quaternion": "float64 x\nfloat64 y\nfloat64 z\nfloat64 w\n",
    "geometry_msgs/msg/Pose": "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
    "geometry_msgs/msg/PoseStamped": "std_msgs/Header header\ngeometry_msgs/Pose pose\n",
    "geometry_msgs/msg/PoseWithCovariance": "geometry_msgs/Pose pose\nfloat64[36] covariance\n",
    "geometry_msgs/msg/Transform": "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n",
    "geometry_msgs/msg/TransformStamped": (
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n"),
    "sensor_msgs/msg/PointField": (
        "uint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\nuint8 INT32=5\nuint8 UINT32=6\n"
        "uint8 FLOAT32=7\nuint8 FLOAT64=8\nstring name\nuint32 offset\nuint8 datatype\nuint32 count\n"),
    "sensor_msgs/msg/PointCloud2": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nsensor_msgs/PointField[] fields\nbool is_bigendian\n"
        "uint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n"),
    "sensor_msgs/msg/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n",
    "tf2_msgs/msg/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "nav_msgs/msg/Path": "std_msgs/Header header\ngeometry_msgs/PoseStamped[] poses\n",
    "visualization_msgs/msg/UVCoordinate": "float32 u\nfloat32 v\n",
    "visualization_msgs/msg/MeshFile": "string filename\nuint8[] data\n",
    "visualization_msgs/msg/Marker": (
        "int32 ARROW=0\nint32 CUBE=1\nint32 SPHERE=2\nint32 CYLINDER=3\nint32 LINE_STRIP=4\nint32 LINE_LIST=5\n"
        "int32 CUBE_LIST=6\nint32 SPHERE_LIST=7\nint32 POINTS=8\nint32 TEXT_VIEW_FACING=9\nint32 MESH_RESOURCE=10\n"
        "int32 TRIANGLE_LIST=11\nint32 ARROW_STRIP=12\nint32 ADD=0\nint32 MODIFY=0\nint32 DELETE=2\n"
        "int32 DELETEALL=3\n"
        "std_msgs/Header header\nstring ns\nint32 id\nint32 type\nint32 action\ngeometry_msgs/Pose pose\n"
        "geometry_msgs/Vector3 scale\nstd_msgs/ColorRGBA color\nbuiltin_interfaces/Duration lifetime\n"
        "bool frame_locked\ngeometry_msgs/Point[] points\nstd_msgs/ColorRGBA[] colors\nstring texture_resource\n"
        "sensor_msgs/CompressedImage texture\nvisualization_msgs/UVCoordinate[] uv_coordinates\nstring text\n"
        "string mesh_resource\nvisualization_msgs/MeshFile mesh_file\nbool mesh_use_embedded_materials\n"),
    "visualization_msgs/msg/MarkerArray": "visualization_msgs/Marker[] markers\n",
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": (
        "vision_msgs/ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n"),
    "vision_msgs/msg/BoundingBox3D": "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size\n",
    "vision_msgs/msg/Detection3D": (
        "std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\nvision_msgs/BoundingBox3D bbox\n"
        "string id\n"),
    "vision_msgs/msg/Detection3DArray": "std_msgs/Header header\nvision_msgs/Detection3D[] detections\n",
}

_SEPARATOR = "=" * 80


def _full_name(field_type: str) -> str:
    """``pkg/Type`` (as a field names it, array brackets and bounds included) → ``pkg/msg/Type``."""
    pkg, _, name = field_type.partition("[")[0].partition("/")
    return f"{pkg}/msg/{name}"


def _dependencies(name: str) -> list[str]:
    """The message types the fields of ``name`` use, in field order (constants and primitives left out)."""
    out = []
    for line in DEFINITIONS[name].splitlines():
        field_type = line.split()[0]
        if "=" not in line and "/" in field_type:
            out.append(_full_name(field_type))
    return out


def schema_text(name: str) -> str:
    """The ``ros2msg`` schema of type ``name`` (``pkg/msg/Type``): its fields, then every type it depends on, each
    once, depth first in field order (rosbag2's layout)."""
    if name not in DEFINITIONS:
        raise KeyError(f"no bundled definition of {name}")
    seen: list[str] = []

    def visit(n: str) -> None:
        for dep in _dependencies(n):
            if dep not in seen:
                seen.append(dep)
                visit(dep)

    visit(name)
    parts = [DEFINITIONS[name]]
    parts += [f"{_SEPARATOR}\nMSG: {dep.replace('/msg/', '/')}\n{DEFINITIONS[dep]}" for dep in seen]
    return "".join(parts)
