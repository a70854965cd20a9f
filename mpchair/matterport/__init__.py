"""Read (and write) Matterport3D house annotations in the exact release format (``.house`` records, the labelled
house ``.ply``, the ``.fsegs.json``/``.semseg.json`` side files, extracted or inside ``house_segmentations.zip``) and
in habitat's layout (``mp3d/<id>/<id>_semantic.ply`` + ``.house``, the ``.navmesh``, extracted or inside
``mp3d_habitat.zip``). The result is a :class:`House` (mesh, per-face object and mpcat40 labels, objects with their
oriented and vertically aligned boxes, regions with floor polygons, levels, the navmesh), all in the raw Matterport
world frame (metres, z up).
"""

from mpchair.matterport.boxes import aligned_box, obb_from_aligned, orthonormal_axes
from mpchair.matterport.categories import CHAIR, mpcat40_name, mpcat40_table, resolve_categories, resolve_category
from mpchair.matterport.house import (
    House,
    HouseObject,
    HouseWarning,
    Level,
    Region,
    aligned_boxes,
    objects_of,
    read_house,
)
from mpchair.matterport.source import HouseSource, find_houses

__all__ = [
    "CHAIR", "House", "HouseObject", "HouseSource", "HouseWarning", "Level", "Region", "aligned_box", "aligned_boxes",
    "find_houses", "mpcat40_name", "mpcat40_table", "obb_from_aligned", "objects_of", "orthonormal_axes",
    "read_house", "resolve_categories", "resolve_category",
]  # fmt: skip
