"""Isotropic remeshing of a lumen surface to the wall's element size, by gmsh.

A segmentation's surface has far more, and far less regular, triangles than the wall needs: a
marching-cubes surface of 0.3 mm triangles where the tensor-mass wall wants 2-3 mm elements, and
slivers that would become slivers of tetrahedra. Quadric decimation keeps the shape but not the
triangles' quality (measured on a 200k-triangle aneurysm: worst triangle quality 0.04, 1 % below
0.07); gmsh reparametrises the surface in patches and meshes it again with triangles of the asked
size (worst 0.2, 1 % below 0.57), keeping the open ends as boundary curves.

gmsh is a compiled library with its own system dependencies (OpenGL and X11 client libraries,
which its PyPI wheel links even when nothing is drawn); they are named when missing.
"""
from __future__ import annotations

import contextlib
import ctypes
import importlib
import logging
import math
import signal
import threading

import numpy as np
import trimesh

from .errors import AnatomyError

logger = logging.getLogger(__name__)

#: Dihedral angle above which gmsh keeps an edge as a feature (none on a smooth vessel: the ends'
#: rims are boundaries, not features).
FEATURE_ANGLE = math.radians(40.0)
#: The Debian/Ubuntu packages gmsh's wheel needs from the system.
SYSTEM_PACKAGES = "libglu1-mesa libxcursor1 libxft2 libxinerama1"


def gmsh_problem() -> str | None:
    """Why gmsh cannot be loaded here, with the fix; None when it can."""
    try:
        importlib.import_module("gmsh")
    except (ImportError, OSError) as exc:  # OSError: the wheel's library misses a system library
        return (f"remeshing needs gmsh, which could not be loaded ({exc}): install the project's dependencies "
                f"(pip install -e .) and gmsh's system libraries (apt-get install {SYSTEM_PACKAGES}), or keep the "
                "surface's own triangles (remesh='never')")
    return None


def _gmsh():
    problem = gmsh_problem()
    if problem:
        raise AnatomyError(problem)
    import gmsh

    return gmsh


@contextlib.contextmanager
def _sigpipe_kept():
    """gmsh's initialisation sets SIGPIPE back to the system's default, which kills the process on a
    write to a closed pipe; Python ignores it (a BrokenPipeError instead), and so must the process
    after remeshing (a run that follows would die with its worker's pipe)."""
    previous = signal.getsignal(signal.SIGPIPE)
    try:
        yield
    finally:
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGPIPE, previous)
        elif previous == signal.SIG_IGN:  # signal.signal is the main thread's; the C call is anyone's
            ctypes.CDLL(None).signal(signal.SIGPIPE, ctypes.c_void_p(1))   # SIG_IGN
        else:
            logger.warning("gmsh reset SIGPIPE to its default in a thread that cannot restore its handler")


def remesh(mesh: trimesh.Trimesh, edge_length: float) -> trimesh.Trimesh:
    """The surface meshed again with triangles of about ``edge_length`` (m); orientation is not kept
    (gmsh's patches are wound independently): check the result with :func:`anatomy.surface.check_surface`."""
    if not (math.isfinite(edge_length) and edge_length > 0):
        raise AnatomyError(f"edge_length must be a length > 0 in metres (got {edge_length!r}), e.g. 0.003")
    gmsh = _gmsh()
    with _sigpipe_kept():
        gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)       # the same triangles on every machine
        gmsh.model.add("lumen")
        surface = gmsh.model.addDiscreteEntity(2)
        tags = np.arange(1, len(mesh.vertices) + 1)
        gmsh.model.mesh.addNodes(2, surface, tags, np.asarray(mesh.vertices, dtype=np.float64).ravel())
        gmsh.model.mesh.addElementsByType(surface, 2, [], (np.asarray(mesh.faces) + 1).ravel())
        gmsh.model.mesh.classifySurfaces(FEATURE_ANGLE, True, True, math.pi)
        gmsh.model.mesh.createGeometry()
        gmsh.option.setNumber("Mesh.MeshSizeMin", edge_length)
        gmsh.option.setNumber("Mesh.MeshSizeMax", edge_length)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
        gmsh.option.setNumber("Mesh.Algorithm", 6)             # frontal-Delaunay: the most regular triangles
        gmsh.model.mesh.generate(2)
        node_tags, coordinates, _ = gmsh.model.mesh.getNodes()
        _, triangle_nodes = gmsh.model.mesh.getElementsByType(2)
    except Exception as exc:  # gmsh raises a bare Exception carrying its last error
        raise AnatomyError(f"remeshing the surface with gmsh failed ({exc}): try another edge_length, or keep the "
                           "surface's own triangles (remesh='never')") from None
    finally:
        gmsh.finalize()
    index = np.zeros(int(node_tags.max()) + 1, dtype=np.int64)
    index[node_tags.astype(np.int64)] = np.arange(len(node_tags))
    faces = index[np.asarray(triangle_nodes, dtype=np.int64).reshape(-1, 3)]
    result = trimesh.Trimesh(coordinates.reshape(-1, 3), faces, process=False)
    result.merge_vertices(digits_vertex=None)
    result.remove_unreferenced_vertices()
    logger.info("remeshed %d triangles into %d at an edge length of %.3g mm", len(mesh.faces), len(result.faces),
                edge_length * 1e3)
    return result
