"""The vessel wall outside a lumen surface: layers of prisms along the normals, each split into three tetrahedra.

A vessel wall is a thin shell (the AAA wall is about 1-2.5 mm thick over centimetres), so it is
meshed the way boundary layers are: each lumen vertex is offset outward along its normal by the
local thickness, in ``layers`` steps, and each triangle sweeps a column of prisms. A prism splits
into three tetrahedra along the diagonals that start at its lowest-numbered vertex: neighbouring
prisms share a side quad with the same two vertices, so they cut it along the same diagonal and the
mesh is conforming (Dompierre et al., "How to subdivide pyramids, prisms and hexahedra into
tetrahedra", IMR 1999). The generator's fusiform wall (:func:`tissue_fmu.mesh.aaa_mesh`) is the same
structure with its own (radial) offset.

Node sets: ``inner`` (the lumen), ``outer``, ``end_<i>`` (the nodes of open end ``i`` through the
wall, the order of :attr:`LumenSurface.ends`) and ``ends`` (all of them: the default clamp).
"""
from __future__ import annotations

import logging

import numpy as np
import trimesh

from tissue_fmu.errors import MeshError
from tissue_fmu.mesh import TetMesh
from tissue_fmu.precompute import signed_volumes

from .errors import AnatomyError
from .intersections import self_intersections
from .surface import LumenSurface, place

logger = logging.getLogger(__name__)

#: The tetrahedra of a prism (bottom v0 v1 v2, top w0 w1 w2, v0 the lowest id): indices into
#: (v0, v1, v2, w0, w1, w2). Each side quad is cut by the diagonal from its lower-id bottom vertex.
_PRISM_TETS = np.array([[0, 1, 2, 5], [0, 1, 5, 4], [0, 3, 4, 5]], dtype=np.int64)
#: A wall thinner than this fraction of its thickness is folded where the offset overlaps.
MIN_RADIUS_RATIO = 0.02
#: The thickness of a wall (m): AAA walls are about 1-2.5 mm thick (Raghavan et al., J Vasc Surg 2006:
#: 0.23-4.26 mm measured on resected sacs); a healthy infrarenal aorta about 1.5-2 mm.
PLAUSIBLE_THICKNESS = (2e-4, 5e-3)


def vertex_normals(surface: LumenSurface) -> np.ndarray:
    """(n, 3) unit normals out of the lumen, area-weighted; at an open end, turned into the end's plane
    so that the end's face of the wall stays flat (it is clamped there)."""
    mesh = surface.mesh
    normals = np.zeros((len(mesh.vertices), 3))
    np.add.at(normals, mesh.faces.reshape(-1), np.repeat(mesh.face_normals * mesh.area_faces[:, None], 3, axis=0))
    for end in surface.ends:
        n = normals[end.vertices]
        normals[end.vertices] = n - np.outer(n @ end.normal, end.normal)
    length = np.linalg.norm(normals, axis=1)
    if (length == 0).any():
        vertex = int(np.flatnonzero(length == 0)[0])
        raise AnatomyError(f"{surface.source}: no outward direction at vertex {vertex} "
                           f"({place(mesh.vertices[vertex], surface)}): its triangles cancel out; remesh the surface")
    return normals / length[:, None]


def _thickness_per_vertex(surface: LumenSurface, thickness) -> np.ndarray:
    n = len(surface.mesh.vertices)
    values = np.broadcast_to(np.asarray(thickness, dtype=np.float64), (n,)) if np.ndim(thickness) == 0 else \
        np.asarray(thickness, dtype=np.float64)
    if values.shape != (n,):
        raise AnatomyError(f"thickness must be a number or one value per lumen vertex ({n}); got shape {values.shape}")
    low, high = PLAUSIBLE_THICKNESS
    if not np.isfinite(values).all() or values.min() < low or values.max() > high:
        raise AnatomyError(f"thickness must be within {low * 1e3:g}-{high * 1e3:g} mm, the walls of aortas and "
                           f"aneurysms (got {values.min() * 1e3:.3g}-{values.max() * 1e3:.3g} mm): give it in metres, "
                           "e.g. 0.0015")
    return values


def _prism_tets(faces: np.ndarray, n_vertices: int, layers: int) -> np.ndarray:
    """(3 layers m, 4) tets of the prism columns, positively oriented for outward-wound faces."""
    order = np.argsort(faces, axis=1)
    ordered = np.take_along_axis(faces, order, axis=1)
    # the sort is an odd permutation of the winding for half the faces: their tets come out negative
    odd = (order == [[0, 2, 1]]).all(1) | (order == [[1, 0, 2]]).all(1) | (order == [[2, 1, 0]]).all(1)
    blocks = []
    for layer in range(layers):
        corners = np.concatenate([ordered + layer * n_vertices, ordered + (layer + 1) * n_vertices], axis=1)
        tets = corners[:, _PRISM_TETS]                                    # (m, 3, 4)
        tets[odd] = tets[odd][:, :, [0, 1, 3, 2]]
        blocks.append(tets.reshape(-1, 4))
    return np.concatenate(blocks)


