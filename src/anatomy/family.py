"""A family of parametric aneurysms, each exported as a lumen surface that takes the patients' path.

Every member is a frozen parameter dataclass (registered in :data:`FAMILY`) whose ``surface()`` is
a lumen surface like a segmentation's: a triangle mesh in metres, its normals pointing out of the
lumen into the wall, its open ends planar boundary loops. A surface goes through
:mod:`anatomy.surface`, :mod:`anatomy.wall` and :mod:`anatomy.centerline` like patient data.

Members (each a ``...Parameters`` dataclass; its fields document the defaults):

``fusiform``
    The symmetric spindle of :func:`tissue_fmu.mesh.aaa_mesh`: the same radius r(z)
    (:func:`tissue_fmu.mesh.aaa_inner_radius`) about the z axis, z in [0, segment_length].
``saccular``
    A straight aorta with a sac bulging on one side (towards ``sac_azimuth_deg``).
``eccentric``
    A fusiform sac whose cross-sections are circles offset from the aortic axis.
``angulated_neck``
    The sac's axis along z; above it the proximal neck bends by ``neck_angle_deg``.
``tortuous``
    The axis winds about z (a helix whose radius fades to zero at both ends), with a sac.
``bifurcation``
    The aorta with a sac splitting into the two common iliac arteries, an implicit surface
    (a smooth union of tubes) meshed by marching tetrahedra.

Frame (like 3D Slicer's RAS): x to the patient's right, y anterior, z superior. The proximal
(renal level) end is the highest, the distal (access) ends lie at z = 0, so that access from
below is the lowest end. Lengths are in metres, angles in degrees.

Published ranges: each member keeps one table (``RANGES``) giving every parameter its range and
the source of it. A value outside raises :class:`AnatomyError` naming the parameter, the value,
the range and the source; ``strict=False`` (for stress tests beyond the clinical ranges) logs a
warning instead. Where no guideline or study gives a bound, the table says so: those bounds are
plausibility limits of this model. Shapes that cannot be built (a sac narrower than its aorta, a
bend tighter than the tube, a lumen that curves tighter than a wall can follow: a radius of curvature,
concave or convex, below :data:`MIN_FOLD_RADIUS`) raise whatever ``strict`` says. The folds are exact
where the shape has a closed form (the sac's profile, the saccular's rim, the neck's bend) and measured
on the surface's definition where it has none (a sac on a winding axis, the bifurcation's junction).

Resolution: ``edge_length`` is the target mean length of the triangles' edges (2.5 mm by
default); ``triangles`` asks for about that many triangles instead (e.g. 200 000 for a benchmark).
The bifurcation's marching grid keeps at least two steps across an iliac's diameter, so with iliacs
narrower than about 5 mm in radius its triangles come out finer than asked.

Besides its surface, a member gives its open ends as the parameters define them (``ends()``: the
distal, access ends first, the proximal end last) and where a scene aims the catheter
(``sac()``, or :func:`sac_center`): the sac's widest cross-section and its farthest wall.

Public functions: :func:`lumen_surface`, :func:`sac_center`, :func:`export_lumen_surface`.
"""
from __future__ import annotations

import logging
import math
from dataclasses import KW_ONLY, InitVar, dataclass, fields
from functools import cached_property
from pathlib import Path
from typing import ClassVar

import numpy as np
import trimesh
from scipy import sparse

from tissue_fmu.mesh import aaa_inner_radius

from .ends import boundary_edges, capped, open_ends
from .errors import AnatomyError

logger = logging.getLogger(__name__)

__all__ = [
    "FAMILY",
    "DEFAULT_EDGE_LENGTH",
    "MIN_FOLD_RADIUS",
    "Range",
    "EndSpec",
    "SacSite",
    "FusiformParameters",
    "SaccularParameters",
    "EccentricParameters",
    "AngulatedNeckParameters",
    "TortuousParameters",
    "BifurcationParameters",
    "lumen_surface",
    "sac_center",
    "export_lumen_surface",
]

DEFAULT_EDGE_LENGTH = 0.0025
EXPORT_FORMATS = (".stl", ".obj", ".ply")
# The curvature of a swept tube's axis times its largest radius must stay below this: at 1 the
# rings on the inner side of a bend meet; 0.8 keeps the inner wall's triangles from collapsing.
MAX_CURVATURE_RADIUS = 0.8
# Above this the marching grid (nodes) or a sweep (vertices) would not fit in memory comfortably.
MAX_GRID_NODES = 60_000_000
# The tightest radius of curvature (m) a lumen may have, concave or convex (seen from outside). The wall is built by
# offsetting the lumen outward by its thickness t (anatomy.wall, 1.5 mm by default): over a concave fold of radius
# rho its outer face shrinks by 1 - t / rho (folding at rho = t, where the outside crosses itself), over a convex
# one it stretches by 1 + t / rho (its elements turn to slivers as rho -> 0). Twice t (3 mm) would be the round
# margin, but the defaults curve tighter (the saccular sac's rim 2.10 mm, the tortuous sac's dome on the inside of
# its bend 2.43 mm, the bifurcation's crotch 2.94 mm) and build: 2 mm keeps a third over t (the outer face at least
# a quarter of the inner one) and admits them.
MIN_FOLD_RADIUS = 0.002

# ------------------------------------------------------------------------------ the sources

SVS_2018 = "SVS practice guidelines (Chaikof et al., J Vasc Surg 2018;67:2-77)"
ESVS_2019 = "ESVS guidelines (Wanhainen et al., Eur J Vasc Endovasc Surg 2019;57:8-93)"
ENDURANT_IFU = ("EVAR instructions for use, Medtronic Endurant II (aortic neck diameter 19-32 mm, neck length "
                ">= 10 mm, infrarenal neck angulation <= 60 deg, iliac diameter 8-25 mm)")
EXCLUDER_IFU = "Gore Excluder instructions for use (neck length >= 15 mm, neck angulation <= 60 deg)"
ROTTERDAM = ("Rotterdam Study (Zhu et al., Sci Rep 2021;11:17762: normal infrarenal diameter median (IQR) "
             "17 (15-18) mm in women, 19 (18-21) mm in men)")
MODEL_LIMIT = "no published range: a plausibility limit of this model"

_AORTA_RANGE_SOURCE = (f"lower bound: the lower quartile of the normal infrarenal aorta in women, {ROTTERDAM}; "
                       f"upper bound: the widest aortic neck on label, {ENDURANT_IFU}")
_SAC_RANGE_SOURCE = (f"lower bound: the definition of an AAA, diameter >= 30 mm ({SVS_2018}; {ESVS_2019}; both "
                     "set elective repair at 55 mm in men); upper bound 100 mm: " + MODEL_LIMIT)


@dataclass(frozen=True)
class Range:
    """A parameter's accepted range, [low, high] in the parameter's unit, and where it comes from."""

    low: float
    high: float
    #: "m", "deg" or "" (a ratio or a count)
    unit: str
    source: str
    #: a radius whose clinical range is published as a diameter (the message shows both)
    diameter: bool = False

    def span(self) -> str:
        """The range as published: millimetres (and the diameters) for lengths."""
        if self.unit != "m":
            return f"{self.low:g}-{self.high:g} {self.unit}".rstrip()
        text = f"{1e3 * self.low:g}-{1e3 * self.high:g} mm"
        return text + (f" (diameter {2e3 * self.low:g}-{2e3 * self.high:g} mm)" if self.diameter else "")

    def shown(self, value: float) -> str:
        if self.unit != "m":
            return f"{value:g} {self.unit}".rstrip()
        return f"{value:g} m ({1e3 * value:g} mm" + (f", diameter {2e3 * value:g} mm)" if self.diameter else ")")


@dataclass(frozen=True)
class EndSpec:
    """An open end as the parameters define it (the surface's loop approximates it)."""

    name: str
    #: centre of the end's circle, m
    center: np.ndarray
    #: unit normal of the end's plane pointing out of the vessel
    normal: np.ndarray
    #: radius of the end's circle, m
    radius: float


@dataclass(frozen=True)
class SacSite:
    """Where a scene aims the catheter: the sac's widest cross-section and its farthest wall."""

    #: the point of the vessel's axis (the swept centerline, for the bifurcation the aorta's axis)
    #: at the sac's widest cross-section, m
    center: np.ndarray
    #: unit tangent of that axis at ``center``, towards the proximal end
    axis: np.ndarray
    #: unit vector perpendicular to ``axis`` from ``center`` to the farthest point of the sac's wall
    #: in that cross-section (a sac of revolution has none: then the outer side of the axis's bend,
    #: or +x where the axis is straight)
    direction: np.ndarray
    #: distance from ``center`` to the wall along ``direction``, m
    reach: float
    #: the largest lumen diameter of that cross-section (the sac's clinical diameter), m
    diameter: float


# ------------------------------------------------------------------------------ shape helpers


def _bump(x, centre: float, length: float) -> np.ndarray:
    """C1 bump cos^2 over |x - centre| < length / 2, zero outside (tissue_fmu.mesh's sac profile):
    value and slope vanish at its ends, so the sac meets the healthy aorta without a kink."""
    xi = (np.asarray(x, dtype=np.float64) - centre) / length
    return np.where(np.abs(xi) < 0.5, np.cos(np.pi * xi) ** 2, 0.0)


def _angle_bump(theta, centre: float, width: float) -> np.ndarray:
    """The C1 bump in angle: cos^2 over |theta - centre| < width / 2 (wrapped), zero elsewhere."""
    wrapped = np.angle(np.exp(1j * (np.asarray(theta, dtype=np.float64) - centre)))
    return _bump(wrapped, 0.0, width)


def _smoothstep(t) -> np.ndarray:
    """0 -> 1 over t in [0, 1] with zero slope at both ends (C1), clamped outside."""
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (C1): the union of two distance fields with a fillet of about k."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from points (n, 3) to the segment [a, b]."""
    ab = b - a
    pa = p - a
    t = np.clip(pa @ ab / (ab @ ab), 0.0, 1.0)
    d = pa - t[:, None] * ab
    return np.sqrt(np.einsum("ij,ij->i", d, d))


# ------------------------------------------------------------------------------ the parameter tables

