"""Read and write habitat's ``<id>.navmesh``: a Recast/Detour "MSET" tile set, with numpy alone (no habitat-sim).

Layout (little-endian; ``../shared/docs/habitat-layout.md`` §1.7, habitat-sim ``PathFinder::Impl::saveNavMesh``)::

    set header (40 B)      int magic 'MSET', int version (1; 2 from habitat-sim 0.2.2), int numTiles,
                           dtNavMeshParams: float orig[3], tileWidth, tileHeight; int maxTiles, maxPolys
    version 2 only (56 B)  NavMeshSettings: 13 floats (cellSize ... detailSampleMaxError), 4 bools
    per tile               uint tileRef, int dataSize; then dataSize bytes of Detour tile data:
      dtMeshHeader (100 B) 15 ints (magic 'DNAV', version 7, x, y, layer, userId, polyCount, vertCount, maxLinkCount,
                           detailMeshCount, detailVertCount, detailTriCount, bvNodeCount, offMeshConCount,
                           offMeshBase), floats walkableHeight, walkableRadius, walkableClimb, bmin[3], bmax[3],
                           bvQuantFactor
      arrays               verts (12 B), polys (32 B dtPoly), links (12 B), detailMeshes (12 B), detailVerts (12 B),
                           detailTris (4 B), bvTree (16 B), offMeshCons (36 B) — each a multiple of 4 bytes

Coordinates in the file are in habitat's y-up run-time frame (the navmesh was built on the rotated ``.glb``);
:func:`read_navmesh` returns them in the Matterport world frame (z up, metres) through
:func:`mpchair.geometry.habitat_to_mp3d`, and :func:`encode_navmesh` converts back with ``mp3d_to_habitat``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mpchair.core.errors import InputError
from mpchair.geometry import habitat_to_mp3d, mp3d_to_habitat

MSET_MAGIC = 0x4D534554  # 'MSET'
MSET_VERSIONS = (1, 2)
DNAV_MAGIC = 0x444E4156  # 'DNAV'
DNAV_VERSION = 7
#: dtPoly flags habitat sets: walkable, door, disabled (zero-area polygons, at load), off-island.
POLY_WALK, POLY_DOOR, POLY_DISABLED, POLY_OFF_ISLAND = 0x01, 0x02, 0x04, 0x08
#: A ``neis`` entry with this bit links to a polygon of another tile.
EXT_LINK = 0x8000
MAX_VERTS_PER_POLY = 6
#: habitat's NavMeshSettings field names (version-2 files), in file order.
SETTINGS_FIELDS = (
    "cell_size", "cell_height", "agent_height", "agent_radius", "agent_max_climb", "agent_max_slope",
    "region_min_size", "region_merge_size", "edge_max_len", "edge_max_error", "verts_per_poly", "detail_sample_dist",
    "detail_sample_max_error",
)  # fmt: skip

_SET_HEADER = np.dtype([("magic", "<i4"), ("version", "<i4"), ("num_tiles", "<i4"), ("orig", "<f4", (3,)),
                        ("tile_width", "<f4"), ("tile_height", "<f4"), ("max_tiles", "<i4"), ("max_polys", "<i4")])
_SETTINGS = np.dtype([(n, "<f4") for n in SETTINGS_FIELDS] + [("flags", "u1", (4,))])
_TILE_HEADER = np.dtype([("ref", "<u4"), ("size", "<i4")])
_MESH_HEADER = np.dtype(
    [(n, "<i4") for n in ("magic", "version", "x", "y", "layer", "user_id", "poly_count", "vert_count",
                          "max_link_count", "detail_mesh_count", "detail_vert_count", "detail_tri_count",
                          "bv_node_count", "off_mesh_con_count", "off_mesh_base")]
    + [("walkable_height", "<f4"), ("walkable_radius", "<f4"), ("walkable_climb", "<f4"), ("bmin", "<f4", (3,)),
       ("bmax", "<f4", (3,)), ("bv_quant_factor", "<f4")]
)  # fmt: skip
_POLY = np.dtype([("first_link", "<u4"), ("verts", "<u2", (6,)), ("neis", "<u2", (6,)), ("flags", "<u2"),
                  ("vert_count", "u1"), ("area_and_type", "u1")])
_DETAIL_MESH = np.dtype([("vert_base", "<u4"), ("tri_base", "<u4"), ("vert_count", "u1"), ("tri_count", "u1"),
                         ("pad", "V2")])
_BV_NODE = np.dtype([("bmin", "<u2", (3,)), ("bmax", "<u2", (3,)), ("i", "<i4")])
_LINK_BYTES, _OFF_MESH_BYTES = 12, 36
assert (_SET_HEADER.itemsize, _SETTINGS.itemsize, _MESH_HEADER.itemsize, _POLY.itemsize, _DETAIL_MESH.itemsize,
        _BV_NODE.itemsize) == (40, 56, 100, 32, 12, 16)  # fmt: skip


@dataclass(frozen=True, eq=False)
class NavMesh:
    """A navmesh as stored, in the Matterport world frame (z up, metres), all tiles merged.

    ``vertices (V,3) float64`` polygon corners; ``poly_vertices (P,6) int64`` indices into ``vertices`` (-1 padding)
    with ``poly_vert_count (P,)``; ``poly_flags (P,) uint16`` (``POLY_*``), ``poly_area (P,)`` (0 ground, 1 door),
    ``poly_type (P,)`` (0 ground polygon, 1 off-mesh connection); ``links (E,2) int64`` pairs of polygons that share
    an edge (``i < j``, across tiles too); ``triangles (T,3,3) float64`` the detail triangles that make up the
    walkable surface, ``triangle_poly (T,)`` their polygon. ``version`` is the MSET version, ``settings`` habitat's
    NavMeshSettings (version 2, else ``None``), ``walkable_height/radius/climb`` the first tile's agent (metres).
    """

    version: int
    settings: dict[str, float] | None
    walkable_height: float
    walkable_radius: float
    walkable_climb: float
    vertices: np.ndarray
    poly_vertices: np.ndarray
    poly_vert_count: np.ndarray
    poly_flags: np.ndarray
    poly_area: np.ndarray
    poly_type: np.ndarray
    links: np.ndarray
    triangles: np.ndarray
    triangle_poly: np.ndarray


class _Reader:
    """Bounds-checked little-endian reads over the file bytes; errors name the file and what was being read."""

    def __init__(self, data: bytes | bytearray | memoryview, path: str):
        self.data, self.path, self.pos = data, path, 0
        self.end = len(data)
        self.tile = False  # reading inside a tile: self.end is its declared end

    def array(self, dtype: np.dtype | str, count: int, what: str) -> np.ndarray:
        dtype = np.dtype(dtype)
        if count < 0:
            raise InputError(f"navmesh {what}: negative count {count}", self.path)
        n = dtype.itemsize * count
        if self.pos + n > self.end:
            if self.tile:
                raise InputError(f"navmesh {what} needs {n} bytes at offset {self.pos}, beyond its tile's declared "
                                 f"end at {self.end}", self.path)  # fmt: skip
            raise InputError(f"navmesh is truncated: {what} needs {n} bytes at offset {self.pos}, file has "
                             f"{len(self.data) - self.pos} left", self.path)  # fmt: skip
        out = np.frombuffer(self.data, dtype=dtype, count=count, offset=self.pos)
        self.pos += n
        return out


def read_navmesh(data: bytes | bytearray | memoryview, path: str = "<navmesh>") -> NavMesh:
    """Parse a habitat ``.navmesh`` (module docstring) into a :class:`NavMesh` in the Matterport world frame.

    Raises :class:`InputError` for a wrong magic or version (file or tile), a truncated file, a tile whose arrays do
    not add up to its declared size, out-of-range polygon or detail indices, non-finite coordinates and trailing bytes.
    """
    r = _Reader(data, path)
    head = r.array(_SET_HEADER, 1, "header")[0]
    if int(head["magic"]) != MSET_MAGIC:
        raise InputError(f"not a habitat navmesh (magic {int(head['magic']) & 0xFFFFFFFF:#010x}, expected 'MSET' "
                         f"{MSET_MAGIC:#010x})", path)  # fmt: skip
    version = int(head["version"])
    if version not in MSET_VERSIONS:
        raise InputError(f"unsupported navmesh version {version} (habitat writes 1 or 2)", path)
    settings = None
    if version == 2:
        s = r.array(_SETTINGS, 1, "NavMeshSettings")[0]
        settings = {n: float(s[n]) for n in SETTINGS_FIELDS}
    n_tiles = int(head["num_tiles"])
    if n_tiles < 0 or n_tiles > 1 << 20:
        raise InputError(f"navmesh declares {n_tiles} tiles", path)
    verts, polys, tris, tri_poly, ext_edges = [], [], [], [], []
    agent = (0.0, 0.0, 0.0)
    n_verts = n_polys = 0
    for k in range(n_tiles):
        th = r.array(_TILE_HEADER, 1, f"tile {k} header")[0]
        size = int(th["size"])
        if int(th["ref"]) == 0 or size <= 0:
            break  # Detour's saver stops at an empty tile
        end = r.pos + size
        if end > len(data):
            raise InputError(f"navmesh is truncated: tile {k} declares {size} bytes at offset {r.pos}, file has "
                             f"{len(data) - r.pos} left", path)  # fmt: skip
        r.end, r.tile = end, True
        t = _read_tile(r, k, path)
        r.end, r.tile = len(data), False
        if r.pos != end:
            raise InputError(f"navmesh tile {k} declares {size} bytes but its header's arrays take "
                             f"{size + r.pos - end}", path)  # fmt: skip
        if k == 0:
            agent = (t["walkable_height"], t["walkable_radius"], t["walkable_climb"])
        v, p = t["verts"], t["polys"]
        pv = p["verts"].astype(np.int64)
        pv[np.arange(6)[None, :] >= p["vert_count"][:, None]] = -1
        verts.append(v)
        polys.append((np.where(pv >= 0, pv + n_verts, -1), p, n_polys))
        tris.append(t["tris"])
        tri_poly.append(t["tri_poly"] + n_polys)
        ext_edges.append(t["ext_edges"] + np.array([n_polys, n_verts, n_verts]))
        n_verts += len(v)
        n_polys += len(p)
    if r.pos != len(data):
        raise InputError(f"navmesh has {len(data) - r.pos} bytes after its last tile (at offset {r.pos})", path)

    vertices = habitat_to_mp3d(np.concatenate(verts)) if verts else np.zeros((0, 3))
    poly_vertices = np.concatenate([pv for pv, _, _ in polys]) if polys else np.zeros((0, 6), np.int64)
    p_all = np.concatenate([p for _, p, _ in polys]) if polys else np.zeros(0, _POLY)
    links = []
    for _, p, base in polys:
        nei = p["neis"].astype(np.int64)
        internal = (nei > 0) & (nei & EXT_LINK == 0) & (np.arange(6)[None, :] < p["vert_count"][:, None])
        a, e = np.nonzero(internal)
        b = nei[a, e] - 1
        if len(b) and b.max() >= len(p):
            raise InputError(f"navmesh polygon {int(a[b >= len(p)][0]) + base} links to polygon "
                             f"{int(b.max())} of {len(p)}", path)  # fmt: skip
        links.append(np.column_stack([a + base, b + base]))
    links.append(_match_external_edges(np.concatenate(ext_edges) if ext_edges else np.zeros((0, 3), np.int64),
                                       vertices))  # fmt: skip
    lk = np.concatenate(links) if links else np.zeros((0, 2), np.int64)
    lk = np.unique(np.sort(lk, axis=1), axis=0) if len(lk) else np.zeros((0, 2), np.int64)
    triangles = habitat_to_mp3d(np.concatenate(tris).reshape(-1, 3)).reshape(-1, 3, 3) if tris else np.zeros((0, 3, 3))
    if not (np.isfinite(vertices).all() and np.isfinite(triangles).all()):
        raise InputError("navmesh has a non-finite vertex", path)
    return NavMesh(
        version=version, settings=settings, walkable_height=agent[0], walkable_radius=agent[1],
        walkable_climb=agent[2], vertices=vertices, poly_vertices=poly_vertices,
        poly_vert_count=p_all["vert_count"].astype(np.int64), poly_flags=p_all["flags"].copy(),
        poly_area=(p_all["area_and_type"] & 0x3F).astype(np.uint8),
        poly_type=(p_all["area_and_type"] >> 6).astype(np.uint8), links=lk, triangles=triangles,
        triangle_poly=np.concatenate(tri_poly) if tri_poly else np.zeros(0, np.int64),
    )  # fmt: skip


def _read_tile(r: _Reader, k: int, path: str) -> dict:
    """One Detour tile at ``r.pos``: its header values, vertices (habitat frame), polygons, detail triangles."""
    h = r.array(_MESH_HEADER, 1, f"tile {k} mesh header")[0]
    if int(h["magic"]) != DNAV_MAGIC:
        raise InputError(f"navmesh tile {k}: bad Detour magic {int(h['magic']) & 0xFFFFFFFF:#010x} (expected 'DNAV')",
                         path)  # fmt: skip
    if int(h["version"]) != DNAV_VERSION:
        raise InputError(f"navmesh tile {k}: Detour data version {int(h['version'])}, expected {DNAV_VERSION}", path)
    c = {n: int(h[n]) for n in _MESH_HEADER.names[:15]}
    verts = r.array("<f4", 3 * c["vert_count"], f"tile {k} vertices").reshape(-1, 3).astype(np.float64)
    polys = r.array(_POLY, c["poly_count"], f"tile {k} polygons")
    r.array("u1", _LINK_BYTES * c["max_link_count"], f"tile {k} links")
    dmeshes = r.array(_DETAIL_MESH, c["detail_mesh_count"], f"tile {k} detail meshes")
    dverts = r.array("<f4", 3 * c["detail_vert_count"], f"tile {k} detail vertices").reshape(-1, 3)
    dtris = r.array("u1", 4 * c["detail_tri_count"], f"tile {k} detail triangles").reshape(-1, 4)
    r.array(_BV_NODE, c["bv_node_count"], f"tile {k} BV tree")
    r.array("u1", _OFF_MESH_BYTES * c["off_mesh_con_count"], f"tile {k} off-mesh connections")

    nv = len(verts)
    vc = polys["vert_count"].astype(np.int64)
    if len(polys) and (vc.max() > MAX_VERTS_PER_POLY):
        raise InputError(f"navmesh tile {k}: a polygon has {int(vc.max())} vertices (at most 6)", path)
    used = np.arange(6)[None, :] < vc[:, None]
    if used.any() and polys["verts"][used].max() >= nv:
        raise InputError(f"navmesh tile {k}: a polygon uses vertex {int(polys['verts'][used].max())} of {nv}", path)
    if c["detail_mesh_count"] > len(polys):
        raise InputError(f"navmesh tile {k}: {c['detail_mesh_count']} detail meshes for {len(polys)} polygons", path)

    # Detail triangles: a corner index below the polygon's vertCount is a polygon vertex, any other is detail vertex
    # vertBase + (index - vertCount).
    n_tri = dmeshes["tri_count"].astype(np.int64)
    tri_base = dmeshes["tri_base"].astype(np.int64)
    if len(dmeshes) and (tri_base + n_tri).max() > len(dtris):
        raise InputError(f"navmesh tile {k}: detail triangles beyond the {len(dtris)} stored", path)
    poly_of_tri = np.repeat(np.arange(len(dmeshes)), n_tri)
    tri_index = np.repeat(tri_base, n_tri) + (np.arange(n_tri.sum()) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri))
    corners = dtris[tri_index, :3].astype(np.int64)
    pvc = vc[poly_of_tri][:, None]
    vbase = dmeshes["vert_base"].astype(np.int64)[poly_of_tri][:, None]
    is_poly = corners < pvc
    if (~is_poly).any() and (vbase + corners - pvc)[~is_poly].max() >= len(dverts):
        raise InputError(f"navmesh tile {k}: a detail triangle uses a detail vertex beyond the {len(dverts)} stored",
                         path)  # fmt: skip
    if is_poly.any() and corners[is_poly].max() >= MAX_VERTS_PER_POLY:
        raise InputError(f"navmesh tile {k}: bad detail triangle corner", path)
    pverts = polys["verts"].astype(np.int64)[poly_of_tri[:, None], np.minimum(corners, 5)]
    tri = verts[np.where(is_poly, pverts, 0)] if nv else np.zeros((*corners.shape, 3))
    tri[~is_poly] = dverts[(vbase + corners - pvc)[~is_poly]]

    # External edges (links to other tiles): (poly, vertex a, vertex b) in this tile's numbering, made global later.
    nei = polys["neis"].astype(np.int64)
    pa, ea = np.nonzero((nei & EXT_LINK != 0) & used)
    pvi = polys["verts"].astype(np.int64)
    ext_edges = np.column_stack([pa, pvi[pa, ea], pvi[pa, (ea + 1) % vc[pa]]]) if len(pa) else np.zeros((0, 3))
    return {
        "walkable_height": float(h["walkable_height"]), "walkable_radius": float(h["walkable_radius"]),
        "walkable_climb": float(h["walkable_climb"]), "verts": verts, "polys": polys, "tris": tri,
        "tri_poly": poly_of_tri, "ext_edges": ext_edges.astype(np.int64),
    }  # fmt: skip


def _match_external_edges(ext: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Pairs of polygons whose tile-border edges ``ext (E,3)`` [poly, vertex a, vertex b] have the same end points (to
    1 mm): Detour's links between tiles, rebuilt (habitat writes one tile, so this is for other tools' files)."""
    by_edge: dict[tuple, list[int]] = {}
    for p, a, b in ext.tolist():
        key = tuple(sorted((tuple(np.round(vertices[a], 3)), tuple(np.round(vertices[b], 3)))))
        by_edge.setdefault(key, []).append(p)
    pairs = [(ps[i], ps[j]) for ps in by_edge.values() for i in range(len(ps)) for j in range(i + 1, len(ps))]
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


