"""The narrow phase's depth is a signed distance to the wall, continuous in the tool's configuration.

Checked against what we did not write: trimesh's signed distance on the default AAA wall (a closed
shell: lumen side and outer side), and finite differences of the tool's motion across the edges and
vertices of that tessellated wall (a signed distance is 1-Lipschitz: no step of the tool may change
the depth by more than the step; the force may not jump).
"""
import numpy as np
import pytest
import trimesh

import haptic_helpers as helpers
from haptic_fmu import narrow_phase
from haptic_fmu.model import ContactModel, ContactParameters
from tissue_fmu.mesh import aaa_mesh

RNG = np.random.default_rng(20261128)


@pytest.fixture(scope="module")
def wall():
    """The default AAA wall's surface: (positions, triangles, trimesh of it)."""
    mesh = aaa_mesh()
    nodes, tri = mesh.surface()
    pos = np.ascontiguousarray(mesh.points[nodes])
    shell = trimesh.Trimesh(pos, tri, process=False)
    assert shell.is_watertight and shell.volume > 0      # closed, normals out of the wall's tissue
    return pos, np.ascontiguousarray(tri, np.int64), shell


def signed_distances(points, pos, tri, trust=np.inf):
    """Our narrow phase's signed distance of each point (radius 0, no side memory), every face a
    candidate: near_dist with a band wide enough to report every point."""
    n = len(points)
    local = helpers.local_from_surface(0.0, pos, np.zeros_like(pos), tri, policy="hold", n_nodes=n)
    k = local.node_faces.size
    out = dict(face=np.full(n, -1, np.int64), w=np.zeros((n, 3)), n=np.zeros((n, 3)), depth=np.zeros(n),
               rate=np.zeros(n), s=np.zeros(n), q=np.zeros((n, 3)), near=np.zeros(n))
    narrow_phase.proximity(local.positions, local.velocities, local.triangles, local.node_ptr, local.node_faces,
                           np.zeros(1, np.int64), local.seg_faces, np.ascontiguousarray(points), np.zeros((n, 3)),
                           0.0, 1.0, np.full(n, trust), np.zeros(n, np.int8), np.zeros((n, 3)), out["face"],
                           out["w"], out["n"],
                           out["depth"], out["rate"], out["s"], out["q"], out["near"],
                           np.zeros((max(k // n, 1), narrow_phase.WORK_COLUMNS)))
    return out["near"]


def points_near(shell, count, spread):
    """Random points within `spread` of the surface, on both sides, near vertices and edges too."""
    on_faces, _ = trimesh.sample.sample_surface(shell, count // 2, seed=7)
    vertices = shell.vertices[RNG.integers(0, len(shell.vertices), count - count // 2)]
    base = np.concatenate([on_faces, vertices])
    return base + RNG.normal(size=base.shape) * spread


def test_signed_distance_matches_trimesh_on_the_default_wall(wall):
    pos, tri, shell = wall
    points = points_near(shell, 300, 0.0007)
    ours = signed_distances(points, pos, tri)
    # trimesh: positive inside the tissue; queried in millimetres, because its tie tolerance on
    # squared distances (tol.merge = 1e-8) is absolute: in metres it takes faces up to 0.1 mm
    # farther than the nearest for ties, and returns one of them
    millimetres = trimesh.Trimesh(shell.vertices * 1e3, shell.faces, process=False)
    theirs = -trimesh.proximity.signed_distance(millimetres, points * 1e3) * 1e-3
    inside = theirs < 0
    assert 40 < inside.sum() < 260                                 # both sides were checked
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-15)


def test_a_point_in_the_lumen_seeing_only_the_outer_surface_is_not_in_contact(wall):
    """The phantom contact of the 2x push: a catheter node in the lumen, 8 mm from the wall, whose
    only candidates are faces of the outer surface. It is behind their planes, yet not in the wall:
    no contact (the old rule gave 8.97 mm of depth, 45 N)."""
    pos, tri, shell = wall
    centroids = pos[tri].mean(axis=1)
    outer = np.flatnonzero(np.einsum("ij,ij->i", shell.face_normals, centroids - [0, 0, centroids[:, 2].mean()])
                           > 0)
    rng = np.random.default_rng(1)
    checked = 0
    for face in rng.choice(outer, 20):
        point = centroids[face] - 0.0095 * shell.face_normals[face]     # behind an outer face ...
        if shell.contains(point[None])[0]:
            continue                                                    # ... in the tissue: not this case
        # ... in the lumen: a margin of 12 mm makes the face a candidate (as a box corner did)
        model = ContactModel(tri[[face]], len(pos), 1, ContactParameters(tool="probe", local_model="hold",
                                                                          stiffness=5000.0, margin=0.012))
        model.set_tissue_frame(0.0, pos, np.zeros_like(pos))
        out = model.step(0.0, 1e-3, point)
        assert model.local.n_faces == 1
        assert out.contact_count == 0 and not out.tool_force.any()
        checked += 1
    assert checked >= 10


def _model(pos, tri, n_tool, tool, radius=0.001):
    """The geometry alone: a rigid wall, the law at the sampled depth, no device limit."""
    model = ContactModel(tri, len(pos), n_tool, ContactParameters(tool=tool, tool_radius=radius, stiffness=1000.0,
                                                                   damping=0.0, local_model="hold",
                                                                   energy_consistent=False, max_force=1e3,
                                                                   max_force_rate=1e9))
    model.set_tissue_frame(0.0, pos, np.zeros_like(pos))
    return model


@pytest.mark.parametrize("tool", ["probe", "centerline"])
def test_depth_and_force_are_continuous_across_edges_and_vertices(wall, tool):
    """Slide a probe (radius 0) or a three-node catheter piece (spheres and capsules of 1 mm) along
    random paths through the wall's surface in 2 um steps: the depth changes by at most what the tool
    moved (a signed distance is 1-Lipschitz; a capsule's excess over its ends at most 3x), and the
    force by at most k times that plus the turn of its direction (bounded by the normal's blend)."""
    pos, tri, shell = wall
    k, step = 1000.0, 2e-6
    n_tool = 1 if tool == "probe" else 3
    radius = 0.0 if tool == "probe" else 0.001
    lipschitz = 1.0 if tool == "probe" else 3.0
    # the direction turns by at most the angle between neighbouring faces (< 0.3 rad here) over the
    # blend length: |dF| <= k (depth change + depth * 0.3 / NORMAL_BLEND_LENGTH * step)
    turn = 0.3 / narrow_phase.NORMAL_BLEND_LENGTH
    rng = np.random.default_rng(3 if tool == "probe" else 4)
    starts = shell.vertices[rng.integers(0, len(shell.vertices), 12)]
    worst = 0.0
    contacts = 0
    for start in starts:
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        shape = np.array([[0.0, 0.0, 0.0]]) if n_tool == 1 else np.array(
            [[0.0, 0.0, -0.006], [0.0, 0.0, -0.003], [0.0, 0.0, 0.0]]) @ _rotation(rng)
        model = _model(pos, tri, n_tool, tool, radius)
        base = start - 0.0008 * direction - (0 if n_tool == 1 else 0.0) + rng.normal(size=3) * 2e-4
        previous = None
        for i in range(800):
            tool_points = base + shape + i * step * direction
            out = model.step(i * 1e-3, 1e-3, tool_points)
            depth = out.penetration_depth
            force = out.tool_force.copy()
            contacts += out.contact_count > 0
            if previous is not None:
                d_depth = abs(depth - previous[0])
                assert d_depth <= lipschitz * step * (1 + 1e-9) + 1e-15, (i, depth, previous[0])
                bound = k * (d_depth + max(depth, previous[0]) * turn * step) * 4 + 1e-12
                jump = np.linalg.norm(force - previous[1])
                worst = max(worst, jump / bound)
                assert jump <= bound, (i, jump, bound)
            previous = (depth, force)
    assert contacts > 1000                                  # the paths did go through the wall


def _rotation(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q


def test_a_capsule_switches_on_from_zero_depth():
    """A segment passing over a ridge between two facets while its ends rest on them: its extra
    contact grows from zero as the ridge rises, and the total force with it (the old capsule
    appeared with a finite depth when its closest point left an end)."""
    pos = np.array([[-0.01, -0.01, 0.0], [-0.01, 0.01, 0.0], [0.0, -0.01, 0.0], [0.0, 0.01, 0.0],
                    [0.01, -0.01, 0.0], [0.01, 0.01, 0.0]])
    tri = np.array([[0, 2, 1], [1, 2, 3], [2, 4, 3], [3, 4, 5]])
    forces = []
    for ridge in np.linspace(-0.0004, 0.0004, 81):
        lifted = pos.copy()
        lifted[2:4, 2] = ridge                     # the middle edge rises: a ridge (or a valley)
        model = ContactModel(tri, 6, 2, ContactParameters(stiffness=1000.0, damping=0.0, tool_radius=0.001,
                                                          local_model="hold", margin=0.01))
        model.set_tissue_frame(0.0, lifted, np.zeros_like(lifted))
        out = model.step(0.0, 1e-3, [[-0.008, 0.0, 0.0009], [0.008, 0.0, 0.0009]])
        forces.append(out.tool_force[2])
    steps = np.abs(np.diff(forces))
    # the ridge rises 10 um per sample: the force may change by k * 10 um (the capsule) + the ends'
    # share of the tilt, never jump
    assert steps.max() <= 1000.0 * 1e-5 * 1.5
    assert forces[-1] > forces[40] > 0.0            # the ridge adds a contact of its own