# The ranges of the fields every member has (see _Member), and with them the segment's length for the members that
# have one: a member merges them into its RANGES ({**_ANEURYSM_RANGES, ...}), overriding a range where its own differs.
_ANEURYSM_RANGES: dict[str, Range] = {
    "aorta_radius": Range(0.0075, 0.016, "m", _AORTA_RANGE_SOURCE, diameter=True),
    "aneurysm_radius": Range(0.015, 0.050, "m", _SAC_RANGE_SOURCE, diameter=True),
    "aneurysm_length": Range(0.020, 0.150, "m", MODEL_LIMIT),
}
_SEGMENT_RANGES: dict[str, Range] = {**_ANEURYSM_RANGES, "segment_length": Range(0.060, 0.250, "m", MODEL_LIMIT)}


@dataclass(frozen=True)
class _Member:
    """Common behaviour of the family's parameter dataclasses.

    Every member is an aorta with a sac, so the three fields saying so are declared here (first, in
    every member's keyword order; a member redeclares one to change its default); the others and
    ``RANGES`` are in each member.
    """

    KIND: ClassVar[str] = ""
    RANGES: ClassVar[dict[str, Range]] = {}
    #: number of open ends of the surface
    N_ENDS: ClassVar[int] = 2
    #: what the error for a sac narrower than the aorta suggests
    _SAC_OUTWARD_FIX: ClassVar[str] = "the sac bulges outward"
    #: what _sac_height is, in the parameters (for the error of a sac that folds)
    _SAC_HEIGHT: ClassVar[str] = "aneurysm_radius - aorta_radius"
    #: the parameters that shape a fold found by measuring the surface, and what the error suggests
    _FOLD_PARAMETERS: ClassVar[tuple[str, ...]] = ("aorta_radius", "aneurysm_radius", "aneurysm_length")
    _FOLD_FIX: ClassVar[str] = "lengthen the sac or reduce its radius"
    #: lumen radius of the healthy aorta, m
    aorta_radius: float = 0.010
    #: the sac's largest lumen radius, m (half its clinical diameter)
    aneurysm_radius: float = 0.025
    #: the sac's length along the axis, m
    aneurysm_length: float = 0.060
    _: KW_ONLY
    #: False: a value outside its published range only logs a warning (stress tests); shapes that
    #: cannot be built still raise
    strict: InitVar[bool] = True

    def __post_init__(self, strict: bool) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not _is_number(value):
                raise AnatomyError(f"{self.KIND}: {f.name} must be a finite number (got {value!r}); "
                                   f"e.g. its default {f.default!r}")
            bounds = self.RANGES[f.name]
            if bounds.unit == "m" and bounds.low > 0.0 and value <= 0.0:
                raise AnatomyError(f"{self.KIND}: {f.name} must be > 0 m (got {value!r}); e.g. its default "
                                   f"{f.default!r}")
            if bounds.low <= value <= bounds.high:
                continue
            text = (f"{self.KIND}: {f.name} = {bounds.shown(value)} is outside its range {bounds.span()}; "
                    f"source: {bounds.source}")
            if strict:
                raise AnatomyError(f"{text}. Give a value in the range, or pass strict=False to build it anyway "
                                   "(a stress test beyond the clinical range; it then logs a warning)")
            logger.warning("%s; built anyway (strict=False)", text)
        self._check_shape()

    def _check_shape(self) -> None:
        """Raise for parameters whose shape cannot be built (whatever ``strict`` says); a member extends it,
        calling this first."""
        self._check_sac_outward()
        self._check_sac_fold()

    def _check_sac_outward(self) -> None:
        if self.aneurysm_radius < self.aorta_radius:
            self._fail(f"aneurysm_radius ({self.aneurysm_radius:g}) < aorta_radius ({self.aorta_radius:g})",
                       self._SAC_OUTWARD_FIX)

    def _sac_height(self) -> float:
        """Height h of the cos^2 bump of the sac's most bulging meridian (its wall's distance from the axis is
        aorta_radius + h bump along the axis); a member whose sac bulges farther than it widens overrides it."""
        return self.aneurysm_radius - self.aorta_radius

    def _check_sac_fold(self) -> None:
        """The sac's meridian aorta_radius + h cos^2(pi x / L) has r'' = -(2 pi^2 h / L^2) cos(2 pi x / L): its
        curvature r'' / (1 + r'^2)^(3/2) is largest, 2 pi^2 h / L^2, where r' = 0: at the centre (convex) and at
        the junctions with the aorta (concave)."""
        height = self._sac_height()
        if height <= 0.0:
            return
        length = self.aneurysm_length
        radius = length * length / (2.0 * math.pi ** 2 * height)
        if radius >= MIN_FOLD_RADIUS:
            return
        # the bounds that would meet the limit: the length for this height, the radius for this length
        shortest = math.sqrt(2.0 * math.pi ** 2 * height * MIN_FOLD_RADIUS)
        widest = self.aorta_radius + (self.aneurysm_radius - self.aorta_radius) * (
            length * length / (2.0 * math.pi ** 2 * MIN_FOLD_RADIUS)) / height
        self._fail(f"the sac's profile (aneurysm_radius {self.aneurysm_radius:g} m over aneurysm_length {length:g} m "
                   f"on aorta_radius {self.aorta_radius:g} m) curves with a radius of {radius * 1e3:.3g} mm at its "
                   f"centre and where it meets the aorta (aneurysm_length^2 / (2 pi^2 h), h = {self._SAC_HEIGHT} = "
                   f"{height * 1e3:.3g} mm), tighter than a wall can follow (MIN_FOLD_RADIUS "
                   f"{MIN_FOLD_RADIUS * 1e3:g} mm)",
                   f"lengthen the sac (aneurysm_length at least {shortest * 1e3:.3g} mm) or reduce its radius "
                   f"(aneurysm_radius at most {widest * 1e3:.3g} mm)")

    def _sac_profile(self, x, centre: float) -> np.ndarray:
        """Radius of a sac of revolution centred at ``centre`` (x and centre along the axis): the aorta's,
        widening over aneurysm_length to aneurysm_radius at the centre."""
        return self.aorta_radius + (self.aneurysm_radius - self.aorta_radius) * _bump(x, centre, self.aneurysm_length)

    def _fail(self, what: str, fix: str) -> None:
        raise AnatomyError(f"{self.KIND}: {what}: {fix}")

    def _shown(self, names: tuple[str, ...]) -> str:
        """The named parameters and their values, for an error."""
        return ", ".join(f"{name} {getattr(self, name):g} {self.RANGES[name].unit}".rstrip() for name in names)

    # -- the surface

    def surface(self, edge_length: float | None = None, triangles: int | None = None) -> trimesh.Trimesh:
        """The lumen surface: metres, normals out of the lumen, the open ends planar loops.

        ``edge_length``: target edge length of the triangles, m (default 2.5 mm); ``triangles``:
        about this many triangles instead (the edge length scaled from a default-size surface).
        """
        if triangles is not None:
            if edge_length is not None:
                raise AnatomyError("give edge_length or triangles, not both")
            count = _positive("triangles", triangles, "200000")
            trial = self._build(DEFAULT_EDGE_LENGTH)
            # the count scales as 1 / edge_length^2 on a surface of fixed area (scaled from the edges the
            # trial has, which are finer than asked where a member needs it)
            edge_length = float(trial.edges_unique_length.mean()) * math.sqrt(len(trial.faces) / count)
        h = DEFAULT_EDGE_LENGTH if edge_length is None else _positive("edge_length", edge_length, "0.0025 (m)")
        narrowest = min(end.radius for end in self.ends())
        if h > narrowest:
            raise AnatomyError(f"{self.KIND}: edge_length {h:g} m is coarser than the narrowest end's radius "
                               f"({narrowest:g} m): use an edge length of at most that")
        mesh = self._build(h)
        _check_surface(mesh, self.KIND, self.N_ENDS)
        return mesh

    def _build(self, edge_length: float) -> trimesh.Trimesh:
        raise NotImplementedError

    def ends(self) -> list[EndSpec]:
        """The open ends as the parameters define them: the distal (access) ends first."""
        raise NotImplementedError

    def sac(self) -> SacSite:
        raise NotImplementedError


def _is_number(value) -> bool:
    """A finite real number (a bool is refused: True is no length)."""
    return (not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating))
            and math.isfinite(value))


def _positive(name: str, value, example: str) -> float:
    if not _is_number(value) or value <= 0:
        raise AnatomyError(f"{name} must be a finite number > 0 (got {value!r}): e.g. {example}")
    return float(value)


def _check_surface(mesh: trimesh.Trimesh, kind: str, n_ends: int) -> None:
    """The properties every member promises, checked on the built surface (a failure is a shape the
    parameters make impossible, e.g. branches that touch)."""
    ends = open_ends(mesh)
    closed = capped(mesh, ends)
    if not (mesh.is_winding_consistent and closed.is_watertight and len(ends) == n_ends and closed.volume > 0):
        raise AnatomyError(f"{kind}: the surface came out broken ({len(ends)} open ends for {n_ends}, watertight "
                           f"when capped: {closed.is_watertight}): the parameters make parts of the vessel meet; "
                           "move them back into their published ranges")


# ------------------------------------------------------------------------------ swept tubes


@dataclass(frozen=True)
class _Axis:
    """A swept tube's axis, finely sampled: arc length, points, tangents and a rotation-minimising
    frame (n1, n2) that turns as little as possible about the tangent (no artificial twist)."""

    u: np.ndarray
    s: np.ndarray
    points: np.ndarray
    tangents: np.ndarray
    n1: np.ndarray

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def at(self, s: np.ndarray, axis_function) -> tuple[np.ndarray, ...]:
        """(points, tangents, n1, n2) at arc lengths s: points on the exact curve, the frame
        interpolated from the fine samples and made orthonormal again."""
        s = np.asarray(s, dtype=np.float64)
        points = axis_function(np.interp(s, self.s, self.u))
        tangents = _unit(np.stack([np.interp(s, self.s, self.tangents[:, i]) for i in range(3)], axis=1))
        n1 = np.stack([np.interp(s, self.s, self.n1[:, i]) for i in range(3)], axis=1)
        n1 = _unit(n1 - np.sum(n1 * tangents, axis=1, keepdims=True) * tangents)
        return points, tangents, n1, np.cross(tangents, n1)


