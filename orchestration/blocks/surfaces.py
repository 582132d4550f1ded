"""Rigid surfaces (plane or tube) for the Contact FMU when no Tissue FMU runs: constant geometry."""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from orchestration.blocks.options import BlockConfigError, check_choice, check_int, check_real, check_vector
from orchestration.blocks.sources import Source, checked_time
from orchestration.checks import is_int, is_real
from orchestration.hosts.description import MAX_PORT_VALUES, PortInfo

logger = logging.getLogger(__name__)


SURFACE_SHAPES = ("plane", "tube")


@dataclass(frozen=True)
class _Geometry:
    positions: np.ndarray   # (n, 3)
    triangles: np.ndarray   # (m, 3) int


def plane_geometry(center, normal, size, divisions) -> _Geometry:
    """A rectangle of size[0] x size[1] centred on `center`, split into divisions[0] x divisions[1]
    cells of two triangles, each with its normal along +normal.

    In-plane axes: u = normalize(normal x e) with e the coordinate axis least aligned with the normal,
    v = normal x u, so (u, v, normal) is right-handed; size[0] runs along u, size[1] along v.
    """
    n = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    e = np.zeros(3)
    e[int(np.argmin(np.abs(n)))] = 1.0
    u = np.cross(n, e)
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    na, nb = divisions
    a = np.linspace(-0.5 * size[0], 0.5 * size[0], na + 1)
    b = np.linspace(-0.5 * size[1], 0.5 * size[1], nb + 1)
    A, B = np.meshgrid(a, b, indexing="ij")  # node (i, j) has id i * (nb + 1) + j
    pos = np.asarray(center, np.float64) + A.reshape(-1, 1) * u + B.reshape(-1, 1) * v
    i, j = np.meshgrid(np.arange(na), np.arange(nb), indexing="ij")
    p00 = (i * (nb + 1) + j).ravel()
    p10, p01 = p00 + nb + 1, p00 + 1
    p11 = p10 + 1
    # edges along u then v: (u x v) = +normal
    tri = np.concatenate([np.stack([p00, p10, p11], 1), np.stack([p00, p11, p01], 1)])
    return _Geometry(pos, tri)


def tube_geometry(start, end, radius, n_circumferential, n_axial) -> _Geometry:
    """An open cylinder around the axis start -> end: n_axial + 1 rings of n_circumferential nodes,
    two triangles per quad, normals pointing to the axis (the tool is inside the tube)."""
    start = np.asarray(start, np.float64)
    axis = np.asarray(end, np.float64) - start
    a = axis / np.linalg.norm(axis)
    e = np.zeros(3)
    e[int(np.argmin(np.abs(a)))] = 1.0
    e1 = np.cross(a, e)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)  # (e1, e2, a) right-handed
    theta = 2.0 * np.pi * np.arange(n_circumferential) / n_circumferential
    s = np.linspace(0.0, 1.0, n_axial + 1)
    radial = np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2
    pos = (start + s[:, None, None] * axis + radius * radial[None, :, :]).reshape(-1, 3)
    k, j = np.meshgrid(np.arange(n_axial), np.arange(n_circumferential), indexing="ij")
    jn = (j + 1) % n_circumferential
    p00 = (k * n_circumferential + j).ravel()            # ring k, angle j
    p01 = (k * n_circumferential + jn).ravel()           # ring k, angle j+1
    p10, p11 = p00 + n_circumferential, p01 + n_circumferential
    # edges along the axis then around: a x t_theta = -radial, i.e. towards the axis
    tri = np.concatenate([np.stack([p00, p10, p11], 1), np.stack([p00, p11, p01], 1)])
    return _Geometry(pos, tri)


PLANE_DEFAULTS = {"center": (0.0, 0.0, 0.0), "normal": (0.0, 0.0, 1.0), "size": 0.1, "divisions": 10}
TUBE_DEFAULTS = {"start": (0.0, 0.0, 0.0), "end": (0.0, 0.0, 0.1), "radius": 0.01,
                  "n_circumferential": 32, "n_axial": 20}


def check_surface(problems, shape, given: dict) -> dict:
    """Validate rigid-surface options for `shape`; return the full option dict with defaults."""
    if check_choice(problems, "shape", shape, SURFACE_SHAPES) is None:
        return {}
    defaults, other = (PLANE_DEFAULTS, TUBE_DEFAULTS) if shape == "plane" else (TUBE_DEFAULTS, PLANE_DEFAULTS)
    for key in given:
        if key in other:
            problems.append(f"{key} applies to shape = '{'tube' if shape == 'plane' else 'plane'}' only; "
                            f"options of shape = '{shape}' are {list(defaults)}")
    opts = {k: given.get(k, d) for k, d in defaults.items()}
    out = {}
    if shape == "plane":
        out["center"] = check_vector(problems, "center", opts["center"], 3, "give the plane centre in m, e.g. [0, 0, 0]")
        normal = check_vector(problems, "normal", opts["normal"], 3,
                         "give the normal (the side where the tool is allowed), e.g. [0, 0, 1]")
        if normal is not None and not np.linalg.norm(normal) > 0:
            problems.append("normal must not be zero: give the direction of the allowed side, e.g. [0, 0, 1]")
            normal = None
        out["normal"] = normal
        size = opts["size"]
        size = [size, size] if is_real(size) else size
        size = check_vector(problems, "size", size, 2, "give the side length in m, or [length_u, length_v], e.g. 0.1")
        if size is not None and not (size > 0).all():
            problems.append(f"size must be > 0 (got {opts['size']!r}): give side lengths in m, e.g. 0.1")
            size = None
        out["size"] = size
        div = opts["divisions"]
        div = [div, div] if is_int(div) else div
        if not (isinstance(div, (list, tuple)) and len(div) == 2 and all(is_int(d) and d >= 1 for d in div)):
            problems.append(f"divisions must be an integer >= 1 or a list of two (got {opts['divisions']!r}): "
                            f"cells per side, e.g. 10")
            div = None
        out["divisions"] = None if div is None else (int(div[0]), int(div[1]))
    else:
        out["start"] = check_vector(problems, "start", opts["start"], 3, "give the first axis point in m")
        out["end"] = check_vector(problems, "end", opts["end"], 3, "give the last axis point in m")
        if out["start"] is not None and out["end"] is not None and not np.linalg.norm(out["end"] - out["start"]) > 0:
            problems.append("end must differ from start: give two distinct axis points in m")
        out["radius"] = check_real(problems, "radius", opts["radius"], "give the tube radius in m, e.g. 0.01", low=0.0)
        out["n_circumferential"] = check_int(problems, "n_circumferential", opts["n_circumferential"],
                                        "nodes around each ring, e.g. 32", low=3)
        out["n_axial"] = check_int(problems, "n_axial", opts["n_axial"], "segments along the axis, e.g. 20", low=1)
    _check_surface_size(problems, shape, out)
    return out


