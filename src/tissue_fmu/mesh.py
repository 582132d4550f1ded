"""Linear tetrahedral meshes: container, validation, generators (box, AAA) and file I/O.

Conventions (shared with the force field and the model): SI units, node-major arrays,
``points`` (n, 3) float64, ``tets`` (m, 4) int64, every tet positively oriented,
i.e. ``det[p1 - p0, p2 - p0, p3 - p0] > 0``.

Structured generators split each hexahedral cell into six tets along the cell's main
diagonal (Kuhn / Freudenthal split).  Every cell uses the same pattern in index space, so
each quadrilateral face is cut along the diagonal joining its lowest-index and
highest-index corners from both sides: neighbouring cells agree and the mesh is conforming.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import logging
import os
from dataclasses import dataclass, field

import numpy as np

from ._checks import as_float, is_integer
from .errors import MeshError
from .precompute import signed_volumes

logger = logging.getLogger(__name__)

__all__ = [
    "MeshError",
    "TetMesh",
    "box_mesh",
    "aaa_mesh",
    "aaa_inner_radius",
    "validate_mesh",
    "load_mesh",
    "save_mesh",
]

# A tet whose |volume| is below this fraction of (its mean edge length)^3 is degenerate.
# A regular tet has V = l^3 / (6 sqrt 2) ~ 0.118 l^3, so this only catches collapsed elements.
DEGENERATE_RELATIVE_VOLUME = 1e-12

# Faces of a positively oriented tet (0, 1, 2, 3), each wound so its normal points outward;
# row f is the face opposite node f.
_OUTWARD_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)

# The six edges of a tet as pairs of local node indices.
_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int64)

_MAX_LISTED_IDS = 10


# --------------------------------------------------------------------------------------
# Small vectorised geometry helpers
# --------------------------------------------------------------------------------------



def _edge_lengths(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(m, 6) edge lengths."""
    d = points[tets[:, _EDGES[:, 1]]] - points[tets[:, _EDGES[:, 0]]]
    return np.sqrt(np.einsum("ijk,ijk->ij", d, d))


def _all_faces(tets: np.ndarray) -> np.ndarray:
    """(4 m, 3) outward-wound faces, ordered face-major within each tet (row 4 e + f)."""
    return tets[:, _OUTWARD_FACES].reshape(-1, 3)


def _face_keys(faces: np.ndarray, n_nodes: int) -> np.ndarray:
    """One integer per face, equal for faces with the same node set (orientation ignored)."""
    s = np.sort(faces, axis=1)
    if n_nodes < 2_000_000:  # n^3 < 2^63: pack three ids into one int64, much faster to unique
        n = np.int64(max(n_nodes, 1))
        return (s[:, 0] * n + s[:, 1]) * n + s[:, 2]
    _, inverse = np.unique(s, axis=0, return_inverse=True)
    return inverse.reshape(-1)


def _id_list(ids: np.ndarray) -> str:
    ids = np.asarray(ids).reshape(-1)
    shown = ", ".join(str(int(i)) for i in ids[:_MAX_LISTED_IDS])
    return shown + (", ..." if ids.size > _MAX_LISTED_IDS else "")


# --------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------


def validate_mesh(points, tets, *, allow_inverted: bool = False) -> None:
    """Check a tetrahedral mesh; raise :class:`MeshError` naming the problem and the fix.

    Errors: wrong shapes or dtypes, NaN/Inf coordinates, node ids out of range, a node
    repeated inside a tet, degenerate tets (|V| <= 1e-12 * mean edge length^3), inverted tets
    (V < 0; accepted with ``allow_inverted=True``, for callers that are correct for either vertex
    order, like :func:`assemble_stiffness`) and non-manifold input (a face shared by more than two tets).  Nodes that no tet
    references only produce a logged warning (they carry no mass or stiffness).
    """
    points = np.asarray(points)
    tets = np.asarray(tets)
    _check_arrays(points, tets)
    n = points.shape[0]
    tets = _check_node_ids(points, tets)
    _check_volumes(points.astype(np.float64, copy=False), tets, allow_inverted)
    _check_manifold(tets, n)
    _warn_unreferenced(tets, n)