def _sample_axis(axis_function, samples: int = 4097) -> _Axis:
    u = np.linspace(0.0, 1.0, samples)
    points = axis_function(u)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    tangents = _unit(np.gradient(points, s, axis=0))
    # Double reflection (Wang, Juettler, Zheng, Liu, ACM Trans Graph 2008): the rotation-minimising
    # frame, sequential by nature (each frame reflects the previous one).
    reference = np.array([1.0, 0.0, 0.0]) if abs(tangents[0, 0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    n1 = np.empty_like(points)
    n1[0] = _unit(reference - (reference @ tangents[0]) * tangents[0])
    for i in range(samples - 1):
        v1 = points[i + 1] - points[i]
        c1 = v1 @ v1
        r_left = n1[i] - (2.0 / c1) * (v1 @ n1[i]) * v1
        t_left = tangents[i] - (2.0 / c1) * (v1 @ tangents[i]) * v1
        v2 = tangents[i + 1] - t_left
        c2 = v2 @ v2
        n1[i + 1] = r_left - (2.0 / c2) * (v2 @ r_left) * v2 if c2 > 1e-30 else r_left
    return _Axis(u, s, points, tangents, n1)


def _zipper(theta: np.ndarray, ring_of: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Triangles between consecutive rings of (possibly) different vertex counts.

    ``theta``: every ring's vertex angles, increasing from 0 within each ring, rings one after the
    other (``ring_of`` their ring, ``offsets`` each ring's first vertex). Between ring A (lower) and
    B the next vertex of either ring is taken in the order of its angle (the greedy 'zipper' of
    lofting): n_A + n_B triangles per pair, wound so that their normals point away from the axis.
    """
    n_rings = len(offsets)
    counts = np.diff(np.append(offsets, len(theta)))
    last = np.append(ring_of[1:] != ring_of[:-1], True)
    following = np.where(last, 2.0 * np.pi, np.append(theta[1:], 0.0))   # where each ring edge ends
    as_a, as_b = ring_of < n_rings - 1, ring_of > 0
    pair = np.concatenate([ring_of[as_a], ring_of[as_b] - 1])
    key = np.concatenate([following[as_a], following[as_b]])
    from_a = np.concatenate([np.ones(as_a.sum(), dtype=bool), np.zeros(as_b.sum(), dtype=bool)])
    order = np.lexsort((~from_a, key, pair))
    pair, from_a = pair[order], from_a[order]
    # how many edges of each ring the pair's zipper has passed before each step
    start = np.searchsorted(pair, np.arange(n_rings - 1))
    a_before = np.cumsum(from_a) - from_a
    b_before = np.cumsum(~from_a) - ~from_a
    a_before = a_before - a_before[start][pair]
    b_before = b_before - b_before[start][pair]
    n_a, n_b = counts[pair], counts[pair + 1]
    a_i = offsets[pair] + a_before % n_a
    a_next = offsets[pair] + (a_before + 1) % n_a
    b_j = offsets[pair + 1] + b_before % n_b
    b_next = offsets[pair + 1] + (b_before + 1) % n_b
    return np.where(from_a[:, None], np.stack([a_i, a_next, b_j], axis=1), np.stack([a_i, b_next, b_j], axis=1))


@dataclass(frozen=True)
class _Swept(_Member):
    """A tube swept along an axis curve c(u), u in [0, 1], with radius r(s, theta) about it (s the arc
    length, theta the angle from the frame's n1 towards n2). Rings of vertices lie in the axis's
    normal planes (so the end rings are planar), spaced evenly along the mean meridian, and each
    ring's vertices evenly along its own perimeter."""

    def _axis_function(self, u: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _radius(self, s: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """r(s, theta); here a sac of revolution centred at the sac's arc length."""
        r = self._sac_profile(s, self._sac_arc_length())
        return np.broadcast_to(r, np.broadcast_shapes(np.shape(s), np.shape(theta)))

    @cached_property
    def _axis(self) -> _Axis:
        return _sample_axis(self._axis_function)

    def __post_init__(self, strict: bool) -> None:
        super().__post_init__(strict)
        # after the member's own checks: they name what the sweep would only find broken
        self._check_sweep()
        self._check_folds()

    def _fine_surface(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(points (n_s, n_theta, 3), radii (n_s, n_theta)) on the fine axis samples."""
        axis = self._axis
        radii = self._radius(axis.s[:, None], theta[None, :])
        n2 = np.cross(axis.tangents, axis.n1)
        directions = (np.cos(theta)[None, :, None] * axis.n1[:, None, :]
                      + np.sin(theta)[None, :, None] * n2[:, None, :])
        return axis.points[:, None, :] + radii[..., None] * directions, radii

    def _check_sweep(self) -> None:
        """No ring crosses its neighbours (curvature x radius < MAX_CURVATURE_RADIUS) and no part of the
        tube comes back to touch another (the axis points far apart along it stay apart in space)."""
        axis = self._axis
        radii = self._radius(axis.s[:, None], np.linspace(0.0, 2.0 * np.pi, 64, endpoint=False)[None, :])
        if (radii <= 0).any():
            self._fail("the radius becomes <= 0", "keep the sac larger than the aorta")
        reach = radii.max(axis=1)
        curvature = np.linalg.norm(np.gradient(axis.tangents, axis.s, axis=0), axis=1)
        worst = int(np.argmax(curvature * reach))
        if curvature[worst] * reach[worst] > MAX_CURVATURE_RADIUS:
            self._fail(f"the axis bends with a radius of {1e3 / curvature[worst]:.3g} mm at "
                       f"{np.round(1e3 * axis.points[worst], 1).tolist()} mm where the lumen reaches "
                       f"{1e3 * reach[worst]:.3g} mm from it, so the inner wall would fold",
                       f"keep the bend radius above {1 / MAX_CURVATURE_RADIUS:g} x the lumen radius there "
                       "(a gentler bend, or a smaller sac)")
        pick = np.linspace(0, len(axis.s) - 1, 400).astype(np.int64)
        s, points, r = axis.s[pick], axis.points[pick], reach[pick]
        distance = np.linalg.norm(points[:, None] - points[None, :], axis=2)
        apart = np.abs(s[:, None] - s[None, :]) > 2.0 * (r[:, None] + r[None, :])
        touching = apart & (distance < r[:, None] + r[None, :])
        if touching.any():
            i, j = np.argwhere(touching)[0]
            self._fail(f"the tube meets itself near {np.round(1e3 * points[i], 1).tolist()} mm and "
                       f"{np.round(1e3 * points[j], 1).tolist()} mm", "wind the axis less or shrink the sac")

    def _check_folds(self) -> None:
        """No principal curvature of the surface beyond 1 / MIN_FOLD_RADIUS, measured: where the sac's profile
        meets a bend of the axis (the sac on the inner side of a bend is squeezed along the axis by 1 - kappa r)
        the shape has no closed form, so the curvatures are those of the swept surface's own definition sampled
        on a fine grid (every second axis sample, 128 angles).

        Where a bend begins, the inner wall's speed along the axis drops at once to 1 - kappa r: the surface is
        smooth there, its parametrisation is not, and second differences (or normals from chords) across it would
        show a fold that is not there. So the normal is the exact one at each sample (the sweep's derivatives
        from the axis's exact tangent and curvature: the rings turn only about the binormal), and the shape
        operator A (-dn = dX A, its eigenvalues the principal curvatures) comes from the normals' turn between
        neighbouring samples over the step between them. Like the chord of a circle this falls a little short
        of the exact curvature, and averages it where it jumps (where a cos^2 sac meets the aorta, 1 % short;
        at the saccular's rim, whose concave peak is narrower than the 2.8 degree step, up to a third): a shape
        the exact formulas (the sac's profile, the saccular's rim, the neck's bend) admit is not refused here,
        and those they refuse get their exact message first. On a sac of revolution on a bent axis, the
        member this is for, four times the samples each way change the result by under 1 %."""
        axis = self._axis
        theta = np.linspace(0.0, 2.0 * np.pi, 128, endpoint=False)
        u, s, centres = axis.u[::2], axis.s[::2], axis.points[::2]
        du = 1e-6
        ahead, behind = self._axis_function(u + du), self._axis_function(u - du)
        velocity = (ahead - behind) / (2.0 * du)
        speed = np.linalg.norm(velocity, axis=1, keepdims=True)
        tangents = velocity / speed
        bend = (ahead - 2.0 * centres + behind) / (du * speed) ** 2
        bend -= np.sum(bend * tangents, axis=1, keepdims=True) * tangents          # d tangent / ds
        n1 = _unit(axis.n1[::2] - np.sum(axis.n1[::2] * tangents, axis=1, keepdims=True) * tangents)
        n2 = np.cross(tangents, n1)
        cos, sin = np.cos(theta)[None, :, None], np.sin(theta)[None, :, None]
        directions = cos * n1[:, None, :] + sin * n2[:, None, :]
        radii = self._radius(s[:, None], theta[None, :])
        points = centres[:, None, :] + radii[..., None] * directions
        # the sweep's derivatives along the axis and around it, the radius's over 0.1 um and 1e-7 rad (over the
        # samples' spacing they would be off where its curvature jumps, and the normal with them)
        s_, theta_ = s[:, None], theta[None, :]
        along = (self._radius(s_ + 1e-7, theta_) - self._radius(s_ - 1e-7, theta_)) / 2e-7
        around = (self._radius(s_, theta_ + 1e-7) - self._radius(s_, theta_ - 1e-7)) / 2e-7
        d_s = (tangents[:, None, :] * (1.0 - radii * np.einsum("ik,ijk->ij", bend, directions))[..., None]
               + along[..., None] * directions)
        d_t = around[..., None] * directions + radii[..., None] * (-sin * n1[:, None, :] + cos * n2[:, None, :])
        normal = _unit(np.cross(d_t, d_s))
        # out of the lumen: away from the axis (whatever the frame's handedness)
        normal *= np.sign(np.einsum("ijk,ijk->ij", normal, points - centres[:, None]))[..., None]

        def dot(a, b):
            return np.einsum("ijk,ijk->ij", a, b)

        # the central differences along the axis and around it: the moves (a, b) and the normal's turns (p, q)
        a, p = np.gradient(points, axis=0), np.gradient(normal, axis=0)
        b = 0.5 * (np.roll(points, -1, axis=1) - np.roll(points, 1, axis=1))
        q = 0.5 * (np.roll(normal, -1, axis=1) - np.roll(normal, 1, axis=1))
        # least squares -[p q] = [a b] A, A = -G^-1 R (G = [a b]^T [a b], R = [a b]^T [p q]); its trace and
        # determinant give the principal curvatures (with the normal outward, concave seen from outside positive)
        g11, g12, g22 = dot(a, a), dot(a, b), dot(b, b)
        r11, r12, r21, r22 = dot(a, p), dot(a, q), dot(b, p), dot(b, q)
        g_det = g11 * g22 - g12 * g12
        half_trace = -0.5 * (g22 * r11 - g12 * r21 - g12 * r12 + g11 * r22) / g_det
        det = (r11 * r22 - r12 * r21) / g_det
        spread = np.sqrt(np.maximum(half_trace ** 2 - det, 0.0))
        # the rows at the ends have one-sided differences (the tube is straight there anyway)
        inner = slice(2, -2)
        for side, curvature in (("concave", (half_trace + spread)[inner]), ("convex", -(half_trace - spread)[inner])):
            worst = np.unravel_index(int(np.argmax(curvature)), curvature.shape)
            if curvature[worst] * MIN_FOLD_RADIUS > 1.0:
                where = (np.round(1e3 * points[inner][worst], 1) + 0.0).tolist()
                self._fail(f"the lumen curves with a {side} radius of {1e3 / curvature[worst]:.3g} mm at {where} mm "
                           f"({self._shown(self._FOLD_PARAMETERS)}; measured on the swept surface: no closed form "
                           f"there), tighter than a wall can follow (MIN_FOLD_RADIUS {MIN_FOLD_RADIUS * 1e3:g} mm)",
                           self._FOLD_FIX)

    def _build(self, edge_length: float) -> trimesh.Trimesh:
        axis = self._axis
        theta_fine = np.linspace(0.0, 2.0 * np.pi, 257)
        fine, _ = self._fine_surface(theta_fine[:-1])
        # the quads' sides: their diagonals make the mean edge about 1.1 times the side
        side = edge_length / 1.1
        # rings placed by the mean meridian length: in a bend the outer wall's edges grow and the
        # inner wall's shrink about equally (spacing by the longest meridian squashes the inner ones)
        step = np.linalg.norm(np.diff(fine, axis=0), axis=2).mean(axis=1)
        meridian = np.concatenate([[0.0], np.cumsum(step)])
        n_rings = max(2, math.ceil(meridian[-1] / side) + 1)
        if n_rings * 2.0 * np.pi * self._radius(axis.s, 0.0).max() / side > MAX_GRID_NODES:
            raise AnatomyError(f"{self.KIND}: edge_length {edge_length:g} m makes too many vertices: use a larger one")
        s_rings = np.interp(np.linspace(0.0, meridian[-1], n_rings), meridian, axis.s)
        s_rings[0], s_rings[-1] = 0.0, axis.length
        centers, tangents, n1, n2 = axis.at(s_rings, self._axis_function)
        # each ring's vertices spaced evenly along its own perimeter, starting at theta = 0
        radii = self._radius(s_rings[:, None], theta_fine[None, :])
        outline = radii[..., None] * (np.cos(theta_fine)[None, :, None] * n1[:, None, :]
                                      + np.sin(theta_fine)[None, :, None] * n2[:, None, :])
        perimeter = np.concatenate([np.zeros((n_rings, 1)),
                                    np.cumsum(np.linalg.norm(np.diff(outline, axis=1), axis=2), axis=1)], axis=1)
        counts = np.maximum(8, np.ceil(perimeter[:, -1] / side).astype(np.int64))
        rings = [np.interp(np.arange(n) * (p[-1] / n), p, theta_fine) for n, p in zip(counts, perimeter)]
        ring_of = np.repeat(np.arange(n_rings), counts)
        theta = np.concatenate(rings)
        r = self._radius(s_rings[ring_of], theta)
        vertices = centers[ring_of] + r[:, None] * (np.cos(theta)[:, None] * n1[ring_of]
                                                    + np.sin(theta)[:, None] * n2[ring_of])
        offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])
        return trimesh.Trimesh(vertices, _zipper(theta, ring_of, offsets), process=False)

    def _end_radius(self, s: float) -> float:
        """Radius of the circle with the end ring's area (the ring is a circle for every member)."""
        theta = np.linspace(0.0, 2.0 * np.pi, 721)[:-1]
        r = self._radius(np.full_like(theta, s), theta)
        return float(np.sqrt(np.mean(r * r)))

    def ends(self) -> list[EndSpec]:
        axis = self._axis
        first = EndSpec("distal", axis.points[0].copy(), -axis.tangents[0], self._end_radius(0.0))
        last = EndSpec("proximal", axis.points[-1].copy(), axis.tangents[-1].copy(), self._end_radius(axis.length))
        return [first, last]

    def _sac_arc_length(self) -> float:
        raise NotImplementedError

    def sac(self) -> SacSite:
        axis = self._axis
        s_c = self._sac_arc_length()
        (center,), (tangent,), (n1,), (n2,) = axis.at(np.array([s_c]), self._axis_function)
        theta = np.linspace(0.0, 2.0 * np.pi, 3601)[:-1]
        r = self._radius(np.full_like(theta, s_c), theta)
        if np.ptp(r) > 1e-9 * r.max():
            best = int(np.argmax(r))
            direction = np.cos(theta[best]) * n1 + np.sin(theta[best]) * n2
        else:
            # a circular cross-section: the catheter meets the outer side of the axis's bend
            bend = np.array([np.interp(s_c, axis.s, c) for c in np.gradient(axis.tangents, axis.s, axis=0).T])
            bend -= (bend @ tangent) * tangent
            direction = -bend / np.linalg.norm(bend) if np.linalg.norm(bend) > 1e-6 else n1
        outline = r[:, None] * (np.cos(theta)[:, None] * n1 + np.sin(theta)[:, None] * n2)
        reach = float(np.max(outline @ direction))
        return SacSite(center, tangent, direction, reach, float(self._sac_diameter(outline)))

    @staticmethod
    def _sac_diameter(outline: np.ndarray) -> float:
        """Largest chord of a cross-section's outline (its Feret diameter)."""
        hull = outline[::4]
        return float(np.sqrt(((hull[:, None] - hull[None, :]) ** 2).sum(axis=2)).max())


# ------------------------------------------------------------------------------ the members


@dataclass(frozen=True)
class _Straight(_Swept):
    """A tube swept up the z axis over the member's ``segment_length`` (declared in each member, last
    among its fields), the sac centred on it."""

    def _check_shape(self) -> None:
        super()._check_shape()
        if self.aneurysm_length > self.segment_length:
            self._fail(f"aneurysm_length ({self.aneurysm_length:g}) > segment_length ({self.segment_length:g})",
                       "lengthen the segment or shorten the sac")

    def _axis_function(self, u):
        u = np.asarray(u, dtype=np.float64)
        return np.stack([np.zeros_like(u), np.zeros_like(u), self.segment_length * u], axis=-1)

    def _sac_arc_length(self) -> float:
        return 0.5 * self.segment_length


@dataclass(frozen=True)
class FusiformParameters(_Straight):
    """A symmetric spindle about the z axis: tissue_fmu.mesh.aaa_mesh's lumen, z in [0, segment_length]."""

    KIND: ClassVar[str] = "fusiform"
    RANGES: ClassVar[dict[str, Range]] = {**_SEGMENT_RANGES}
    _SAC_OUTWARD_FIX: ClassVar[str] = "the sac bulges outward; give equal radii for a straight aorta"
    #: the length of the segment, m (distal end at z = 0)
    segment_length: float = 0.130

    def _radius(self, s, theta):
        # the very function of today's generator, so the two shapes are the same to round-off
        r = aaa_inner_radius(s, self.aorta_radius, self.aneurysm_radius, self.aneurysm_length, self.segment_length)
        return np.broadcast_to(r, np.broadcast_shapes(np.shape(s), np.shape(theta)))


@dataclass(frozen=True)
class SaccularParameters(_Straight):
    """A straight aorta along z with a sac bulging towards ``sac_azimuth_deg`` (from +x towards +y).

    The radius is r0 + depth * bump(z) * bump(theta): the cross-section through the sac's centre
    spans 2 * aneurysm_radius from the wall opposite to the sac's dome.
    """

    KIND: ClassVar[str] = "saccular"
    RANGES: ClassVar[dict[str, Range]] = {
        **_SEGMENT_RANGES,
        "aneurysm_length": Range(0.015, 0.120, "m", MODEL_LIMIT),
        "sac_width_deg": Range(60.0, 300.0, "deg", MODEL_LIMIT),
        "sac_azimuth_deg": Range(-360.0, 360.0, "deg", "any direction around the axis"),
    }
    #: half the largest transverse lumen diameter through the sac (opposite wall to dome), m
    aneurysm_radius: float = 0.020
    #: the sac's extent along the axis at its base, m
    aneurysm_length: float = 0.045
    #: the sac's extent around the circumference at its base, degrees
    sac_width_deg: float = 150.0
    #: the direction of the dome, degrees from +x towards +y (90: anterior, an arbitrary default)
    sac_azimuth_deg: float = 90.0
    segment_length: float = 0.130

    _SAC_HEIGHT: ClassVar[str] = "2 (aneurysm_radius - aorta_radius)"
    _FOLD_PARAMETERS: ClassVar[tuple[str, ...]] = _Member._FOLD_PARAMETERS + ("sac_width_deg",)
    _FOLD_FIX: ClassVar[str] = "lengthen or widen the sac (aneurysm_length, sac_width_deg) or reduce its radius"

    def _check_sac_outward(self) -> None:
        # unlike the others, equal radii are refused too: they would make no sac at all
        if self.aneurysm_radius <= self.aorta_radius:
            self._fail(f"aneurysm_radius ({self.aneurysm_radius:g}) <= aorta_radius ({self.aorta_radius:g})",
                       "a sac spans more than the aorta's diameter; enlarge it")

    def _sac_height(self) -> float:
        return 2.0 * (self.aneurysm_radius - self.aorta_radius)

    def _check_shape(self) -> None:
        super()._check_shape()
        self._check_rim_fold()

    def _check_rim_fold(self) -> None:
        """The cross-section through the sac's centre is the polar curve r = r0 + D cos^2(pi phi / W) (phi from
        the azimuth, W the width): its curvature (r^2 + 2 r'^2 - r r'') / (r^2 + r'^2)^(3/2), with r' = 0 and
        r'' = -+2 pi^2 D / W^2 at the dome's top and at its rim, is (r0 + D + c) / (r0 + D)^2 at the top (convex)
        and (r0 - c) / r0^2 at the rim (concave when c = 2 pi^2 D / W^2 > r0). Away from that section the bump
        along the axis scales D down, so these are the extremes."""
        r0, depth, width = self.aorta_radius, self._sac_height(), math.radians(self.sac_width_deg)
        c = 2.0 * math.pi ** 2 * depth / width ** 2
        # the widest sac and the narrowest width at which the rim's concave radius is MIN_FOLD_RADIUS
        allowed = r0 + r0 * r0 / MIN_FOLD_RADIUS
        narrowest = math.degrees(math.sqrt(2.0 * math.pi ** 2 * depth / allowed))
        widest = r0 + 0.5 * allowed * width ** 2 / (2.0 * math.pi ** 2)
        shown = (f"(sac_width_deg {self.sac_width_deg:g} deg, depth {self._SAC_HEIGHT} = {depth * 1e3:.3g} mm, "
                 f"aorta_radius {r0:g} m)")
        if c > r0 and r0 * r0 / (c - r0) < MIN_FOLD_RADIUS:
            self._fail(f"the sac's rim {shown} turns into the aorta with a concave radius of "
                       f"{r0 * r0 / (c - r0) * 1e3:.3g} mm (aorta_radius^2 / (2 pi^2 depth / width^2 - aorta_radius)), "
                       f"tighter than a wall can follow (MIN_FOLD_RADIUS {MIN_FOLD_RADIUS * 1e3:g} mm)",
                       f"widen the sac (sac_width_deg at least {narrowest:.4g}) or reduce its radius (aneurysm_radius "
                       f"at most {widest * 1e3:.3g} mm)")
        top = (r0 + depth) ** 2 / (r0 + depth + c)
        if top < MIN_FOLD_RADIUS:
            self._fail(f"the sac's dome {shown} curves around its top with a convex radius of {top * 1e3:.3g} mm "
                       "((aorta_radius + depth)^2 / (aorta_radius + depth + 2 pi^2 depth / width^2)), tighter than a "
                       f"wall can follow (MIN_FOLD_RADIUS {MIN_FOLD_RADIUS * 1e3:g} mm)",
                       "widen the sac (sac_width_deg)")

    def _radius(self, s, theta):
        depth = 2.0 * (self.aneurysm_radius - self.aorta_radius)
        along = _bump(s, 0.5 * self.segment_length, self.aneurysm_length)
        around = _angle_bump(theta, math.radians(self.sac_azimuth_deg), math.radians(self.sac_width_deg))
        return self.aorta_radius + depth * along * around


@dataclass(frozen=True)
class EccentricParameters(_Straight):
    """A fusiform sac along z whose circular cross-sections are offset from the aortic axis.

    The section at height z is a circle of radius R(z) (the fusiform profile) centred
    e(z) = eccentricity * (aneurysm_radius - aorta_radius) * bump(z) towards ``offset_azimuth_deg``:
    0 is the fusiform sac, 1 keeps the wall opposite the offset straight.
    """

    KIND: ClassVar[str] = "eccentric"
    RANGES: ClassVar[dict[str, Range]] = {
        **_SEGMENT_RANGES,
        "eccentricity": Range(0.0, 1.0, "", MODEL_LIMIT + " (0: centred, 1: the opposite wall straight)"),
        "offset_azimuth_deg": Range(-360.0, 360.0, "deg", "any direction around the axis"),
    }
    eccentricity: float = 0.6
    #: the direction of the offset, degrees from +x towards +y (90: anterior, an arbitrary default)
    offset_azimuth_deg: float = 90.0
    segment_length: float = 0.130

    _SAC_HEIGHT: ClassVar[str] = "(1 + eccentricity) (aneurysm_radius - aorta_radius)"
    _FOLD_PARAMETERS: ClassVar[tuple[str, ...]] = _Member._FOLD_PARAMETERS + ("eccentricity",)
    _FOLD_FIX: ClassVar[str] = "lengthen the sac, or reduce its radius or its eccentricity"

    def _sac_height(self) -> float:
        # the wall on the offset's side: e(z) + R(z) = aorta_radius + (1 + eccentricity) (R - r0) bump(z) (a negative
        # eccentricity, refused below, would offset it to the other side)
        return (1.0 + abs(self.eccentricity)) * (self.aneurysm_radius - self.aorta_radius)

    def _check_shape(self) -> None:
        super()._check_shape()
        offset = self.eccentricity * (self.aneurysm_radius - self.aorta_radius)
        if offset < 0 or self.aneurysm_radius - offset < 0.5 * self.aorta_radius:
            self._fail(f"the sac's centre (offset {offset:g} m) leaves the aortic axis less than half the aortic "
                       "radius inside the lumen", "lower the eccentricity (at most 1)")

    def _radius(self, s, theta):
        b = _bump(s, 0.5 * self.segment_length, self.aneurysm_length)
        big = self.aorta_radius + (self.aneurysm_radius - self.aorta_radius) * b
        e = self.eccentricity * (self.aneurysm_radius - self.aorta_radius) * b
        psi = np.asarray(theta) - math.radians(self.offset_azimuth_deg)
        # the polar radius about the axis of a circle (radius big) whose centre sits e away from it
        return e * np.cos(psi) + np.sqrt(big * big - (e * np.sin(psi)) ** 2)


@dataclass(frozen=True)
class AngulatedNeckParameters(_Swept):
    """The sac's axis along z; above the sac the proximal neck bends by ``neck_angle_deg`` (an arc of
    ``bend_radius``, then straight up to the renal level). The neck length is measured along the
    axis from the proximal end to the sac, bend included, as on a CT centerline."""

    KIND: ClassVar[str] = "angulated_neck"
    _FOLD_PARAMETERS: ClassVar[tuple[str, ...]] = _Member._FOLD_PARAMETERS + ("bend_radius", "neck_angle_deg")
    _FOLD_FIX: ClassVar[str] = "lengthen the sac or reduce its radius, or widen the neck's bend (bend_radius)"
    RANGES: ClassVar[dict[str, Range]] = {
        **_ANEURYSM_RANGES,
        "neck_length": Range(0.010, 0.080, "m", f"lower bound: the shortest neck on label, {ENDURANT_IFU} "
                             f"({EXCLUDER_IFU}); upper bound: " + MODEL_LIMIT),
        "neck_angle_deg": Range(0.0, 60.0, "deg", f"the on-label limit of most EVAR devices: {ENDURANT_IFU}; "
                                f"{EXCLUDER_IFU}; steeper necks are 'hostile'"),
        "bend_radius": Range(0.008, 0.100, "m", MODEL_LIMIT),
        "bend_azimuth_deg": Range(-360.0, 360.0, "deg", "any direction around the axis"),
        "distal_length": Range(0.005, 0.100, "m", MODEL_LIMIT),
    }
    #: along the axis from the proximal end (renal level) to the sac, bend included, m
    neck_length: float = 0.035
    #: angle between the neck's axis and the sac's axis, degrees
    neck_angle_deg: float = 45.0
    #: radius of the neck's bend (on its axis), m
    bend_radius: float = 0.025
    #: the direction the neck leans to, degrees from +x towards +y (90: anterior, an arbitrary default)
    bend_azimuth_deg: float = 90.0
    #: from the distal end (z = 0) to the sac, m
    distal_length: float = 0.035

    def _check_shape(self) -> None:
        super()._check_shape()
        arc = self.bend_radius * math.radians(self.neck_angle_deg)
        if arc > self.neck_length:
            self._fail(f"the bend ({arc * 1e3:.3g} mm along the axis) does not fit in the neck "
                       f"({self.neck_length * 1e3:.3g} mm)", "lengthen the neck, reduce the angle or the bend radius")
        # the bent neck is a piece of torus (the sac ends where the bend starts): along the axis, its inner wall is
        # an arc of radius bend_radius - aorta_radius around the bend's centre, concave seen from outside
        inner = self.bend_radius - self.aorta_radius
        if self.neck_angle_deg > 0.0 and inner < MIN_FOLD_RADIUS:
            self._fail(f"the inner wall of the neck's bend (bend_radius {self.bend_radius:g} m, aorta_radius "
                       f"{self.aorta_radius:g} m) curves with a concave radius of {inner * 1e3:.3g} mm (bend_radius - "
                       f"aorta_radius), tighter than a wall can follow (MIN_FOLD_RADIUS {MIN_FOLD_RADIUS * 1e3:g} mm)",
                       f"widen the bend (bend_radius at least {(self.aorta_radius + MIN_FOLD_RADIUS) * 1e3:.3g} mm)")

    def _axis_function(self, u):
        s = np.asarray(u, dtype=np.float64) * self._total_length
        start = self.distal_length + self.aneurysm_length           # where the bend starts
        gamma = math.radians(self.neck_angle_deg)
        rho = self.bend_radius
        lean = np.array([math.cos(math.radians(self.bend_azimuth_deg)), math.sin(math.radians(self.bend_azimuth_deg)),
                         0.0])
        up = np.array([0.0, 0.0, 1.0])
        psi = np.clip((s - start) / rho, 0.0, gamma)                  # angle turned so far
        beyond = np.maximum(s - start - rho * gamma, 0.0)           # straight neck past the bend
        along = np.minimum(s, start)
        # straight sac axis, then the arc, then the straight neck in the turned direction
        return (along[:, None] * up + rho * (1.0 - np.cos(psi))[:, None] * lean + rho * np.sin(psi)[:, None] * up
                + beyond[:, None] * (math.sin(gamma) * lean + math.cos(gamma) * up))

    @property
    def _total_length(self) -> float:
        return self.distal_length + self.aneurysm_length + self.neck_length

    def _sac_arc_length(self) -> float:
        return self.distal_length + 0.5 * self.aneurysm_length


@dataclass(frozen=True)
class TortuousParameters(_Swept):
    """An aorta whose axis winds about z: c(u) = (A E cos(2 pi n u), A E sin(2 pi n u), L u) with the
    envelope E = sin^2(pi u), so both ends are on the z axis and vertical; the sac sits halfway along
    the axis (by arc length)."""

    KIND: ClassVar[str] = "tortuous"
    _FOLD_PARAMETERS: ClassVar[tuple[str, ...]] = _Member._FOLD_PARAMETERS + ("winding_radius", "turns",
                                                                              "segment_length")
    _FOLD_FIX: ClassVar[str] = ("lengthen the sac or reduce its radius, or wind the axis less (a smaller "
                                "winding_radius, fewer turns or a longer segment_length)")
    RANGES: ClassVar[dict[str, Range]] = {
        **_SEGMENT_RANGES,
        "winding_radius": Range(0.0, 0.030, "m", MODEL_LIMIT),
        "turns": Range(0.25, 3.0, "", MODEL_LIMIT),
    }
    #: the largest distance of the axis from the z axis, m
    winding_radius: float = 0.015
    #: turns of the axis about z over the segment
    turns: float = 0.5
    #: the height between the two ends, m
    segment_length: float = 0.130

    def _check_shape(self) -> None:
        super()._check_shape()
        if self.aneurysm_length > 0.9 * self._axis.length:
            self._fail(f"aneurysm_length ({self.aneurysm_length:g}) leaves no neck on the {self._axis.length:g} m axis",
                       "lengthen the segment or shorten the sac")

    def _axis_function(self, u):
        u = np.asarray(u, dtype=np.float64)
        radius = self.winding_radius * np.sin(np.pi * u) ** 2
        angle = 2.0 * np.pi * self.turns * u
        return np.stack([radius * np.cos(angle), radius * np.sin(angle), self.segment_length * u], axis=-1)

    @property
    def tortuosity_index(self) -> float:
        """Axis length over the distance between its ends."""
        return self._axis.length / self.segment_length

    def _sac_arc_length(self) -> float:
        return 0.5 * self._axis.length


# ------------------------------------------------------------------------------ the bifurcation: an implicit surface

# Kuhn's split of a cube into six tetrahedra along its main diagonal: every tet is a chain of
# corners 000 <= e_a <= e_a + e_b <= 111 (bits x = 1, y = 2, z = 4). All cubes use the same split,
# so neighbours cut their shared faces alike and the extracted surface is closed.
_KUHN_TETS = np.array([[0, a, a | b, 7] for a, b in ((1, 2), (1, 4), (2, 1), (2, 4), (4, 1), (4, 2))])
_CORNER_OFFSETS = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)])


def _marching_tetrahedra(field, origin: np.ndarray, spacing: float, shape: tuple[int, int, int]) -> trimesh.Trimesh:
    """The surface field = 0 (negative inside) on a regular grid, its normals pointing to field > 0.

    Marching tetrahedra has no ambiguous case: the zero set of the field's linear interpolant over
    the Kuhn tets is a closed 2-manifold, one vertex per crossed grid edge, without holes.
    """
    nx, ny, nz = shape
    axes = [origin[i] + spacing * np.arange(n) for i, n in enumerate(shape)]
    values = np.empty(shape)
    slab = max(1, 2_000_000 // (ny * nz))                  # evaluate in slabs to bound the memory
    for i in range(0, nx, slab):
        grid = np.stack(np.meshgrid(axes[0][i:i + slab], axes[1], axes[2], indexing="ij"), axis=-1)
        values[i:i + slab] = field(grid.reshape(-1, 3)).reshape(grid.shape[:3])
    # an exact zero would put a vertex on a grid node (a zero-area triangle): nudge it outside
    values[values == 0.0] = 1e-300
    inside = values < 0.0
    corners = [inside[dx:nx - 1 + dx, dy:ny - 1 + dy, dz:nz - 1 + dz] for dx, dy, dz in _CORNER_OFFSETS]
    mixed = np.logical_or.reduce(corners) & ~np.logical_and.reduce(corners)
    cube = np.argwhere(mixed)                                          # (m, 3) lower corners
    node = cube[:, None, None, :] + _CORNER_OFFSETS[_KUHN_TETS][None]  # (m, 6, 4, 3)
    node = node.reshape(-1, 4, 3)
    linear = (node[..., 0] * ny + node[..., 1]) * nz + node[..., 2]
    tet_inside = inside.reshape(-1)[linear]
    count = tet_inside.sum(axis=1)
    keep = (count > 0) & (count < 4)
    node, linear, tet_inside, count = node[keep], linear[keep], tet_inside[keep], count[keep]
    flat_values = values.reshape(-1)
    positions = origin + spacing * node                               # (t, 4, 3)
    # the triangle's normal must point from the inside corners to the outside ones
    outward = ((positions * ~tet_inside[..., None]).sum(1) / (4 - count)[:, None]
               - (positions * tet_inside[..., None]).sum(1) / count[:, None])

    def crossing(tets, a, b):
        """Vertex keys and positions where the edges (a, b) of the given tets cross zero."""
        la, lb = linear[tets, a], linear[tets, b]
        lower = np.minimum(la, lb)   # Kuhn edges join a node to one above it in every coordinate
        step = node[tets, np.where(la < lb, b, a)] - node[tets, np.where(la < lb, a, b)]
        key = lower * 7 + (step @ np.array([1, 2, 4])) - 1
        fa, fb = flat_values[la], flat_values[lb]
        t = fa / (fa - fb)
        pa, pb = positions[tets, a], positions[tets, b]
        return key, pa + t[:, None] * (pb - pa)

    keys, points, faces = [], [], []
    # one corner apart from the other three: one triangle around it
    lone_rows = np.flatnonzero((count == 1) | (count == 3))
    odd = np.where(count[lone_rows, None] == 1, tet_inside[lone_rows], ~tet_inside[lone_rows])
    order = np.argsort(~odd, axis=1, kind="stable")                   # the lone corner first
    triangle = [crossing(lone_rows, order[:, 0], order[:, k]) for k in (1, 2, 3)]
    faces.append((np.stack([k for k, _ in triangle], 1), np.stack([p for _, p in triangle], 1), outward[lone_rows]))
    # two inside, two outside: a planar quad, split along its shorter diagonal
    quad_rows = np.flatnonzero(count == 2)
    order = np.argsort(~tet_inside[quad_rows], axis=1, kind="stable")  # inside a, b then outside c, d
    a, b, c, d = order.T
    quad = [crossing(quad_rows, x, y) for x, y in ((a, c), (a, d), (b, d), (b, c))]
    qk = np.stack([k for k, _ in quad], 1)
    qp = np.stack([p for _, p in quad], 1)
    first = (np.linalg.norm(qp[:, 0] - qp[:, 2], axis=1) <= np.linalg.norm(qp[:, 1] - qp[:, 3], axis=1))[:, None]
    for left, right in (((0, 1, 2), (0, 1, 3)), ((0, 2, 3), (1, 2, 3))):
        pick = np.where(first, np.array(left), np.array(right))
        faces.append((np.take_along_axis(qk, pick, 1), np.take_along_axis(qp, pick[..., None], 1),
                      outward[quad_rows]))
    for k, p, _ in faces:
        keys.append(k.reshape(-1))
        points.append(p.reshape(-1, 3))
    _, first_index, inverse = np.unique(np.concatenate(keys), return_index=True, return_inverse=True)
    vertices = np.concatenate(points)[first_index]
    triangles = inverse.reshape(-1, 3)
    corners_of = np.concatenate([p for _, p, _ in faces])
    normals = np.cross(corners_of[:, 1] - corners_of[:, 0], corners_of[:, 2] - corners_of[:, 0])
    flip = np.einsum("ij,ij->i", normals, np.concatenate([o for _, _, o in faces])) < 0
    triangles[flip] = triangles[flip][:, ::-1]
    return trimesh.Trimesh(vertices, triangles, process=False)


def _gradient(field, points: np.ndarray, step: float) -> np.ndarray:
    """Central-difference gradient of a scalar field at points (n, 3)."""
    offsets = np.eye(3) * step
    return np.stack([(field(points + o) - field(points - o)) / (2.0 * step) for o in offsets], axis=1)


def _project(field, points: np.ndarray, step: float, iterations: int = 3) -> np.ndarray:
    """Newton steps along the gradient onto field = 0."""
    for _ in range(iterations):
        g = _gradient(field, points, step)
        points = points - (field(points) / np.maximum(np.einsum("ij,ij->i", g, g), 1e-30))[:, None] * g
    return points


def _relax(mesh: trimesh.Trimesh, field, step: float, iterations: int,
           ends: tuple[EndSpec, ...] = ()) -> trimesh.Trimesh:
    """Even out marching tetrahedra's uneven triangles: move each vertex towards its neighbours'
    mean within the tangent plane, then back onto the surface (the shape stays the field's).

    A vertex of an open end's loop moves along the loop only (towards its two loop neighbours) and
    is put back onto the end's plane and the surface: the ends stay planar circles.
    """
    n = len(mesh.vertices)
    edges = mesh.edges_unique
    loop_edges = boundary_edges(mesh)
    on_loop = np.zeros(n, dtype=bool)
    on_loop[loop_edges.reshape(-1)] = True

    def adjacency(pairs):
        return sparse.coo_matrix((np.ones(2 * len(pairs)), (pairs.reshape(-1), pairs[:, ::-1].reshape(-1))),
                                 shape=(n, n)).tocsr()

    neighbours = sparse.diags((~on_loop).astype(np.float64)) @ adjacency(edges)
    if on_loop.any():
        neighbours = neighbours + sparse.diags(on_loop.astype(np.float64)) @ adjacency(loop_edges)
    degree = np.maximum(np.asarray(neighbours.sum(axis=1)).reshape(-1, 1), 1.0)
    points = np.asarray(mesh.vertices, dtype=np.float64)
    loop_ids = np.flatnonzero(on_loop)
    if ends:
        distance = np.stack([np.abs((points[loop_ids] - e.center) @ e.normal) for e in ends], axis=1)
        plane_of = np.argmin(distance, axis=1)
        centers = np.stack([e.center for e in ends])[plane_of]
        normals = np.stack([e.normal for e in ends])[plane_of]

    def onto_planes(p):
        if ends:
            p[loop_ids] -= np.einsum("ij,ij->i", p[loop_ids] - centers, normals)[:, None] * normals
        return p

    points = onto_planes(_project(field, points, step))
    for _ in range(iterations):
        gradient = _gradient(field, points, step)
        normal = _unit(gradient)
        move = neighbours @ points / degree - points
        move -= np.einsum("ij,ij->i", move, normal)[:, None] * normal
        points = points + 0.5 * move
        # back onto the surface by Newton steps along this iteration's gradient (the moves are small,
        # the field's gradient hardly turns over them: a fresh one would cost six field evaluations)
        squared = np.maximum(np.einsum("ij,ij->i", gradient, gradient), 1e-30)
        for _ in range(2):
            points = points - (field(points) / squared)[:, None] * gradient
        points = onto_planes(points)
    return trimesh.Trimesh(onto_planes(_project(field, points, step, iterations=2)), mesh.faces, process=False)


def _level_set_curvatures(field, points: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """(concave, convex) seen from outside: the largest principal curvature of each kind (1/m, 0 or less when
    there is none) of the surface field = 0 (negative inside) at points on it, from the field's gradient g and
    Hessian H by central differences: the eigenvalues of the shape operator P H P / |g| in the tangent plane."""
    offsets = np.eye(3) * step
    centre = field(points)
    plus = [field(points + o) for o in offsets]
    minus = [field(points - o) for o in offsets]
    gradient = np.stack([(a - b) / (2.0 * step) for a, b in zip(plus, minus)], axis=1)
    hessian = np.empty((len(points), 3, 3))
    for i in range(3):
        hessian[:, i, i] = (plus[i] - 2.0 * centre + minus[i]) / step ** 2
        for j in range(i + 1, 3):
            hessian[:, i, j] = hessian[:, j, i] = (
                field(points + offsets[i] + offsets[j]) - field(points + offsets[i] - offsets[j])
                - field(points - offsets[i] + offsets[j]) + field(points - offsets[i] - offsets[j])) / (4.0 * step ** 2)
    length = np.linalg.norm(gradient, axis=1)
    normal = gradient / length[:, None]
    first = _unit(np.cross(normal, np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])))
    tangent = np.stack([first, np.cross(normal, first)], axis=2)
    # with the gradient outward a sphere's are +1 / radius: convex positive
    k = np.linalg.eigvalsh(np.einsum("nia,nij,njb->nab", tangent, hessian, tangent) / length[:, None, None])
    return -k[:, 0], k[:, 1]


def _clip(mesh: trimesh.Trimesh, origin: np.ndarray, normal: np.ndarray) -> trimesh.Trimesh:
    """The part of a surface where (p - origin) . normal < 0, cut along the plane: a triangle across
    it keeps its part (a triangle or a quad split in two) in its winding; the crossing points are
    shared by the triangles on both sides of an edge, so the cut is one boundary loop."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    height = (vertices - origin) @ normal
    kept = height[faces] < 0.0
    n_kept = kept.sum(axis=1)
    whole = faces[n_kept == 3]
    mixed = faces[(n_kept == 1) | (n_kept == 2)]
    mixed_kept = kept[(n_kept == 1) | (n_kept == 2)]
    # rotate each crossing triangle (keeping its winding) so that its odd vertex comes first
    lone = np.where(mixed_kept.sum(axis=1) == 1, np.argmax(mixed_kept, axis=1), np.argmin(mixed_kept, axis=1))
    rolled = np.take_along_axis(mixed, (lone[:, None] + np.arange(3)) % 3, axis=1)
    first, second, third = rolled.T
    edges = np.concatenate([np.stack([first, second], 1), np.stack([first, third], 1)])
    keys, inverse = np.unique(np.sort(edges, axis=1), axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    ha, hb = height[keys[:, 0]], height[keys[:, 1]]
    t = ha / (ha - hb)
    points = vertices[keys[:, 0]] + t[:, None] * (vertices[keys[:, 1]] - vertices[keys[:, 0]])
    n = len(vertices)
    cross_12 = n + inverse[:len(first)]          # on edge (first, second)
    cross_13 = n + inverse[len(first):]          # on edge (first, third)
    one = mixed_kept.sum(axis=1) == 1
    pieces = [whole,
              np.stack([first, cross_12, cross_13], 1)[one],                 # the kept corner's triangle
              np.stack([cross_12, second, third], 1)[~one],                   # the kept quad, in two
              np.stack([cross_12, third, cross_13], 1)[~one]]
    clipped = trimesh.Trimesh(np.concatenate([vertices, points]), np.concatenate(pieces), process=False)
    clipped.remove_unreferenced_vertices()
    return clipped


def _cut_end(mesh: trimesh.Trimesh, end: EndSpec, clearance: float) -> trimesh.Trimesh:
    """Cut the tube open at an end's plane, keeping the vessel's side.

    Vertices closer to the plane than ``clearance`` are first pushed away from it along the tube's
    axis (monotonically, so no triangle flips; the tube is a straight cylinder there, so they stay
    on it): the cut then makes no sliver triangles.
    """
    vertices = np.asarray(mesh.vertices, dtype=np.float64).copy()
    offset = vertices - end.center
    height = offset @ end.normal
    lateral = np.linalg.norm(offset - height[:, None] * end.normal, axis=1)
    near = (np.abs(height) < 2.0 * clearance) & (lateral < 1.5 * end.radius)
    pushed = np.where(height[near] < 0.0, -1.0, 1.0) * (clearance + 0.5 * np.abs(height[near]))
    vertices[near] += (pushed - height[near])[:, None] * end.normal
    return _clip(trimesh.Trimesh(vertices, mesh.faces, process=False), end.center, end.normal)


@dataclass(frozen=True)
class BifurcationParameters(_Member):
    """The aorta with a fusiform sac splitting into the two common iliac arteries below it.

    The aorta runs up the z axis from the bifurcation (at z = iliac_length * cos(angle / 2)) over
    ``aortic_length``, the sac at its middle; the iliacs run down and out in the x-z plane to their
    ends at z = 0 (the right one at +x). Near the bifurcation the aorta's section becomes an ellipse
    spanning both iliacs (wide in x, flat in y), as the distal aorta flattens into its two branches;
    a smooth union of the three tubes' distance fields joins them with fillets, the carina included.
    """

    KIND: ClassVar[str] = "bifurcation"
    N_ENDS: ClassVar[int] = 3
    RANGES: ClassVar[dict[str, Range]] = {
        **_ANEURYSM_RANGES,
        "aortic_length": Range(0.080, 0.250, "m", MODEL_LIMIT),
        "iliac_radius": Range(0.004, 0.0125, "m", f"the iliac diameters on label, {ENDURANT_IFU}", diameter=True),
        "iliac_length": Range(0.020, 0.100, "m", MODEL_LIMIT),
        "bifurcation_angle_deg": Range(20.0, 100.0, "deg", MODEL_LIMIT),
    }
    #: from the bifurcation up to the proximal end (renal level), m; the sac is centred on it
    aortic_length: float = 0.130
    #: lumen radius of both common iliac arteries, m
    iliac_radius: float = 0.005
    #: from the bifurcation to each iliac end along its axis, m
    iliac_length: float = 0.050
    #: the angle between the two iliac axes, degrees
    bifurcation_angle_deg: float = 50.0

    def _check_shape(self) -> None:
        super()._check_shape()
        if self.iliac_radius > self.aorta_radius:
            self._fail(f"iliac_radius ({self.iliac_radius:g}) > aorta_radius ({self.aorta_radius:g})",
                       "the iliac arteries are narrower than the aorta they branch from")
        distal_neck = 0.5 * (self.aortic_length - self.aneurysm_length)
        if distal_neck < self._taper:
            self._fail(f"the aorta below the sac ({distal_neck * 1e3:.3g} mm) is shorter than the taper into the "
                       f"bifurcation ({self._taper * 1e3:.3g} mm)", "lengthen aortic_length or shorten the sac")
        gap = 2.0 * self.iliac_length * math.sin(self._half_angle) - 2.0 * self.iliac_radius / math.cos(
            self._half_angle)
        if gap < 2.0 * self.iliac_radius:
            self._fail("the iliac ends would overlap", "widen the bifurcation angle or lengthen the iliacs")
        # at the bifurcation the aorta's section is the ellipse spanning the iliacs, iliac_radius from front to back:
        # a slot 2 iliac_radius deep, each iliac as wide (and curving around with that radius)
        if self.iliac_radius < MIN_FOLD_RADIUS:
            self._fail(f"the distal aorta flattens to a lumen 2 iliac_radius = {2e3 * self.iliac_radius:.3g} mm deep, "
                       f"narrower than a wall can follow (2 MIN_FOLD_RADIUS = {2e3 * MIN_FOLD_RADIUS:g} mm)",
                       f"widen the iliacs (iliac_radius at least {MIN_FOLD_RADIUS * 1e3:g} mm)")
        self._check_junction_folds()

    def _check_junction_folds(self) -> None:
        """No principal curvature of the junction beyond 1 / MIN_FOLD_RADIUS, measured: the crotch between the
        iliacs, the flattened distal aorta and its rounded bottom are fillets of a smooth union (no closed form), so
        the curvatures are the field's own, from its Hessian (finite differences) at points on its zero set.

        The points: the grid nodes within a step of the surface, 2 mm apart, then 0.67 mm apart within those
        (the field is symmetric in x and y: one quadrant), projected onto it, up to where the aorta is a surface
        of revolution (above it, the sac's profile is _check_sac_fold's, exactly) and short of the iliacs' ends
        (cut away there); the worst of them is then refined by a pattern search along the surface. Against all
        the nodes 0.3 mm apart (ten times the cost) the radii agree within 0.5 %."""
        extension = self.iliac_radius

        def field(p):
            return self._field(p, extension)

        beta = self._half_angle
        z_b = self.bifurcation_height
        # above: the taper, the rounded bottom's and the iliacs' fillets are behind (the iliac tubes start
        # 1.5 iliac radii inside the aorta, their fillets reach a blend further)
        top = z_b + self._taper + 2.0 * self._blend
        coarse, split = 0.002, 3
        fine = coarse / split
        half_x = self.iliac_radius / math.cos(beta) + self.iliac_length * math.sin(beta) + 2.0 * self.iliac_radius
        half_y = max(self.aneurysm_radius, 2.0 * self.iliac_radius)
        axes = [np.arange(0.0, half_x + coarse, coarse), np.arange(0.0, half_y + coarse, coarse),
                np.arange(-2.0 * self.iliac_radius, top + coarse, coarse)]
        nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        near = nodes[np.abs(field(nodes)) < coarse]
        offsets = (np.stack(np.meshgrid(*[np.arange(split) - 0.5 * (split - 1)] * 3, indexing="ij"), axis=-1)
                   .reshape(-1, 3) * fine)
        nodes = (near[:, None, :] + offsets[None, :, :]).reshape(-1, 3)
        step = 5e-5
        ends = self.ends()

        def kept(points):
            for end in ends:
                points = points[(points - end.center) @ end.normal < 0.0]
            return points

        points = kept(_project(field, nodes[np.abs(field(nodes)) < 0.6 * fine], step))
        for side in (0, 1):
            curvature = _level_set_curvatures(field, points, step)[side]
            best = int(np.argmax(curvature))
            worst, at = float(curvature[best]), points[best]
            # a pattern search: the largest curvature among points around the worst on the surface, closer and
            # closer (the samples are fine's apart: the peak may lie between them)
            reach = fine
            circle = np.linspace(0.0, 2.0 * np.pi, 8, endpoint=False)
            ring = np.stack([np.cos(circle), np.sin(circle), np.zeros_like(circle)], axis=1)
            pattern = np.concatenate([ring, ring[:, [0, 2, 1]], ring[:, [2, 0, 1]]])
            for _ in range(8):
                around = kept(_project(field, at + reach * pattern, step))
                values = _level_set_curvatures(field, around, step)[side] if len(around) else np.zeros(1)
                if values.max() > worst:
                    worst, at = float(values.max()), around[int(np.argmax(values))]
                else:
                    reach *= 0.5
            if worst * MIN_FOLD_RADIUS > 1.0:
                self._fail(f"the junction curves with a {('concave', 'convex')[side]} radius of {1e3 / worst:.3g} mm "
                           f"at {(np.round(1e3 * at, 1) + 0.0).tolist()} mm "
                           f"({self._shown(('aorta_radius', 'iliac_radius', 'bifurcation_angle_deg'))}; measured on "
                           "the implicit surface: no closed form there), tighter than a wall can follow "
                           f"(MIN_FOLD_RADIUS {MIN_FOLD_RADIUS * 1e3:g} mm)",
                           "widen the bifurcation angle (bifurcation_angle_deg) or the iliacs (iliac_radius): the "
                           "crotch's fillet scales with both")

    # -- geometry

    @property
    def _half_angle(self) -> float:
        return 0.5 * math.radians(self.bifurcation_angle_deg)

    @property
    def _taper(self) -> float:
        """Length over which the aorta's section turns into the ellipse spanning the iliacs."""
        return 2.0 * self.aorta_radius

    @property
    def _blend(self) -> float:
        """Radius of the fillets of the smooth union: 1.5 iliac radii rounds the carina enough for a
        2-3 mm mesh (a tighter one folds the triangles there by up to 80 degrees)."""
        return 1.5 * self.iliac_radius

    @property
    def bifurcation_height(self) -> float:
        return self.iliac_length * math.cos(self._half_angle)

    def _iliac_axis(self, side: float) -> tuple[np.ndarray, np.ndarray]:
        """(start at the bifurcation level, unit direction) of the iliac on side +1 (right) or -1."""
        beta = self._half_angle
        # the iliacs start side by side, touching at the axis, their outer walls flush with the aorta's
        start = np.array([side * self.iliac_radius / math.cos(beta), 0.0, self.bifurcation_height])
        return start, np.array([side * math.sin(beta), 0.0, -math.cos(beta)])

    def _top(self) -> float:
        return self.bifurcation_height + self.aortic_length

    def _aorta_field(self, p: np.ndarray, extension: float) -> np.ndarray:
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        z_b = self.bifurcation_height
        r = self._sac_profile(z, z_b + 0.5 * self.aortic_length)
        # the section's semi-axes: from the circle above the taper to the ellipse spanning the iliacs
        beta = self._half_angle
        fade = 1.0 - _smoothstep((z - z_b) / self._taper)
        a = r + (2.0 * self.iliac_radius / math.cos(beta) - self.aorta_radius) * fade
        b = r + (self.iliac_radius - self.aorta_radius) * fade
        q = np.hypot(x / a, y / b)
        slope = np.hypot(x / (a * a), y / (b * b)) / np.maximum(q, 1e-12)
        # (q - 1) / |grad q| approximates the distance to the elliptic section (exact on a circle)
        tube = np.where(q > 1e-12, (q - 1.0) / np.maximum(slope, 1e-12), -np.minimum(a, b))
        closed = -_smin(-tube, z - z_b, self._blend)                  # rounded bottom at the bifurcation
        return np.maximum(closed, z - (self._top() + extension))          # cut away above the end anyway

    def _field(self, p: np.ndarray, extension: float) -> np.ndarray:
        tubes = []
        for side in (1.0, -1.0):
            start, direction = self._iliac_axis(side)
            # from inside the aorta (so no cap shows) to beyond the end (cut off later)
            a = start - 1.5 * self.iliac_radius * direction
            b = start + (self.iliac_length + extension) * direction
            tubes.append(_segment_distance(p, a, b) - self.iliac_radius)
        return _smin(self._aorta_field(p, extension), _smin(tubes[0], tubes[1], self._blend), self._blend)

    def _build(self, edge_length: float) -> trimesh.Trimesh:
        # marching tetrahedra's relaxed triangles have edges of about 0.52 grid steps (measured); the
        # grid keeps at least two steps across an iliac's diameter whatever the edge length asks (the
        # iliacs' topology and the carina need them)
        spacing = min(edge_length / 0.52, self.iliac_radius)
        extension = max(3.0 * spacing, self.iliac_radius)
        beta = self._half_angle
        reach_x = (self.iliac_radius / math.cos(beta) + (self.iliac_length + extension) * math.sin(beta)
                   + self.iliac_radius)
        half_x = max(reach_x, 2.0 * self.iliac_radius / math.cos(beta), self.aneurysm_radius) + 2.0 * spacing
        half_y = self.aneurysm_radius + 2.0 * spacing
        low = -(extension * math.cos(beta) + self.iliac_radius) - 2.0 * spacing
        high = self._top() + extension + 2.0 * spacing
        origin = np.array([-half_x, -half_y, low])
        shape = tuple(int(math.ceil(extent / spacing)) + 1 for extent in (2 * half_x, 2 * half_y, high - low))
        if math.prod(shape) > MAX_GRID_NODES:
            raise AnatomyError(f"{self.KIND}: edge_length {edge_length:g} m needs a grid of {math.prod(shape)} nodes "
                               f"(at most {MAX_GRID_NODES}): use a larger edge length or fewer triangles")

        def field(p):
            return self._field(p, extension)

        mesh = _marching_tetrahedra(field, origin, spacing, shape)
        mesh = _relax(mesh, field, 1e-3 * spacing, iterations=10)
        ends = tuple(self.ends())
        for end in ends:
            mesh = _cut_end(mesh, end, clearance=0.15 * spacing)
        # the cut leaves uneven triangles along the loops: relax them, the loops kept on their planes
        return _relax(mesh, field, 1e-3 * spacing, iterations=5, ends=ends)

    def ends(self) -> list[EndSpec]:
        ends = []
        for side, name in ((1.0, "right_iliac"), (-1.0, "left_iliac")):
            start, direction = self._iliac_axis(side)
            ends.append(EndSpec(name, start + self.iliac_length * direction, direction, self.iliac_radius))
        ends.append(EndSpec("proximal", np.array([0.0, 0.0, self._top()]), np.array([0.0, 0.0, 1.0]),
                            self.aorta_radius))
        return ends

    def sac(self) -> SacSite:
        center = np.array([0.0, 0.0, self.bifurcation_height + 0.5 * self.aortic_length])
        return SacSite(center, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), self.aneurysm_radius,
                       2.0 * self.aneurysm_radius)


# ------------------------------------------------------------------------------ the registry and its functions

FAMILY: dict[str, type[_Member]] = {
    cls.KIND: cls for cls in (FusiformParameters, SaccularParameters, EccentricParameters, AngulatedNeckParameters,
                              TortuousParameters, BifurcationParameters)
}


def _parameters(kind: str, strict: bool, parameters: dict) -> _Member:
    if kind not in FAMILY:
        raise AnatomyError(f"no member {kind!r} in the aneurysm family: choose one of {sorted(FAMILY)}")
    cls = FAMILY[kind]
    names = [f.name for f in fields(cls)]
    unknown = sorted(set(parameters) - set(names))
    if unknown:
        raise AnatomyError(f"{kind}: unknown parameter(s) {unknown}: its parameters are {names}")
    return cls(**parameters, strict=strict)


def lumen_surface(kind: str, *, edge_length: float | None = None, triangles: int | None = None, strict: bool = True,
                  **parameters) -> trimesh.Trimesh:
    """The lumen surface of a family member (metres, open ends, normals out of the lumen).

    ``parameters`` are the member's dataclass fields (defaults otherwise); ``edge_length`` (m) or
    ``triangles`` set the resolution; ``strict=False`` builds values outside their published ranges
    with a logged warning.
    """
    return _parameters(kind, strict, parameters).surface(edge_length=edge_length, triangles=triangles)


def sac_center(kind: str, *, strict: bool = True, **parameters) -> SacSite:
    """Where the sac is widest and the direction of its farthest wall (to aim a catheter at)."""
    return _parameters(kind, strict, parameters).sac()


def export_lumen_surface(kind_or_mesh: str | trimesh.Trimesh, path, *, edge_length: float | None = None,
                         triangles: int | None = None, strict: bool = True, **parameters) -> Path:
    """Write a member's lumen surface (or a given mesh) as STL, OBJ or PLY, by the path's extension.

    Coordinates are written in metres, as :mod:`anatomy.surface` reads them. Returns the path.
    """
    path = Path(path)
    if path.suffix.lower() not in EXPORT_FORMATS:
        raise AnatomyError(f"cannot write {path.name!r}: give a path ending in one of {', '.join(EXPORT_FORMATS)}")
    if isinstance(kind_or_mesh, trimesh.Trimesh):
        if parameters or edge_length is not None or triangles is not None:
            raise AnatomyError("a mesh is written as it is: give no parameters, edge_length or triangles with it")
        mesh = kind_or_mesh
    else:
        mesh = lumen_surface(kind_or_mesh, edge_length=edge_length, triangles=triangles, strict=strict, **parameters)
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(path)
    return path
