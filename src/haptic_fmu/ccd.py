"""Continuous collision detection (CCD) of vertex-face and edge-edge pairs, batched.

Conservative by construction (no missed contact; see `ccd_kernels` for the method and its
floating-point error bound): a query is a hit when the two primitives come within the contact
margin at some time of the step. The returned time of impact (toi, fraction of the step in
[0, 1]) is a lower bound of the first contact time, early by at most about tolerance * L / speed.

Tolerances (L = the query's extent, the largest coordinate range over its points):
- `tolerance` (default 1e-6, relative to L): resolution. A part of the (t, u, w) domain that
  cannot be excluded is accepted as contact once F = (vertex - face point) or (edge point - edge
  point) varies by at most tolerance * L over it, or once the primitives are within
  tolerance * L (+ margin) of each other at its start time. So near misses closer than about
  tolerance * L may be reported as hits: the source of false positives.
- `min_separation` (default 1e-10, relative to L): contact margin, primitives closer than
  min_separation * L (L-infinity) count as touching. A round-off bound (6e-14 * max|coordinate|)
  is always added, which is what makes the exclusion test rigorous in floating point.
- `min_distance` (default 0, absolute, m): extra margin, e.g. a tool radius (L-infinity test, so
  conservative for the Euclidean distance).
- `max_boxes` (default 10000): work budget per query; if it runs out the query is reported as a
  hit at the earliest unresolved time (conservative) and a warning is logged. The hardest of
  the 7,279 sample queries needs 1661 boxes (about 50 ns each).

Linear motion: points move on straight lines from t=0 to t=1. Spline motion: cubic Hermite
trajectories from positions p0, p1 and velocities v0, v1 over [0, dt], i.e. Bezier control
points p0, p0 + v0 dt/3, p1 - v1 dt/3, p1; toi is the fraction of dt.
"""
import logging
from fractions import Fraction
from pathlib import Path

import numpy as np

from . import ccd_kernels

logger = logging.getLogger(__name__)

DEFAULT_TOLERANCE = 1e-6
DEFAULT_MIN_SEPARATION = 1e-10
DEFAULT_MAX_BOXES = 10_000
_STACK_CAPACITY = 4096


class CCDInputError(ValueError):
    """Invalid input to a continuous collision detection query."""


def _check_finite(name, array):
    if not np.all(np.isfinite(array)):
        bad = int(np.flatnonzero(~np.isfinite(array.reshape(array.shape[0], -1)).all(axis=1))[0])
        raise CCDInputError(f"{name} has non-finite values (first at query {bad}): pass finite float64 "
                            f"coordinates (positions in m, velocities in m/s)")


def _as_float_array(name, array, trailing_shape, meaning):
    array = np.asarray(array, dtype=np.float64)
    if array.ndim != 1 + len(trailing_shape) or array.shape[1:] != trailing_shape:
        raise CCDInputError(f"{name} must have shape (n, {', '.join(map(str, trailing_shape))}) (got {array.shape}): "
                            f"{meaning}")
    _check_finite(name, array)
    return array


def _check_options(tolerance, min_separation, min_distance, max_boxes):
    if not (np.isfinite(tolerance) and tolerance > 0.0):
        raise CCDInputError(f"tolerance must be > 0 (got {tolerance}): give a relative tolerance, e.g. 1e-6")
    if not (np.isfinite(min_separation) and min_separation >= 0.0):
        raise CCDInputError(f"min_separation must be >= 0 (got {min_separation}): give a relative margin, e.g. 1e-10")
    if not (np.isfinite(min_distance) and min_distance >= 0.0):
        raise CCDInputError(f"min_distance must be >= 0 (got {min_distance}): give an absolute margin in m, e.g. 0.001")
    if int(max_boxes) < 1:
        raise CCDInputError(f"max_boxes must be >= 1 (got {max_boxes}): give a work budget per query, e.g. 10000")


def _run(points, edge_edge, tolerance, min_separation, min_distance, max_boxes, return_stats):
    _check_options(tolerance, min_separation, min_distance, max_boxes)
    n = points.shape[0]
    hit = np.zeros(n, dtype=np.bool_)
    toi = np.full(n, np.inf)
    status = np.zeros(n, dtype=np.int8)
    boxes = np.zeros(n, dtype=np.int64)
    ccd_kernels.ccd_batch(np.ascontiguousarray(points), edge_edge, float(tolerance), float(min_separation),
                          float(min_distance), int(max_boxes), _STACK_CAPACITY, hit, toi, status, boxes)
    n_unresolved = int(np.count_nonzero(status))
    if n_unresolved:
        logger.warning("%d of %d CCD queries ran out of budget and were reported as conservative hits; "
                       "raise max_boxes or tolerance if this is frequent", n_unresolved, n)
    if return_stats:
        return hit, toi, {"unresolved": status.astype(bool), "boxes_checked": boxes}
    return hit, toi


def _linear_points(queries):
    queries = _as_float_array("queries", queries, (8, 3),
                              "8 points per query: the 4 primitive points at t0, then the same at t1")
    return queries.reshape(queries.shape[0], 2, 4, 3)


