"""Catheter numba kernels against slow plain-Python/numpy reference implementations.

The references below are the algorithms of ``CenterlineCurve`` / ``CatheterKinematics`` /
``CatheterModel.step`` as they were before the kernels existed (copied verbatim in logic), so
every test compares the fast path with the original behaviour over many random centerlines,
insertions, bend vectors and forces. Tolerance: 1e-12 relative to the segment length for
positions (the kernels repeat the same arithmetic; only dot-product summation order may differ).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from catheter_fmu import CatheterModel, CatheterParameters, CenterlineCurve
from catheter_fmu import kernels
from catheter_fmu.kinematics import CatheterKinematics

# ======================================================================================
# Reference implementations (plain Python / numpy, the pre-kernel algorithms)
# ======================================================================================


def ref_cross(a, b) -> np.ndarray:
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def ref_rotate_min(x, a, b) -> np.ndarray:
    v = ref_cross(a, b)
    c = float(a @ b)
    vx = ref_cross(v, x)
    return x + vx + ref_cross(v, vx) / (1.0 + c)


def ref_segment_index(curve: CenterlineCurve, s: float) -> int:
    i = int(np.searchsorted(curve.arc, s, side="right")) - 1
    return min(max(i, 0), curve.directions.shape[0] - 1)


def ref_point(curve: CenterlineCurve, s: float) -> np.ndarray:
    i = ref_segment_index(curve, s)
    return curve.vertices[i] + (s - curve.arc[i]) * curve.directions[i]


def ref_frame(curve: CenterlineCurve, s: float):
    i = ref_segment_index(curve, s)
    w = (s - curve.arc[i]) / curve.segment_lengths[i]
    w = min(max(w, 0.0), 1.0)
    t = (1.0 - w) * curve.vertex_tangents[i] + w * curve.vertex_tangents[i + 1]
    t /= math.sqrt(float(t @ t))
    e1 = ref_rotate_min(curve.vertex_normals[i], curve.vertex_tangents[i], t)
    e1 -= (e1 @ t) * t
    e1 /= math.sqrt(float(e1 @ e1))
    return t, e1, ref_cross(t, e1)


def ref_chain_back(curve: CenterlineCurve, s_start: float, n_points: int, spacing: float) -> np.ndarray:
    out = np.empty((n_points, 3))
    s_cur = float(s_start)
    j = ref_segment_index(curve, s_cur)
    p_cur = curve.vertices[j] + (s_cur - curve.arc[j]) * curve.directions[j]
    k = 0
    steps = spacing * np.arange(1, n_points + 1, dtype=np.float64)
    while k < n_points:
        cand = s_cur - steps[: n_points - k]
        m = cand.size if j == 0 else int(np.count_nonzero(cand >= curve.arc[j]))
        if m:
            out[k : k + m] = curve.vertices[j] + (cand[:m] - curve.arc[j])[:, None] * curve.directions[j]
            k += m
            s_cur = float(cand[m - 1])
            p_cur = out[k - 1]
            if k == n_points:
                break
        jj = j - 1
        while True:
            rel = curve.vertices[jj] - p_cur
            b = float(curve.directions[jj] @ rel)
            c = float(rel @ rel) - spacing * spacing
            disc = b * b - c
            if disc >= 0.0:
                root = -b - math.sqrt(disc)
                length = float(curve.segment_lengths[jj])
                if root <= length * (1.0 + 1e-12) and (root >= 0.0 or jj == 0):
                    root = min(root, length)
                    break
            if jj == 0:
                root = float((p_cur - curve.vertices[0]) @ curve.directions[0]) - spacing
                break
            jj -= 1
        p_cur = curve.vertices[jj] + root * curve.directions[jj]
        s_cur = float(curve.arc[jj]) + root
        out[k] = p_cur
        k += 1
        j = jj
    return out


def ref_link_fraction(n_active: int) -> np.ndarray:
    return (np.arange(1, n_active + 1) - 0.5) / n_active


def ref_active_chain(n_active, segment_length, base, t, e1, e2, bend_vector) -> np.ndarray:
    b1, b2 = bend_vector
    beta = math.hypot(b1, b2)
    d = (b1 * e1 + b2 * e2) / beta if beta > 0.0 else e1
    ang = beta * ref_link_fraction(n_active)
    links = np.cos(ang)[:, None] * t + np.sin(ang)[:, None] * d
    return base + segment_length * np.cumsum(links, axis=0)


def ref_base_frame(curve, active_length, insertion):
    s_b = insertion - active_length
    t, e1, e2 = ref_frame(curve, s_b)
    return ref_point(curve, s_b), t, e1, e2


def ref_shape(curve, n_segments, n_active, segment_length, insertion, bend_vector, frame=None) -> np.ndarray:
    active_length = n_active * segment_length
    base, t, e1, e2 = ref_base_frame(curve, active_length, insertion) if frame is None else frame
    n_prox = n_segments - n_active
    pos = np.zeros((n_segments + 1, 3))
    if n_prox:
        pos[n_prox - 1 :: -1] = ref_chain_back(curve, insertion - active_length, n_prox, segment_length)
    pos[n_prox] = base
    pos[n_prox + 1 :] = ref_active_chain(n_active, segment_length, base, t, e1, e2, bend_vector)
    return pos


class ReferenceStepper:
    """The pre-kernel ``CatheterModel.step`` / ``_outputs_from`` running on a model's state
    (actuator, regulator, monitor, passive bend) with the reference geometry above."""

    MAX_TOTAL_BEND = math.pi

    def __init__(self, model: CatheterModel) -> None:
        self.m = model
        p = model.params
        self.n_segments = p.n_segments
        self.n_active = p.n_active_segments
        self.seg = float(p.segment_length)
        self.active_length = self.n_active * self.seg

    def reset(self, insertion, rotation=0.0):
        m = self.m
        m.actuator.angle = 0.0
        m.actuator.rate_limited = 0
        m.regulator.reset()
        m.monitor.warning = False
        m.passive_bend = np.zeros(2)
        m.time = 0.0
        return self._outputs_from(float(insertion), float(rotation), 0.0, 0.0, None)

    def step(self, t, dt, insertion, rotation, tip_force, external_command=0.0):
        m = self.m
        force = np.asarray(tip_force, dtype=np.float64)
        frame = ref_base_frame(m.curve, self.active_length, insertion)
        e1, e2 = frame[2], frame[3]
        f1 = float(force @ e1)
        f2 = float(force @ e2)
        force_magnitude = math.sqrt(float(force @ force))
        cos_r, sin_r = math.cos(rotation), math.sin(rotation)
        if m.mode == "regulate":
            command = m.regulator.command(force_magnitude, f1 * cos_r + f2 * sin_r, dt, m.actuator.rate_limited)
        elif m.mode == "external":
            command = external_command
        else:
            command = 0.0
        command = m.actuator.clip_command(command)
        m.actuator.step(command, dt)
        target1 = m.passive_gain * f1
        target2 = m.passive_gain * f2
        tau = m.params.passive_time_constant
        keep = math.exp(-dt / tau) if tau > 0.0 else 0.0
        pb = m.passive_bend
        pb[0] = target1 + (pb[0] - target1) * keep
        pb[1] = target2 + (pb[1] - target2) * keep
        m.time = float(t) + dt
        return self._outputs_from(insertion, rotation, command, force_magnitude, frame, cos_r, sin_r)

    def _outputs_from(self, insertion, rotation, command, force_magnitude, frame, cos_r=None, sin_r=None):
        m = self.m
        if cos_r is None:
            cos_r, sin_r = math.cos(rotation), math.sin(rotation)
        angle = m.actuator.angle
        b1 = angle * cos_r + m.passive_bend[0]
        b2 = angle * sin_r + m.passive_bend[1]
        total = math.hypot(b1, b2)
        if total > self.MAX_TOTAL_BEND:
            b1, b2 = b1 * self.MAX_TOTAL_BEND / total, b2 * self.MAX_TOTAL_BEND / total
        pos = ref_shape(m.curve, self.n_segments, self.n_active, self.seg, insertion, (b1, b2), frame)
        warning, scale = m.monitor.update(force_magnitude)
        return {
            "centerline_positions": pos.reshape(-1).copy(),
            "tip_position": pos[-1].copy(),
            "bend_angle": angle,
            "actuator_command": command,
            "effort_warning": warning,
            "advised_insertion_scale": scale,
            "tip_force_magnitude": force_magnitude,
            "total_bend": math.hypot(b1, b2),
        }


# ======================================================================================
# Random test data
# ======================================================================================

SEG = 0.005
ATOL = 1e-12 * SEG  # "same results to 1e-12 relative to the segment length"


def random_centerline(rng: np.random.Generator, n_vertices: int | None = None) -> CenterlineCurve:
    """Random polyline: segment lengths 1-25 mm, turns up to ~80 deg per vertex (below the limit)."""
    n = int(rng.integers(2, 12)) if n_vertices is None else n_vertices
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    pts = [rng.normal(scale=0.01, size=3)]
    for _ in range(n - 1):
        pts.append(pts[-1] + rng.uniform(0.001, 0.025) * d)
        # turn by a random angle up to 80 deg about a random axis normal to d
        axis = np.cross(d, rng.normal(size=3))
        axis /= np.linalg.norm(axis)
        ang = math.radians(rng.uniform(0.0, 80.0))
        d = math.cos(ang) * d + math.sin(ang) * np.cross(axis, d)
        d /= np.linalg.norm(d)
    return CenterlineCurve(np.array(pts))


def grid_centerline(rng: np.random.Generator, spacing: float) -> CenterlineCurve:
    """Segment lengths that are whole multiples of ``spacing``: chains meet vertices at exactly one
    spacing (the regression of test_chain_back_through_a_vertex_at_exactly_one_spacing)."""
    n = int(rng.integers(2, 7))
    pts = [np.zeros(3)]
    d = np.array([0.0, 0.0, 1.0])
    for _ in range(n - 1):
        pts.append(pts[-1] + spacing * int(rng.integers(1, 6)) * d)
        ang = math.radians(rng.uniform(5.0, 60.0))
        phi = rng.uniform(0, 2 * math.pi)
        axis = np.array([math.cos(phi), math.sin(phi), 0.0])
        axis -= (axis @ d) * d
        axis /= np.linalg.norm(axis)
        d = math.cos(ang) * d + math.sin(ang) * np.cross(axis, d)
        d /= np.linalg.norm(d)
    return CenterlineCurve(np.array(pts))


def sample_arcs(rng: np.random.Generator, curve: CenterlineCurve, n: int) -> np.ndarray:
    """Arc lengths before, on, just beside and between vertices, and beyond the end."""
    L = curve.length
    s = list(rng.uniform(-0.3 * L - 0.01, 1.3 * L + 0.01, size=n))
    for a in curve.arc:
        s += [float(a), float(np.nextafter(a, -np.inf)), float(np.nextafter(a, np.inf))]
    return np.array(s)


# ======================================================================================
# Kernels against references
# ======================================================================================


def test_segment_index_matches_searchsorted():
    rng = np.random.default_rng(1)
    for _ in range(30):
        curve = random_centerline(rng)
        for s in sample_arcs(rng, curve, 40):
            assert kernels.segment_index(curve.arc, float(s)) == ref_segment_index(curve, float(s))
            assert curve.segment_index(float(s)) == ref_segment_index(curve, float(s))


def test_point_and_frame_match_reference():
    rng = np.random.default_rng(2)
    for _ in range(30):
        curve = random_centerline(rng)
        for s in sample_arcs(rng, curve, 30):
            s = float(s)
            np.testing.assert_allclose(curve.point(s), ref_point(curve, s), rtol=0, atol=ATOL)
            for new, ref in zip(curve.frame(s), ref_frame(curve, s)):
                np.testing.assert_allclose(new, ref, rtol=0, atol=1e-13)
            np.testing.assert_allclose(curve.points([s, s]), [ref_point(curve, s)] * 2, rtol=0, atol=ATOL)


def _check_chain(curve, s, n, spacing):
    new = curve.chain_back(s, n, spacing)
    ref = ref_chain_back(curve, s, n, spacing)
    np.testing.assert_allclose(new, ref, rtol=0, atol=1e-12 * spacing)
    # and the defining property: consecutive joints exactly one spacing apart
    gaps = np.linalg.norm(np.diff(np.vstack([curve.point(s), new]), axis=0), axis=1)
    np.testing.assert_allclose(gaps, spacing, rtol=1e-9)


def test_chain_back_matches_reference_on_random_centerlines():
    rng = np.random.default_rng(3)
    for _ in range(40):
        curve = random_centerline(rng)
        spacing = float(rng.uniform(0.001, 0.01))
        for s in sample_arcs(rng, curve, 10):
            _check_chain(curve, float(s), int(rng.integers(1, 40)), spacing)


def test_chain_back_matches_reference_when_vertices_fall_on_whole_spacings():
    rng = np.random.default_rng(4)
    for _ in range(40):
        curve = grid_centerline(rng, SEG)
        # starts a whole number of spacings past a vertex, and one ulp either side
        for k in range(1, 8):
            for a in curve.arc:
                s0 = float(a) + k * SEG
                for s in (s0, float(np.nextafter(s0, -1.0)), float(np.nextafter(s0, 1.0))):
                    _check_chain(curve, s, 26, SEG)


def test_chain_back_regression_root_exactly_at_a_vertex_is_clamped():
    """The regression case of test_catheter_model: the kernel clamps the root at the vertex."""
    curve = CenterlineCurve(np.array([[0, 0, 0], [0, 0, 0.05], [0.0085, 0, 0.09]]))
    for s in (0.06, np.nextafter(0.06, 0.0), np.nextafter(0.06, 1.0)):
        out = np.empty((26, 3))
        kernels.chain_back(curve.vertices, curve.directions, curve.arc, curve.segment_lengths, float(s), 0.005, out)
        np.testing.assert_allclose(out, ref_chain_back(curve, float(s), 26, 0.005), rtol=0, atol=ATOL)
        assert np.all(np.abs(out[2:, 0]) < 1e-12)
        # The joint that meets vertex 1 is clamped onto it: no joint behind it passes the
        # vertex, not even by a rounding.
        assert np.all(out[1:, 2] <= curve.vertices[1, 2])
        assert np.array_equal(out[1], curve.vertices[1])


def test_active_chain_matches_reference():
    rng = np.random.default_rng(5)
    curve = random_centerline(rng)
    for n_active in (1, 2, 4, 7):
        kin = CatheterKinematics(curve, 10, SEG, n_active)
        for _ in range(50):
            base, t, e1, e2 = ref_base_frame(curve, kin.active_length, float(rng.uniform(-0.02, curve.length + 0.05)))
            bend = (0.0, 0.0) if rng.random() < 0.1 else tuple(rng.uniform(-math.pi, math.pi, size=2))
            np.testing.assert_allclose(
                kin.active_chain(base, t, e1, e2, bend),
                ref_active_chain(n_active, SEG, base, t, e1, e2, bend),
                rtol=0,
                atol=ATOL,
            )


def test_tip_jacobian_matches_finite_differences():
    """d tip / d bend of the implicit passive bend, against central differences of active_chain
    (straight, small, large and folded bends)."""
    rng = np.random.default_rng(9)
    curve = random_centerline(rng)
    h = 1e-7
    for n_active in (1, 4, 7):
        kin = CatheterKinematics(curve, 10, SEG, n_active)
        for k in range(40):
            frame = np.array(ref_base_frame(curve, kin.active_length, float(rng.uniform(0.0, curve.length))))
            bend = ((0.0, 0.0), (1e-7, -3e-8), (0.02, 0.01))[k] if k < 3 else tuple(rng.uniform(-3.0, 3.0, size=2))
            jac = np.zeros((3, 2))
            kernels.tip_jacobian(frame, bend[0], bend[1], kin._link_fraction, SEG, jac)
            out = np.zeros((n_active, 3))
            numeric = np.zeros((3, 2))
            for c in range(2):
                tips = []
                for sign in (1.0, -1.0):
                    b = list(bend)
                    b[c] += sign * h
                    kernels.active_chain(frame, b[0], b[1], kin._link_fraction, SEG, out)
                    tips.append(out[-1].copy())
                numeric[:, c] = (tips[0] - tips[1]) / (2 * h)
            np.testing.assert_allclose(jac, numeric, rtol=0, atol=1e-7 * SEG * n_active)
    # straight tip: it moves by L / 2 per radian across its tangent
    np.testing.assert_allclose(_straight_jacobian(kin, frame), 0.5 * kin.active_length *
                               frame[2:].T, atol=1e-15)


def _straight_jacobian(kin, frame):
    jac = np.zeros((3, 2))
    kernels.tip_jacobian(frame, 0.0, 0.0, kin._link_fraction, SEG, jac)
    return jac


def test_kinematics_shape_and_base_frame_match_reference():
    rng = np.random.default_rng(6)
    for _ in range(30):
        curve = random_centerline(rng)
        n_seg = int(rng.integers(1, 35))
        n_act = int(rng.integers(1, n_seg + 1))
        kin = CatheterKinematics(curve, n_seg, SEG, n_act)
        for _ in range(15):
            ins = float(rng.uniform(-0.05, curve.length + 0.05))
            bend = tuple(rng.uniform(-2.0, 2.0, size=2))
            for new, ref in zip(kin.base_frame(ins), ref_base_frame(curve, kin.active_length, ins)):
                np.testing.assert_allclose(new, ref, rtol=0, atol=ATOL)
            ref = ref_shape(curve, n_seg, n_act, SEG, ins, bend)
            np.testing.assert_allclose(kin.shape(ins, bend), ref, rtol=0, atol=ATOL)
            frame = ref_base_frame(curve, kin.active_length, ins)
            np.testing.assert_allclose(kin.shape(ins, bend, frame), ref, rtol=0, atol=ATOL)


@pytest.mark.parametrize("mode", ["regulate", "external", "off"])
def test_model_step_matches_reference_step(mode):
    """Whole steps: random insertions, rotations, forces and commands on random centerlines."""
    rng = np.random.default_rng({"regulate": 7, "external": 8, "off": 9}[mode])
    for trial in range(4):
        curve = random_centerline(rng, n_vertices=int(rng.integers(2, 10)))
        params = CatheterParameters(centerline=curve, controller_mode=mode,
                                    passive_time_constant=0.0 if trial == 3 else 0.01)
        new, old = CatheterModel(params, 1e-3), CatheterModel(params, 1e-3)
        ref = ReferenceStepper(old)
        ins0 = float(rng.uniform(0.0, curve.length))
        out_new, out_ref = new.reset(ins0, 0.2), ref.reset(ins0, 0.2)
        np.testing.assert_allclose(out_new.centerline_positions, out_ref["centerline_positions"], rtol=0, atol=ATOL)
        for k in range(300):
            t = k * 1e-3
            ins = ins0 + 0.02 * math.sin(3.0 * t) + float(rng.uniform(-1e-3, 1e-3))
            rot = 0.2 + float(rng.uniform(-0.5, 0.5))
            force = rng.normal(scale=0.4, size=3) * (k % 50 > 10)
            cmd = float(rng.uniform(-2.0, 2.0))
            a = new.step(t, 1e-3, ins, rot, force, cmd)
            b = ref.step(t, 1e-3, ins, rot, force, cmd)
            np.testing.assert_allclose(a.centerline_positions, b["centerline_positions"], rtol=0, atol=ATOL)
            np.testing.assert_allclose(a.tip_position, b["tip_position"], rtol=0, atol=ATOL)
            scalars = ("bend_angle", "actuator_command", "advised_insertion_scale", "tip_force_magnitude", "total_bend")
            for name in scalars:
                assert abs(getattr(a, name) - b[name]) <= 1e-12 * max(1.0, abs(b[name])), name
            assert a.effort_warning == b["effort_warning"]
            assert new.time == old.time