def _check_arrays(points: np.ndarray, tets: np.ndarray) -> None:
    """Shapes and dtypes of the two arrays."""
    if points.ndim != 2 or points.shape[1] != 3:
        raise MeshError(
            f"points must have shape (n, 3) (got {points.shape}): give one row of x, y, z "
            "coordinates in metres per node"
        )
    if points.shape[0] < 4:
        raise MeshError(f"points must hold at least 4 nodes (got {points.shape[0]}): a tet needs four")
    if not (np.issubdtype(points.dtype, np.floating) or np.issubdtype(points.dtype, np.integer)):
        raise MeshError(
            f"points must be real numbers (got dtype {points.dtype}): pass a float64 array"
        )
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise MeshError(
            f"tets must have shape (m, 4) (got {tets.shape}): give four node ids per linear "
            "tetrahedron (quadratic tets: keep only the first four columns)"
        )
    if tets.shape[0] == 0:
        raise MeshError("tets is empty (shape (0, 4)): the mesh needs at least one tetrahedron")
    if not np.issubdtype(tets.dtype, np.integer):
        raise MeshError(
            f"tets must hold integer node ids (got dtype {tets.dtype}): convert with "
            "tets.astype(np.int64) after checking the values are whole numbers"
        )


def _check_node_ids(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Finite coordinates, node ids in range and distinct within each tet; returns tets as int64."""
    bad_nodes = np.flatnonzero(~np.isfinite(points).all(axis=1))
    if bad_nodes.size:
        raise MeshError(
            f"points contain NaN or Inf coordinates at {bad_nodes.size} node(s), first ids "
            f"[{_id_list(bad_nodes)}]: give finite coordinates for every node"
        )

    n = points.shape[0]
    out_of_range = np.flatnonzero(((tets < 0) | (tets >= n)).any(axis=1))
    if out_of_range.size:
        raise MeshError(
            f"tets reference node ids outside [0, {n - 1}] in {out_of_range.size} element(s), "
            f"first element ids [{_id_list(out_of_range)}]: node ids are 0-based row indices "
            "into points (subtract 1 if the source file counts from 1)"
        )
    tets = tets.astype(np.int64, copy=False)

    s = np.sort(tets, axis=1)
    repeated = np.flatnonzero((s[:, 1:] == s[:, :-1]).any(axis=1))
    if repeated.size:
        raise MeshError(
            f"tets repeat a node id within the element in {repeated.size} element(s), first "
            f"element ids [{_id_list(repeated)}]: each tet needs four distinct nodes; remove "
            "these collapsed elements"
        )
    return tets


def _check_volumes(points: np.ndarray, tets: np.ndarray, allow_inverted: bool) -> None:
    """No degenerate tet, and no inverted one unless ``allow_inverted``."""
    volumes = signed_volumes(points, tets)
    scale = _edge_lengths(points, tets).mean(axis=1) ** 3
    degenerate = np.flatnonzero(np.abs(volumes) <= DEGENERATE_RELATIVE_VOLUME * scale)
    if degenerate.size:
        raise MeshError(
            f"{degenerate.size} degenerate (zero-volume, flat) tet(s), first element ids "
            f"[{_id_list(degenerate)}]: |volume| <= {DEGENERATE_RELATIVE_VOLUME:g} * (mean edge "
            "length)^3; remove or re-mesh these elements"
        )
    inverted = np.flatnonzero(volumes < 0.0)
    if inverted.size and not allow_inverted:
        raise MeshError(
            f"{inverted.size} inverted tet(s) (negative volume), first element ids "
            f"[{_id_list(inverted)}]: swap two nodes of each listed tet or pass "
            "fix_orientation=True to load_mesh"
        )


def _check_manifold(tets: np.ndarray, n: int) -> None:
    """No face shared by more than two tets."""
    keys = _face_keys(_all_faces(tets), n)
    unique_keys, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    over_shared = counts[inverse.reshape(-1)] > 2
    if over_shared.any():
        elements = np.unique(np.flatnonzero(over_shared) // 4)
        n_faces = int((counts > 2).sum())
        raise MeshError(
            f"non-manifold mesh: {n_faces} face(s) shared by more than two tets (overlapping "
            f"or duplicated elements), {elements.size} element(s) involved, first element ids "
            f"[{_id_list(elements)}]: remove duplicate elements or re-mesh the region"
        )


def _warn_unreferenced(tets: np.ndarray, n: int) -> None:
    """Log the nodes no tet uses (they carry no mass or stiffness)."""
    referenced = np.zeros(n, dtype=bool)
    referenced[tets.reshape(-1)] = True
    unreferenced = np.flatnonzero(~referenced)
    if unreferenced.size:
        logger.warning(
            "%d node(s) are not used by any tet (first ids [%s]); they get no mass or "
            "stiffness, drop them (load_mesh does so by default)",
            unreferenced.size,
            _id_list(unreferenced),
        )


def _validate_sets(sets: dict, limit: int, kind: str, what: str) -> dict[str, np.ndarray]:
    checked = {}
    for name, ids in sets.items():
        arr = np.asarray(ids)
        if arr.size and not np.issubdtype(arr.dtype, np.integer):
            if arr.dtype == bool and arr.shape == (limit,):
                arr = np.flatnonzero(arr)
            else:
                raise MeshError(
                    f"{kind} {name!r} must be integer {what} ids (got dtype {arr.dtype}): "
                    f"pass an index array or a boolean mask of length {limit}"
                )
        arr = np.unique(arr.astype(np.int64).reshape(-1))
        if arr.size and (arr[0] < 0 or arr[-1] >= limit):
            raise MeshError(
                f"{kind} {name!r} holds ids outside [0, {limit - 1}]: {what} ids are 0-based"
            )
        checked[str(name)] = arr
    return checked


# --------------------------------------------------------------------------------------
# Container
# --------------------------------------------------------------------------------------


@dataclass
class TetMesh:
    """A validated linear tetrahedral mesh (see module docstring for conventions)."""

    points: np.ndarray
    tets: np.ndarray
    node_sets: dict[str, np.ndarray] = field(default_factory=dict)
    element_sets: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        validate_mesh(self.points, self.tets)
        self.points = np.ascontiguousarray(self.points, dtype=np.float64)
        self.tets = np.ascontiguousarray(self.tets, dtype=np.int64)
        self.node_sets = _validate_sets(self.node_sets, self.n_nodes, "node set", "node")
        self.element_sets = _validate_sets(self.element_sets, self.n_tets, "element set", "element")

    @property
    def n_nodes(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_tets(self) -> int:
        return int(self.tets.shape[0])

    def volumes(self) -> np.ndarray:
        """(m,) element volumes in m^3 (positive for a valid mesh)."""
        return signed_volumes(self.points, self.tets)

    def boundary_faces(self) -> np.ndarray:
        """(t, 3) outward-wound boundary triangles in GLOBAL node ids.

        A boundary face belongs to exactly one tet; each tet's faces are wound outward, so the
        surviving copies are outward for the solid.
        """
        faces = _all_faces(self.tets)
        keys = _face_keys(faces, self.n_nodes)
        _, first, counts = np.unique(keys, return_index=True, return_counts=True)
        return faces[np.sort(first[counts == 1])]

    def surface(self) -> tuple[np.ndarray, np.ndarray]:
        """(surface_nodes sorted (k,), triangles (t, 3) as local indices into surface_nodes)."""
        faces = self.boundary_faces()
        surface_nodes, local = np.unique(faces, return_inverse=True)
        return surface_nodes, local.reshape(-1, 3).astype(np.int64)

    def radius_ratios(self) -> np.ndarray:
        """(m,) 3 r_in / r_circ of each tet: 1 for a regular tet, -> 0 for slivers."""
        volumes = self.volumes()
        p0 = self.points[self.tets[:, 0]]
        a = self.points[self.tets[:, 1]] - p0
        b = self.points[self.tets[:, 2]] - p0
        c = self.points[self.tets[:, 3]] - p0
        # Circumradius: |a^2 (b x c) + b^2 (c x a) + c^2 (a x b)| / (12 V).
        aa = np.einsum("ij,ij->i", a, a)[:, None]
        bb = np.einsum("ij,ij->i", b, b)[:, None]
        cc = np.einsum("ij,ij->i", c, c)[:, None]
        numerator = aa * np.cross(b, c) + bb * np.cross(c, a) + cc * np.cross(a, b)
        r_circ = np.linalg.norm(numerator, axis=1) / (12.0 * volumes)
        # Inradius: 3 V / total face area.
        faces = self.points[self.tets[:, _OUTWARD_FACES]]  # (m, 4, 3, 3)
        areas = 0.5 * np.linalg.norm(
            np.cross(faces[:, :, 1] - faces[:, :, 0], faces[:, :, 2] - faces[:, :, 0]), axis=2
        ).sum(axis=1)
        r_in = 3.0 * volumes / areas
        return 3.0 * r_in / r_circ

    def quality(self) -> dict:
        """Counts and element-quality statistics.

        radius ratio: :meth:`radius_ratios`; edge ratio = longest / shortest edge of a tet (1 for a
        regular tet).
        """
        volumes = self.volumes()
        radius_ratio = self.radius_ratios()
        edges = _edge_lengths(self.points, self.tets)
        edge_ratio = edges.max(axis=1) / edges.min(axis=1)
        return {
            "n_nodes": self.n_nodes,
            "n_tets": self.n_tets,
            "min_volume": float(volumes.min()),
            "mean_volume": float(volumes.mean()),
            "max_volume": float(volumes.max()),
            "total_volume": float(volumes.sum()),
            "min_radius_ratio": float(radius_ratio.min()),
            "mean_radius_ratio": float(radius_ratio.mean()),
            "max_edge_ratio": float(edge_ratio.max()),
            "min_edge_length": float(edges.min()),
            "max_edge_length": float(edges.max()),
        }


# --------------------------------------------------------------------------------------
# Structured generators
# --------------------------------------------------------------------------------------


def _kuhn_pattern() -> np.ndarray:
    """(6, 4) corner numbers of the six Kuhn tets of a hex, positively oriented.

    Corner number c = d0 + 2 d1 + 4 d2 for index offsets (d0, d1, d2) in {0, 1}.  Tet for the
    axis permutation (a, b, c): corner 0 -> +e_a -> +e_a +e_b -> corner 7.  Orientation is
    fixed once on the unit cube; any orientation-preserving map of index space keeps it.
    """
    unit = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=float)
    pattern = []
    for perm in itertools.permutations(range(3)):
        first = 1 << perm[0]
        second = first + (1 << perm[1])
        tet = [0, first, second, 7]
        if signed_volumes(unit, np.array([tet]))[0] < 0:
            tet[2], tet[3] = tet[3], tet[2]
        pattern.append(tet)
    return np.array(pattern, dtype=np.int64)


_KUHN = _kuhn_pattern()


def _hex_cells_to_tets(corners: np.ndarray) -> np.ndarray:
    """(c, 8) hex corner node ids (corner numbering of _kuhn_pattern) -> (6 c, 4) tets."""
    return corners[:, _KUHN].reshape(-1, 4)


def _structured_corners(node_id: np.ndarray, periodic0: bool = False) -> np.ndarray:
    """(c, 8) corner ids of every cell of a structured grid of node ids node_id[i, j, k].

    With periodic0 the first index wraps around (cell n0-1 joins nodes n0-1 and 0).
    """
    if periodic0:
        node_id = np.concatenate([node_id, node_id[:1]], axis=0)
    n0, n1, n2 = (s - 1 for s in node_id.shape)
    corners = np.empty((n0, n1, n2, 8), dtype=np.int64)
    for c in range(8):
        d0, d1, d2 = c & 1, (c >> 1) & 1, (c >> 2) & 1
        corners[..., c] = node_id[d0 : d0 + n0, d1 : d1 + n1, d2 : d2 + n2]
    return corners.reshape(-1, 8)


def _positive_finite(name: str, value, example: str) -> float:
    x = as_float(value)
    if x is None:
        raise MeshError(f"{name} must be a number (got {value!r}): e.g. {example}")
    if not np.isfinite(x) or x <= 0.0:
        raise MeshError(f"{name} must be finite and > 0 (got {value!r}): e.g. {example}")
    return x


def _count(name: str, value, minimum: int, example: str) -> int:
    if not is_integer(value):
        raise MeshError(f"{name} must be an integer (got {value!r}): e.g. {example}")
    if value < minimum:
        raise MeshError(f"{name} must be >= {minimum} (got {value}): e.g. {example}")
    return int(value)


def box_mesh(size=(1.0, 1.0, 1.0), divisions=(2, 2, 2), origin=(0.0, 0.0, 0.0)) -> TetMesh:
    """Axis-aligned box [origin, origin + size] split into nx*ny*nz hexes of 6 tets each.

    Node sets "xmin", "xmax", "ymin", "ymax", "zmin", "zmax" hold the nodes on each face.
    """
    if len(size) != 3 or len(divisions) != 3 or len(origin) != 3:
        raise MeshError("size, divisions and origin must each have three entries (x, y, z)")
    lengths = [_positive_finite(f"size[{i}]", s, "0.01 (m)") for i, s in enumerate(size)]
    counts = [_count(f"divisions[{i}]", d, 1, "4") for i, d in enumerate(divisions)]
    start = np.asarray(origin, dtype=np.float64)
    if not np.isfinite(start).all():
        raise MeshError(f"origin must be finite (got {origin!r}): e.g. (0.0, 0.0, 0.0)")

    axes = [start[i] + np.linspace(0.0, lengths[i], counts[i] + 1) for i in range(3)]
    # linspace ends exactly at start + length only up to round-off; pin the end plane.
    for i in range(3):
        axes[i][-1] = start[i] + lengths[i]
    grid = np.meshgrid(*axes, indexing="ij")
    points = np.stack([g.reshape(-1) for g in grid], axis=1)
    shape = tuple(c + 1 for c in counts)
    node_id = np.arange(points.shape[0], dtype=np.int64).reshape(shape)
    tets = _hex_cells_to_tets(_structured_corners(node_id))

    node_sets = {
        "xmin": node_id[0].reshape(-1),
        "xmax": node_id[-1].reshape(-1),
        "ymin": node_id[:, 0].reshape(-1),
        "ymax": node_id[:, -1].reshape(-1),
        "zmin": node_id[:, :, 0].reshape(-1),
        "zmax": node_id[:, :, -1].reshape(-1),
    }
    return TetMesh(points, tets, node_sets, {})


def _aneurysm_bump(z: np.ndarray, centre: float, length: float) -> np.ndarray:
    """C1 fusiform bump: cos^2 over |z - centre| < length / 2, zero outside.

    Value and slope both vanish at the ends, so the wall has no kink where the sac meets the
    healthy aorta (a kink would concentrate stress artificially).
    """
    xi = (z - centre) / length
    return np.where(np.abs(xi) < 0.5, np.cos(np.pi * xi) ** 2, 0.0)


def aaa_inner_radius(z, aorta_radius=0.010, aneurysm_radius=0.025, aneurysm_length=0.060,
                     segment_length=0.130) -> np.ndarray:
    """Lumen radius r(z) of :func:`aaa_mesh` (exposed for analytic checks)."""
    z = np.asarray(z, dtype=np.float64)
    bump = _aneurysm_bump(z, 0.5 * segment_length, aneurysm_length)
    return aorta_radius + (aneurysm_radius - aorta_radius) * bump


def aaa_mesh(aorta_radius=0.010, aneurysm_radius=0.025, aneurysm_length=0.060,
             segment_length=0.130, wall_thickness=0.0015, n_circumferential=32, n_axial=40,
             n_radial=2) -> TetMesh:
    """Fusiform abdominal aortic aneurysm: a tube wall of revolution about the z axis.

    Lumen radius r(z) = aorta_radius + (aneurysm_radius - aorta_radius) * cos^2 bump centred
    at segment_length / 2 over aneurysm_length; the wall spans [r(z), r(z) + wall_thickness]
    radially, z in [0, segment_length].  Structured (circumferential x axial x radial) hexes,
    periodic around the axis, 6 tets each: 6 * n_circumferential * n_axial * n_radial tets.

    node_sets: "inlet" (z = 0), "outlet" (z = segment_length), "inner" (lumen surface),
    "outer"; element_sets: "sac" (centroid within the bulge, |z - L/2| < aneurysm_length / 2).
    """
    r0 = _positive_finite("aorta_radius", aorta_radius, "0.010 (m)")
    ra = _positive_finite("aneurysm_radius", aneurysm_radius, "0.025 (m)")
    la = _positive_finite("aneurysm_length", aneurysm_length, "0.060 (m)")
    length = _positive_finite("segment_length", segment_length, "0.130 (m)")
    h = _positive_finite("wall_thickness", wall_thickness, "0.0015 (m)")
    nc = _count("n_circumferential", n_circumferential, 8, "32")
    na = _count("n_axial", n_axial, 1, "40")
    nr = _count("n_radial", n_radial, 1, "2")
    if ra < r0:
        raise MeshError(
            f"aneurysm_radius ({ra}) must be >= aorta_radius ({r0}): the sac bulges outward; "
            "use equal radii for a straight aorta"
        )
    if la > length:
        raise MeshError(
            f"aneurysm_length ({la}) must be <= segment_length ({length}): lengthen the "
            "segment or shorten the aneurysm"
        )

    theta = np.arange(nc) * (2.0 * np.pi / nc)
    z = np.linspace(0.0, length, na + 1)
    z[-1] = length
    s = np.arange(nr + 1) / nr
    r_inner = aaa_inner_radius(z, r0, ra, la, length)
    # Index order (theta, z, radial) maps orientation-preservingly to (x, y, z):
    # det d(x,y,z)/d(theta,z,rho) = R * wall_thickness > 0, so Kuhn tets stay positive.
    radius = r_inner[None, :, None] + h * s[None, None, :]  # (1, na+1, nr+1)
    shape = (nc, na + 1, nr + 1)
    points = np.empty(shape + (3,), dtype=np.float64)
    points[..., 0] = radius * np.cos(theta)[:, None, None]
    points[..., 1] = radius * np.sin(theta)[:, None, None]
    points[..., 2] = z[None, :, None]
    points = points.reshape(-1, 3)
    node_id = np.arange(points.shape[0], dtype=np.int64).reshape(shape)
    tets = _hex_cells_to_tets(_structured_corners(node_id, periodic0=True))

    centroid_z = points[tets, 2].mean(axis=1)
    sac = np.flatnonzero(np.abs(centroid_z - 0.5 * length) < 0.5 * la)
    node_sets = {
        "inlet": node_id[:, 0, :].reshape(-1),
        "outlet": node_id[:, -1, :].reshape(-1),
        "inner": node_id[:, :, 0].reshape(-1),
        "outer": node_id[:, :, -1].reshape(-1),
    }
    try:
        return TetMesh(points, tets, node_sets, {"sac": sac})
    except MeshError as exc:
        raise MeshError(
            f"aaa_mesh produced an invalid mesh ({exc}); the resolution is too coarse for the "
            "geometry: increase n_circumferential / n_axial or reduce the bulge"
        ) from exc


# --------------------------------------------------------------------------------------
# File I/O (meshio)
# --------------------------------------------------------------------------------------

# Node / element sets travel through files as 0/1 point / cell data arrays with these
# prefixes, which every meshio format with point and cell data (vtu, msh, xdmf, ...) can hold.
_NODE_SET_PREFIX = "node_set:"
_ELEMENT_SET_PREFIX = "element_set:"


def save_mesh(mesh: TetMesh, path, file_format: str | None = None) -> None:
    """Write ``mesh`` with meshio, node / element sets as 0/1 data arrays.

    The format comes from the extension unless file_format (a meshio format name) is given;
    ".msh" means gmsh 4.1 (meshio alone would pick the ANSYS format, which drops the sets).
    """
    import meshio

    path = os.fspath(path)
    if file_format is None and path.lower().endswith(".msh"):
        file_format = "gmsh"

    point_data = {}
    for name, ids in mesh.node_sets.items():
        mask = np.zeros(mesh.n_nodes, dtype=np.int32)
        mask[ids] = 1
        point_data[_NODE_SET_PREFIX + name] = mask
    cell_data = {}
    for name, ids in mesh.element_sets.items():
        mask = np.zeros(mesh.n_tets, dtype=np.int32)
        mask[ids] = 1
        cell_data[_ELEMENT_SET_PREFIX + name] = [mask]
    out = meshio.Mesh(mesh.points, [("tetra", mesh.tets)], point_data=point_data,
                      cell_data=cell_data)
    try:
        meshio.write(path, out, file_format=file_format)
    except Exception as exc:  # meshio raises many types (WriteError, KeyError, ValueError)
        raise MeshError(
            f"could not write mesh to {path!r}: {type(exc).__name__}: {exc}; use a "
            "format meshio writes with tetra cells, e.g. .vtu or .msh"
        ) from exc


def _orient_positively(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    volumes = signed_volumes(points, tets)
    inverted = volumes < 0.0
    if inverted.any():
        logger.info("fix_orientation: swapped two nodes of %d inverted tet(s)", int(inverted.sum()))
        tets = tets.copy()
        tets[inverted, 2], tets[inverted, 3] = tets[inverted, 3], tets[inverted, 2].copy()
    return tets


def load_mesh(path, fix_orientation: bool = False, drop_unreferenced: bool = True) -> TetMesh:
    """Read a tetrahedral mesh with meshio (any format it reads with "tetra" cells) and validate.

    All "tetra" blocks are concatenated; other cell types (surface triangles, lines) are
    ignored.  fix_orientation swaps two nodes of every inverted tet.  drop_unreferenced removes
    nodes no tet uses (e.g. gmsh geometry points), renumbering the rest in order, because such
    nodes would carry no mass.  Sets saved by :func:`save_mesh` are restored.
    """
    import meshio

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise MeshError(f"mesh file not found: {path!r}: check the path (relative paths are "
                        f"resolved from {os.getcwd()!r})")
    # meshio prints reader complaints and, when every candidate reader fails, calls
    # sys.exit(1); capture its chatter for the message and turn the exit into a MeshError.
    chatter = io.StringIO()
    try:
        with contextlib.redirect_stdout(chatter), contextlib.redirect_stderr(chatter):
            raw = meshio.read(path)
    except (Exception, SystemExit) as exc:  # ReadError, KeyError, ValueError, ... by format
        detail = " ".join(chatter.getvalue().split()) or f"{type(exc).__name__}: {exc}"
        raise MeshError(
            f"could not read mesh file {path!r} ({detail}): give a file in a format meshio "
            "reads (e.g. .vtu, .vtk, .msh, .xdmf, .mesh) with tetra cells"
        ) from exc
    if chatter.getvalue().strip():
        logger.info("meshio while reading %s: %s", path, chatter.getvalue().strip())

    blocks = [i for i, block in enumerate(raw.cells) if block.type == "tetra"]
    if not blocks:
        found = sorted({block.type for block in raw.cells}) or ["none"]
        surface = " (a surface: for a vessel's lumen surface, build its wall with `python -m orchestration " \
                  "scene-from-anatomy`)" if found == ["triangle"] else ""
        raise MeshError(
            f"mesh file {path!r} has no linear tetrahedra ('tetra' cells); found cell types "
            f"{found}{surface}: export a volume mesh with 4-node tetrahedra (for tetra10 keep the "
            "corner nodes)"
        )
    tets = np.concatenate([raw.cells[i].data for i in blocks]).astype(np.int64)
    points = np.asarray(raw.points, dtype=np.float64)
    if points.ndim == 2 and points.shape[1] == 2:
        raise MeshError(f"mesh file {path!r} has 2-D points: tetrahedra need x, y, z coordinates")

    node_sets = {}
    for key, values in raw.point_data.items():
        if key.startswith(_NODE_SET_PREFIX):
            node_sets[key[len(_NODE_SET_PREFIX):]] = np.flatnonzero(np.asarray(values).reshape(-1))
    for key, ids in getattr(raw, "point_sets", {}).items():
        node_sets.setdefault(key, np.asarray(ids, dtype=np.int64).reshape(-1))
    element_sets = {}
    for key, per_block in raw.cell_data.items():
        if key.startswith(_ELEMENT_SET_PREFIX):
            mask = np.concatenate([np.asarray(per_block[i]).reshape(-1) for i in blocks])
            element_sets[key[len(_ELEMENT_SET_PREFIX):]] = np.flatnonzero(mask)

    # Checks that must precede any indexing with tets (fix_orientation, compaction).
    if points.ndim != 2 or points.shape[1] != 3 or tets.size == 0:
        validate_mesh(points, tets)
    if ((tets < 0) | (tets >= points.shape[0])).any():
        validate_mesh(points, tets)

    if drop_unreferenced:
        used = np.zeros(points.shape[0], dtype=bool)
        used[tets.reshape(-1)] = True
        if not used.all():
            logger.info("load_mesh: dropped %d node(s) not used by any tet", int((~used).sum()))
            new_id = np.cumsum(used) - 1
            points = points[used]
            tets = new_id[tets]
            node_sets = {k: new_id[v[used[v]]] for k, v in node_sets.items()}
    if fix_orientation:
        if not np.isfinite(points).all():
            validate_mesh(points, tets)
        tets = _orient_positively(points, tets)
    return TetMesh(points, tets, node_sets, element_sets)