def vertex_face(queries, *, tolerance=DEFAULT_TOLERANCE, min_separation=DEFAULT_MIN_SEPARATION, min_distance=0.0,
                max_boxes=DEFAULT_MAX_BOXES, return_stats=False):
    """Linear-motion vertex-face CCD. queries (n, 8, 3): rows v, f0, f1, f2 at t0, then at t1.

    Returns (hit bool[n], toi float[n]) with toi in [0, 1] for hits and inf otherwise
    (plus a stats dict when return_stats).
    """
    return _run(_linear_points(queries), False, tolerance, min_separation, min_distance, max_boxes, return_stats)


def edge_edge(queries, *, tolerance=DEFAULT_TOLERANCE, min_separation=DEFAULT_MIN_SEPARATION, min_distance=0.0,
              max_boxes=DEFAULT_MAX_BOXES, return_stats=False):
    """Linear-motion edge-edge CCD. queries (n, 8, 3): rows ea0, ea1, eb0, eb1 at t0, then at t1."""
    return _run(_linear_points(queries), True, tolerance, min_separation, min_distance, max_boxes, return_stats)


def hermite_control_points(p0, p1, v0, v1, dt):
    """Bezier control points (n, 4, k, 3) of cubic Hermite trajectories over [0, dt] (arrays (n, k, 3))."""
    p0 = _as_float_array("p0", p0, (4, 3), "positions of the 4 points at the start of the step")
    n = p0.shape[0]
    p1 = _as_float_array("p1", p1, (4, 3), "positions of the 4 points at the end of the step")
    v0 = _as_float_array("v0", v0, (4, 3), "velocities of the 4 points at the start of the step")
    v1 = _as_float_array("v1", v1, (4, 3), "velocities of the 4 points at the end of the step")
    for name, a in (("p1", p1), ("v0", v0), ("v1", v1)):
        if a.shape[0] != n:
            raise CCDInputError(f"{name} has {a.shape[0]} queries but p0 has {n}: pass one row per query in all arrays")
    dt = np.asarray(dt, dtype=np.float64)
    if dt.ndim == 0:
        dt = np.full(n, float(dt))
    if dt.shape != (n,) or not np.all(np.isfinite(dt)) or np.any(dt <= 0.0):
        raise CCDInputError(f"dt must be a positive finite scalar or one per query, shape ({n},) (got {dt!r:.80}): "
                            f"give the step length in s, e.g. 0.001")
    scale = (dt / 3.0)[:, None, None]
    return np.stack([p0, p0 + v0 * scale, p1 - v1 * scale, p1], axis=1)


def vertex_face_spline(p0, p1, v0, v1, dt, *, tolerance=DEFAULT_TOLERANCE, min_separation=DEFAULT_MIN_SEPARATION,
                       min_distance=0.0, max_boxes=DEFAULT_MAX_BOXES, return_stats=False):
    """Vertex-face CCD on cubic Hermite (C1) trajectories. Arrays (n, 4, 3): v, f0, f1, f2; toi is a fraction of dt."""
    points = hermite_control_points(p0, p1, v0, v1, dt)
    return _run(points, False, tolerance, min_separation, min_distance, max_boxes, return_stats)


def edge_edge_spline(p0, p1, v0, v1, dt, *, tolerance=DEFAULT_TOLERANCE, min_separation=DEFAULT_MIN_SEPARATION,
                     min_distance=0.0, max_boxes=DEFAULT_MAX_BOXES, return_stats=False):
    """Edge-edge CCD on cubic Hermite (C1) trajectories. Arrays (n, 4, 3): ea0, ea1, eb0, eb1."""
    points = hermite_control_points(p0, p1, v0, v1, dt)
    return _run(points, True, tolerance, min_separation, min_distance, max_boxes, return_stats)


def read_sample_queries(csv_path):
    """Read a CCD benchmark file (8 rows per query of x_num, x_den, y_num, y_den, z_num, z_den, truth).

    Numerators may exceed 64 bits, so they are parsed as Python integers and converted exactly
    (power-of-two denominators). Returns queries (n, 8, 3) float64 and truth bool[n].
    """
    rows = []
    truth = []
    for line_number, line in enumerate(Path(csv_path).read_text().splitlines(), start=1):
        if not line.strip():
            continue
        fields = line.split(",")
        if len(fields) != 7:
            raise CCDInputError(f"{csv_path}:{line_number} has {len(fields)} columns, expected 7 "
                                f"(x_num, x_den, y_num, y_den, z_num, z_den, truth)")
        rows.append([float(Fraction(int(fields[2 * k]), int(fields[2 * k + 1]))) for k in range(3)])
        truth.append(int(fields[6]))
    if len(rows) % 8:
        raise CCDInputError(f"{csv_path} has {len(rows)} rows, not a multiple of 8 (8 rows per query)")
    queries = np.array(rows, dtype=np.float64).reshape(-1, 8, 3)
    truth = np.array(truth, dtype=np.int64).reshape(-1, 8)
    return queries, truth[:, 0].astype(bool)


def read_sample_query_set(root, kind):
    """All queries of one kind ('vertex-face' or 'edge-edge') under the sample-queries root, all scenes."""
    if kind not in ("vertex-face", "edge-edge"):
        raise CCDInputError(f"kind must be 'vertex-face' or 'edge-edge' (got {kind!r})")
    files = sorted(Path(root).glob(f"*/{kind}/*.csv"))
    if not files:
        raise CCDInputError(f"no {kind} csv files under {root}: give the ccd-sample-queries directory")
    parts = [read_sample_queries(f) for f in files]
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
