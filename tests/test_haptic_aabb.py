"""Broad phase: AABB tree pair sets against brute-force enumeration, refit against rebuild, box makers."""
import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from haptic_fmu import aabb
from haptic_fmu.aabb import AABBInputError, AABBTree


def brute_force_pairs(alo, ahi, blo, bhi):
    """Slow reference: all (i, j) whose closed boxes overlap, in lexicographic order."""
    overlap = np.all((alo[:, None, :] <= bhi[None, :, :]) & (blo[None, :, :] <= ahi[:, None, :]), axis=2)
    return np.argwhere(overlap).astype(np.int64)


def random_boxes(rng, m, size=0.1):
    centre = rng.uniform(0.0, 1.0, (m, 3))
    return centre - rng.uniform(0.0, size, (m, 3)), centre + rng.uniform(0.0, size, (m, 3))


def random_mesh(rng, n_faces):
    """Random triangles (a 'triangle soup' mesh) of size about 0.05 in the unit cube."""
    centre = rng.uniform(0.0, 1.0, (n_faces, 1, 3))
    vertices = (centre + rng.normal(0.0, 0.03, (n_faces, 3, 3))).reshape(-1, 3)
    return vertices, np.arange(3 * n_faces).reshape(n_faces, 3)


def check_tree_invariants(tree):
    """Every node box contains its children's boxes; leaves hold each primitive exactly once."""
    seen = []
    for node in range(tree.n_nodes):
        if tree.left[node] < 0:
            prims = tree.order[tree.start[node]:tree.start[node] + tree.count[node]]
            seen.extend(prims.tolist())
            assert np.all(tree.node_lo[node] <= tree.lo[prims]) and np.all(tree.hi[prims] <= tree.node_hi[node])
        else:
            for child in (tree.left[node], tree.right[node]):
                assert child > node
                assert np.all(tree.node_lo[node] <= tree.node_lo[child])
                assert np.all(tree.node_hi[child] <= tree.node_hi[node])
    assert sorted(seen) == list(range(tree.n_primitives))


@pytest.mark.parametrize("m,k,leaf_size", [(1, 1, 4), (2, 9, 1), (37, 11, 4), (300, 250, 4), (2000, 500, 8)])
def test_query_tree_and_boxes_equal_brute_force(m, k, leaf_size):
    rng = np.random.default_rng(m * 1000 + k)
    alo, ahi = random_boxes(rng, m)
    blo, bhi = random_boxes(rng, k)
    tree_a = AABBTree.build(alo, ahi, leaf_size=leaf_size)
    tree_b = AABBTree.build(blo, bhi, leaf_size=leaf_size)
    check_tree_invariants(tree_a)
    reference = brute_force_pairs(alo, ahi, blo, bhi)
    assert len(reference) > 0 or m * k < 100
    np.testing.assert_array_equal(tree_a.query_tree(tree_b), reference)
    np.testing.assert_array_equal(tree_a.query_boxes(blo, bhi), reference)
    # swapping the roles transposes the pair set
    swapped = tree_b.query_tree(tree_a)[:, ::-1]
    np.testing.assert_array_equal(swapped[np.lexsort((swapped[:, 1], swapped[:, 0]))], reference)