#: A rigid surface lies within this distance of the origin, m: the scenes model a vessel or a
#: device workspace (0.1-0.2 m); coordinates of kilometres cannot be meant, and far larger ones
#: overflow the contact model's squared distances.
SURFACE_MAX_EXTENT = 10.0


def _check_surface_size(problems, shape, out: dict) -> None:
    """The surface's node coordinates must fit a port (MAX_PORT_VALUES) and lie within
    SURFACE_MAX_EXTENT of the origin: anything else is a typo."""
    for key in ("center", "start", "end", "size", "radius"):
        value = out.get(key)
        if value is not None and float(np.max(np.abs(value))) > SURFACE_MAX_EXTENT:
            problems.append(f"{key} must be within {SURFACE_MAX_EXTENT:g} m (got {np.asarray(value).tolist()!r}): "
                            "give lengths in m; the scenes model a vessel or a device workspace of 0.1-0.2 m")
    if shape == "plane" and out.get("divisions") is not None:
        na, nb = out["divisions"]
        nodes, fix = (na + 1) * (nb + 1), "fewer divisions"
    elif shape == "tube" and out.get("n_circumferential") is not None and out.get("n_axial") is not None:
        nodes, fix = out["n_circumferential"] * (out["n_axial"] + 1), "fewer n_circumferential or n_axial"
    else:
        return
    if 3 * nodes > MAX_PORT_VALUES:
        problems.append(f"the surface would have {nodes} nodes, more than {MAX_PORT_VALUES // 3} ({MAX_PORT_VALUES} "
                        f"coordinates, the most a port holds); give {fix}")


class RigidSurfaceSource(Source):
    """Constant surface geometry for the Contact FMU: outputs ``positions`` (n,3), ``velocities``
    (zeros, n,3) and ``triangles`` (Int32 (m,3), carried as float64).

    Orientation contract of the Contact FMU: triangle normals (right-hand rule) point to the side
    where the tool is allowed: along ``normal`` for a plane, towards the axis for a tube.
    """

    constant = True

    def __init__(self, name: str, shape: str = "plane", **options):
        problems: list[str] = []
        unknown = sorted(set(options) - set(PLANE_DEFAULTS) - set(TUBE_DEFAULTS))
        if unknown:
            problems.append(f"unknown options {unknown}: valid are ['shape', {', '.join(map(repr, PLANE_DEFAULTS))}] "
                            f"for a plane and {list(TUBE_DEFAULTS)} for a tube")
        clean = check_surface(problems, shape, {k: v for k, v in options.items() if v is not None})
        if problems:
            raise BlockConfigError(problems, name)
        self.name = name
        self.shape = shape
        self.options = clean
        geom = plane_geometry(**clean) if shape == "plane" else tube_geometry(**clean)
        self.triangle_ids = geom.triangles.astype(np.int32)
        self.n_nodes = int(geom.positions.shape[0])
        self.n_triangles = int(geom.triangles.shape[0])
        logger.debug("rigid %s '%s': %d nodes, %d triangles", shape, name, self.n_nodes, self.n_triangles)
        self._values = {
            "positions": geom.positions.ravel(),
            "velocities": np.zeros(3 * self.n_nodes),
            "triangles": geom.triangles.astype(np.float64).ravel(),
        }
        nodes, tris = (self.n_nodes, 3), (self.n_triangles, 3)
        self.ports = {
            "positions": PortInfo("positions", "output", "Float64", "constant", "m", nodes,
                                  description="surface node positions"),
            "velocities": PortInfo("velocities", "output", "Float64", "constant", "m/s", nodes,
                                   description="surface node velocities (zero: rigid)"),
            "triangles": PortInfo("triangles", "output", "Int32", "constant", None, tris,
                                  description="node ids per triangle, normals towards the allowed side"),
        }

    @property
    def positions(self) -> np.ndarray:
        return self._values["positions"].reshape(-1, 3).copy()

    def evaluate(self, t: float) -> dict[str, np.ndarray]:
        checked_time(t)
        return {k: v.copy() for k, v in self._values.items()}