#: habitat's default NavMeshSettings (habitat-sim ``NavMeshSettings::setDefaults``), written in version-2 files.
DEFAULT_SETTINGS = {
    "cell_size": 0.05, "cell_height": 0.2, "agent_height": 1.5, "agent_radius": 0.1, "agent_max_climb": 0.2,
    "agent_max_slope": 45.0, "region_min_size": 20.0, "region_merge_size": 20.0, "edge_max_len": 12.0,
    "edge_max_error": 1.3, "verts_per_poly": 6.0, "detail_sample_dist": 6.0, "detail_sample_max_error": 1.0,
}  # fmt: skip


def encode_navmesh(vertices: np.ndarray, polys: np.ndarray, *, version: int = 1,
                   settings: dict[str, float] | None = None, flags: np.ndarray | None = None) -> bytes:
    """Bytes of a one-tile habitat ``.navmesh`` (MSET ``version`` 1 or 2) holding the given convex polygons.

    ``vertices (V,3)`` Matterport world frame (z up, metres; stored as float32 in habitat's y-up frame), ``polys
    (P,K)`` vertex indices per polygon (convex, K <= 6, padded with -1). Neighbours come from
    shared edges, each polygon's detail mesh is its own triangle fan, the BV tree is one leaf per polygon (a valid
    Detour tree), links are left empty as Detour's builder leaves them. ``flags (P,)`` default to ``POLY_WALK``;
    ``settings`` (version 2) default to :data:`DEFAULT_SETTINGS`, whose agent also fills the tile header.
    """
    if version not in MSET_VERSIONS:
        raise ValueError(f"version must be one of {MSET_VERSIONS}")
    st = dict(DEFAULT_SETTINGS, **(settings or {}))
    v = mp3d_to_habitat(vertices).astype(np.float32)
    polys = np.asarray(polys, dtype=np.int64).reshape(len(polys), -1)
    n_poly, width = polys.shape
    if width > MAX_VERTS_PER_POLY or len(v) >= 0xFFFF or n_poly >= 0x7FFF:
        raise ValueError("at most 6 vertices per polygon, 65534 vertices and 32766 polygons per tile")
    pv = np.full((n_poly, 6), 0, dtype=np.int64)
    pv[:, :width] = np.where(polys >= 0, polys, 0)
    vc = (polys >= 0).sum(axis=1)
    if (vc < 3).any():
        raise ValueError("every polygon needs at least 3 vertices")

    # Neighbours across shared edges: edge e of polygon p runs from vertex e to vertex e+1 (mod count).
    neis = np.zeros((n_poly, 6), dtype=np.int64)
    owner: dict[tuple[int, int], tuple[int, int]] = {}
    for p in range(n_poly):
        for e in range(vc[p]):
            a, b = int(pv[p, e]), int(pv[p, (e + 1) % vc[p]])
            key = (min(a, b), max(a, b))
            if key in owner:
                q, f = owner.pop(key)
                neis[p, e], neis[q, f] = q + 1, p + 1
            else:
                owner[key] = (p, e)
    poly = np.zeros(n_poly, dtype=_POLY)
    poly["first_link"] = 0xFFFFFFFF  # DT_NULL_LINK: links are built when Detour adds the tile
    poly["verts"], poly["neis"] = pv, neis
    poly["flags"] = POLY_WALK if flags is None else flags
    poly["vert_count"] = vc
    poly["area_and_type"] = 0  # area GROUND, type ground polygon
    n_links = int(np.count_nonzero(neis))

    # Detail meshes: a fan (0, i, i+1) per polygon, no extra detail vertices; edge flags mark polygon borders.
    n_tri = vc - 2
    dmesh = np.zeros(n_poly, dtype=_DETAIL_MESH)
    dmesh["tri_base"] = np.concatenate([[0], np.cumsum(n_tri)[:-1]])
    dmesh["tri_count"] = n_tri
    dtris = []
    for p in range(n_poly):
        for i in range(1, vc[p] - 1):
            edge = (i == 1) | (1 << 2) | ((i + 1 == vc[p] - 1) << 4)  # 0→i, i→i+1, i+1→0 on the boundary
            dtris.append((0, i, i + 1, edge))
    dtri = np.array(dtris, dtype=np.uint8).reshape(-1, 4)

    bmin = v.min(axis=0) if len(v) else np.zeros(3, np.float32)
    bmax = v.max(axis=0) if len(v) else np.zeros(3, np.float32)
    quant = 1.0 / st["cell_size"]
    corners = v[pv] * np.where(np.arange(6)[None, :, None] < vc[:, None, None], 1, np.nan)
    bv = np.zeros(n_poly, dtype=_BV_NODE)
    bv["bmin"] = np.clip(np.floor((np.nanmin(corners, axis=1) - bmin) * quant), 0, 0xFFFF)
    bv["bmax"] = np.clip(np.ceil((np.nanmax(corners, axis=1) - bmin) * quant), 0, 0xFFFF)
    bv["i"] = np.arange(n_poly)

    mh = np.zeros(1, dtype=_MESH_HEADER)
    mh["magic"], mh["version"], mh["user_id"] = DNAV_MAGIC, DNAV_VERSION, 0
    mh["poly_count"], mh["vert_count"], mh["max_link_count"] = n_poly, len(v), n_links
    mh["detail_mesh_count"], mh["detail_tri_count"], mh["bv_node_count"] = n_poly, len(dtri), n_poly
    mh["off_mesh_base"] = n_poly
    mh["walkable_height"], mh["walkable_radius"] = st["agent_height"], st["agent_radius"]
    mh["walkable_climb"] = st["agent_max_climb"]
    mh["bmin"], mh["bmax"], mh["bv_quant_factor"] = bmin, bmax, quant
    tile = b"".join([mh.tobytes(), v.tobytes(), poly.tobytes(), bytes(_LINK_BYTES * n_links), dmesh.tobytes(),
                     dtri.tobytes(), bv.tobytes()])  # fmt: skip

    head = np.zeros(1, dtype=_SET_HEADER)
    head["magic"], head["version"], head["num_tiles"] = MSET_MAGIC, version, 1
    head["orig"], head["tile_width"], head["tile_height"] = bmin, bmax[0] - bmin[0], bmax[2] - bmin[2]
    head["max_tiles"], head["max_polys"] = 1, n_poly
    out = [head.tobytes()]
    if version == 2:
        s = np.zeros(1, dtype=_SETTINGS)
        for n in SETTINGS_FIELDS:
            s[n] = st[n]
        s["flags"] = (1, 1, 1, 0)
        out.append(s.tobytes())
    # Detour's first tile reference with 32-bit refs: salt 1 above the tile and polygon bits (one tile: no tile bits).
    poly_bits = max(1, int(n_poly - 1).bit_length())
    th = np.zeros(1, dtype=_TILE_HEADER)
    th["ref"], th["size"] = 1 << poly_bits, len(tile)
    out += [th.tobytes(), tile]
    return b"".join(out)