@pytest.mark.parametrize("n_faces", [10, 500, 3000])
def test_mesh_against_tool_segments_and_refit(n_faces):
    """Tissue triangle tree vs tool segment tree, before and after motion (refit) vs brute force and rebuild."""
    rng = np.random.default_rng(n_faces)
    vertices, faces = random_mesh(rng, n_faces)
    tool = np.cumsum(rng.normal(0.0, 0.05, (40, 3)), axis=0) + 0.5
    lo, hi = aabb.triangle_boxes(vertices, faces, inflate=0.002)
    slo, shi = aabb.segment_boxes(tool, radius=0.001)
    tissue_tree = AABBTree.build(lo, hi)
    tool_tree = AABBTree.build(slo, shi, leaf_size=2)
    np.testing.assert_array_equal(tissue_tree.query_tree(tool_tree), brute_force_pairs(lo, hi, slo, shi))

    moved = vertices + rng.normal(0.0, 0.02, vertices.shape)
    tool_moved = tool + rng.normal(0.0, 0.02, tool.shape)
    lo2, hi2 = aabb.triangle_boxes(vertices, faces, positions_end=moved, inflate=0.002)
    slo2, shi2 = aabb.segment_boxes(tool, positions_end=tool_moved, radius=0.001)
    tissue_tree.refit(lo2, hi2)
    tool_tree.refit(slo2, shi2)
    check_tree_invariants(tissue_tree)
    reference = brute_force_pairs(lo2, hi2, slo2, shi2)
    assert len(reference) > 0
    refitted = tissue_tree.query_tree(tool_tree)
    rebuilt = AABBTree.build(lo2, hi2).query_tree(AABBTree.build(slo2, shi2, leaf_size=2))
    np.testing.assert_array_equal(refitted, reference)
    np.testing.assert_array_equal(rebuilt, reference)
    np.testing.assert_array_equal(tissue_tree.query_boxes(slo2, shi2), reference)


def test_refit_after_motion_equals_rebuild_on_sphere_self_query():
    """Self-overlap pairs of a deformed icosphere: refitted tree == rebuilt tree == brute force."""
    rng = np.random.default_rng(7)
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.01)
    vertices = np.asarray(mesh.vertices)
    faces = np.asarray(mesh.faces)
    tree = AABBTree.build(*aabb.triangle_boxes(vertices, faces))
    moved = vertices * (1.0 + 0.3 * np.sin(5.0 * vertices[:, :1] / 0.01)) + rng.normal(0.0, 2e-4, vertices.shape)
    lo, hi = aabb.triangle_boxes(moved, faces)
    tree.refit(lo, hi)
    rebuilt = AABBTree.build(lo, hi)
    reference = brute_force_pairs(lo, hi, lo, hi)
    np.testing.assert_array_equal(tree.query_tree(tree), reference)
    np.testing.assert_array_equal(rebuilt.query_tree(rebuilt), reference)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(*[st.integers(-6, 6)] * 3, *[st.integers(0, 3)] * 3), min_size=1, max_size=40),
       st.lists(st.tuples(*[st.integers(-6, 6)] * 3, *[st.integers(0, 3)] * 3), min_size=1, max_size=40),
       st.integers(1, 5))
def test_integer_boxes_with_exact_touching(boxes_a, boxes_b, leaf_size):
    """Integer boxes touch exactly on faces, edges and corners: closed-box overlap must agree with brute force."""
    a = np.array(boxes_a, dtype=float)
    b = np.array(boxes_b, dtype=float)
    alo, ahi = a[:, :3], a[:, :3] + a[:, 3:]
    blo, bhi = b[:, :3], b[:, :3] + b[:, 3:]
    tree = AABBTree.build(alo, ahi, leaf_size=leaf_size)
    reference = brute_force_pairs(alo, ahi, blo, bhi)
    np.testing.assert_array_equal(tree.query_tree(AABBTree.build(blo, bhi, leaf_size=leaf_size)), reference)
    np.testing.assert_array_equal(tree.query_boxes(blo, bhi), reference)


def test_output_buffer_growth_with_many_pairs():
    """All boxes overlap all others: m*k pairs exceed the initial buffer and must all be returned."""
    lo = np.zeros((60, 3))
    hi = np.ones((60, 3))
    tree = AABBTree.build(lo, hi)
    pairs = tree.query_tree(tree)
    assert pairs.shape == (3600, 2)
    np.testing.assert_array_equal(pairs, brute_force_pairs(lo, hi, lo, hi))