def build_wall(surface: LumenSurface, thickness=0.0015, layers: int = 2,
               element_sets: dict[str, np.ndarray] | None = None) -> TetMesh:
    """The tetrahedral wall of ``thickness`` (m, one number or one per lumen vertex) outside the lumen.

    ``element_sets`` maps names to boolean masks over the lumen's triangles; each becomes a set of the
    tetrahedra above those triangles (e.g. ``sac``). Refused: a thickness outside the plausible range,
    a wall that folds (where the lumen curves tighter than the wall is thick) or whose outside crosses
    itself (two vessels closer than twice the thickness), each with where it happens.
    """
    if not isinstance(layers, (int, np.integer)) or not 1 <= layers <= 16:
        raise AnatomyError(f"layers must be a whole number of element layers across the wall, 1 to 16 (got {layers!r})")
    mesh = surface.mesh
    t = _thickness_per_vertex(surface, thickness)
    normals = vertex_normals(surface)
    inner = np.asarray(mesh.vertices, dtype=np.float64)
    n = len(inner)
    points = np.concatenate([inner + (k / layers) * t[:, None] * normals for k in range(layers + 1)])
    faces = np.asarray(mesh.faces, dtype=np.int64)
    outer_faces = faces + layers * n
    crossing = self_intersections(points, outer_faces, limit=1)
    if len(crossing):
        at = points[outer_faces[crossing[0]]].reshape(-1, 3).mean(axis=0)
        raise AnatomyError(f"{surface.source}: the wall's outside crosses itself around {place(at, surface)}: two "
                           "parts of the vessel are closer than twice the wall's thickness there (or the lumen turns "
                           "tighter than it); use a thinner wall or separate them in the segmentation")
    tets = _prism_tets(faces, n, layers)
    volumes = signed_volumes(points, tets)
    folded = np.flatnonzero(volumes <= 0.0)
    if folded.size:
        at = points[tets[folded[0]]].mean(axis=0)
        raise AnatomyError(f"{surface.source}: the wall folds over itself at {folded.size} element(s), the first "
                           f"around {place(at, surface)}: the lumen curves tighter there than the wall is thick "
                           f"({t.max() * 1e3:.3g} mm); use a thinner wall, or smooth or remesh the surface there")
    node_sets = {"inner": np.arange(n), "outer": np.arange(n) + layers * n}
    ends = []
    for i, end in enumerate(surface.ends):
        ids = (end.vertices[None, :] + n * np.arange(layers + 1)[:, None]).ravel()
        node_sets[f"end_{i}"] = ids
        ends.append(ids)
    if ends:
        node_sets["ends"] = np.concatenate(ends)
    sets = {}
    for name, mask in (element_sets or {}).items():
        above = np.flatnonzero(np.asarray(mask, dtype=bool))
        # the tets of layer l above triangle f are 3 m l + 3 f + (0, 1, 2) (the order of _prism_tets)
        per_layer = (3 * above[:, None] + np.arange(3)).ravel()
        sets[name] = np.add.outer(3 * len(faces) * np.arange(layers), per_layer).ravel()
    try:
        wall = TetMesh(points, tets, node_sets, sets)
    except MeshError as exc:
        raise AnatomyError(f"{surface.source}: the wall is not a valid mesh ({exc}): remesh the surface") from None
    quality = wall.quality()
    if quality["min_radius_ratio"] < MIN_RADIUS_RATIO:
        worst = int(np.argmin(wall.radius_ratios()))
        raise AnatomyError(f"{surface.source}: the wall has a sliver (radius ratio {quality['min_radius_ratio']:.3g}, "
                           f"below {MIN_RADIUS_RATIO}) around {place(points[tets[worst]].mean(axis=0), surface)}: "
                           "remesh the surface (a sliver of a triangle makes a sliver of the wall)")
    logger.info("wall: %d nodes, %d tetrahedra, worst radius ratio %.3f, %.3g-%.3g mm thick", wall.n_nodes,
                wall.n_tets, quality["min_radius_ratio"], t.min() * 1e3, t.max() * 1e3)
    return wall


def lumen_of(wall: TetMesh, inner: str = "inner") -> trimesh.Trimesh:
    """The lumen surface of a generated wall (its boundary triangles on the ``inner`` node set), wound out of
    the lumen: the generator's anatomy as a segmentation would deliver it."""
    faces = wall.boundary_faces()
    on_inner = np.isin(faces, wall.node_sets[inner]).all(axis=1)
    used, local = np.unique(faces[on_inner], return_inverse=True)
    # a tet's boundary faces point out of the wall, i.e. into the lumen on the inner side
    return trimesh.Trimesh(wall.points[used], local.reshape(-1, 3)[:, ::-1], process=False)