def test_box_makers_hand_computed():
    positions = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 3.0]])
    end = positions + np.array([0.0, 0.0, -1.0])
    lo, hi = aabb.triangle_boxes(positions, [[0, 1, 2], [1, 2, 3]], positions_end=end, inflate=0.5)
    np.testing.assert_array_equal(lo, [[-0.5, -0.5, -1.5], [-0.5, -0.5, -1.5]])
    np.testing.assert_array_equal(hi, [[1.5, 2.5, 0.5], [1.5, 2.5, 3.5]])
    lo, hi = aabb.segment_boxes(positions[:3], radius=0.25)
    np.testing.assert_array_equal(lo, [[-0.25, -0.25, -0.25], [-0.25, -0.25, -0.25]])
    np.testing.assert_array_equal(hi, [[1.25, 0.25, 0.25], [1.25, 2.25, 0.25]])
    lo, hi = aabb.point_boxes(positions[:2], positions_end=end[:2])
    np.testing.assert_array_equal(lo, [[0.0, 0.0, -1.0], [1.0, 0.0, -1.0]])
    np.testing.assert_array_equal(hi, [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])


def test_spline_swept_boxes_contain_sampled_trajectories():
    """Dense samples of the cubic Hermite trajectories lie inside the boxes; the boxes are not loose beyond
    the control-point hull (the extreme control points are attained by the box)."""
    rng = np.random.default_rng(3)
    n, dt = 30, 1e-3
    p0 = rng.uniform(0.0, 0.01, (n, 3))
    p1 = p0 + rng.normal(0.0, 1e-3, (n, 3))
    v0 = rng.normal(0.0, 5.0, (n, 3))
    v1 = rng.normal(0.0, 5.0, (n, 3))
    faces = rng.integers(0, n, (20, 3))
    lo, hi = aabb.spline_swept_boxes(p0, p1, v0, v1, dt, faces)
    s = np.linspace(0.0, 1.0, 201)[:, None, None]
    h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
    path = h00 * p0 + h10 * dt * v0 + h01 * p1 + h11 * dt * v1  # (201, n, 3)
    sampled = path[:, faces, :]  # (201, m, 3, 3)
    assert np.all(sampled.min(axis=(0, 2)) >= lo) and np.all(sampled.max(axis=(0, 2)) <= hi)
    control = np.stack([p0, p0 + v0 * (dt / 3), p1 - v1 * (dt / 3), p1], axis=1)[faces]  # (m, 3, 4, 3)
    np.testing.assert_array_equal(lo, control.min(axis=(1, 2)))


def test_validation_messages():
    with pytest.raises(AABBInputError, match="lo > hi"):
        AABBTree.build(np.ones((2, 3)), np.zeros((2, 3)))
    with pytest.raises(AABBInputError, match="shape"):
        AABBTree.build(np.zeros((2, 2)), np.zeros((2, 2)))
    with pytest.raises(AABBInputError, match="non-finite"):
        AABBTree.build(np.full((1, 3), np.nan), np.zeros((1, 3)))
    tree = AABBTree.build(np.zeros((3, 3)), np.ones((3, 3)))
    with pytest.raises(AABBInputError, match="same primitives"):
        tree.refit(np.zeros((4, 3)), np.ones((4, 3)))
    with pytest.raises(AABBInputError, match="outside"):
        aabb.triangle_boxes(np.zeros((3, 3)), [[0, 1, 3]])
    with pytest.raises(AABBInputError, match="inflate"):
        aabb.triangle_boxes(np.zeros((3, 3)), [[0, 1, 2]], inflate=-1.0)
    with pytest.raises(AABBInputError, match="at least 2"):
        aabb.segment_boxes(np.zeros((1, 3)))


def test_empty_tree_returns_no_pairs():
    empty = AABBTree.build(np.zeros((0, 3)), np.zeros((0, 3)))
    full = AABBTree.build(np.zeros((2, 3)), np.ones((2, 3)))
    assert empty.query_tree(full).shape == (0, 2)
    assert full.query_tree(empty).shape == (0, 2)
    assert full.query_boxes(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0, 2)
