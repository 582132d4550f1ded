"""The contact's tissue-frame intake kernels against plain numpy references (the code they
replaced in the 1 kHz loop): the local model's topology, the tree refit, the tool's query boxes,
the patch slots and the compliance block."""
import numpy as np
import pytest

from haptic_fmu import aabb, aabb_kernels, rendering, rendering_kernels
from haptic_fmu.rendering import LocalModel, check_compliance


def reference_capture(triangles, node_pairs, n_nodes, seg_pairs, n_segments):
    """np.unique / lexsort version of LocalModel.capture's topology."""
    def csr(pairs, n_rows, face_map):
        if pairs.shape[0] == 0:
            return np.zeros(n_rows + 1, np.int64), np.zeros(0, np.int64)
        order = np.lexsort((pairs[:, 1], pairs[:, 0]))
        ptr = np.zeros(n_rows + 1, np.int64)
        np.cumsum(np.bincount(pairs[order, 0], minlength=n_rows), out=ptr[1:])
        return ptr, face_map[pairs[order, 1]]

    faces = np.unique(np.concatenate([node_pairs[:, 1], seg_pairs[:, 1]]))
    face_map = np.full(triangles.shape[0], -1, np.int64)
    face_map[faces] = np.arange(faces.size)
    vertices, local_tri = np.unique(triangles[faces].reshape(-1), return_inverse=True)
    return (faces, vertices, local_tri.reshape(-1, 3), *csr(node_pairs, n_nodes, face_map),
            *csr(seg_pairs, n_segments, face_map))


@pytest.mark.parametrize("seed", range(6))
def test_capture_builds_the_same_local_model_as_the_numpy_reference(seed):
    rng = np.random.default_rng(seed)
    n_vertices, n_tri, n_nodes, n_segments = 300, 500, 31, 30
    triangles = rng.integers(0, n_vertices, size=(n_tri, 3))
    # pairs as a tree query returns them: unique, in any order, some rows empty
    node_pairs = np.unique(np.column_stack([rng.integers(0, n_nodes, 40 * seed + 1),
                                            rng.integers(0, n_tri, 40 * seed + 1)]), axis=0)
    seg_pairs = np.unique(np.column_stack([rng.integers(0, n_segments, 25 * seed),
                                           rng.integers(0, n_tri, 25 * seed)]), axis=0).reshape(-1, 2)
    node_pairs, seg_pairs = rng.permutation(node_pairs), rng.permutation(seg_pairs)
    positions = rng.normal(size=(n_vertices, 3))
    local = LocalModel("compliance")
    for _ in range(2):  # the second capture reuses the scratch maps
        local.capture(0.5, positions, -positions, triangles, node_pairs, n_nodes, seg_pairs, n_segments)
        faces, vertices, tri, node_ptr, node_faces, seg_ptr, seg_faces = reference_capture(
            triangles, node_pairs, n_nodes, seg_pairs, n_segments)
        for got, want in [(local.faces, faces), (local.vertices, vertices), (local.triangles, tri),
                          (local.node_ptr, node_ptr), (local.node_faces, node_faces), (local.seg_ptr, seg_ptr),
                          (local.seg_faces, seg_faces)]:
            np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(local.frame_positions, positions[vertices])
        assert np.all(local._scratch[0] == -1) and np.all(local._scratch[1] == -1)


def test_refit_gives_every_node_the_box_of_its_primitives():
    rng = np.random.default_rng(1)
    lo = rng.normal(size=(777, 3))
    tree = aabb.AABBTree.build(lo, lo + rng.uniform(0, 0.1, size=lo.shape))
    new_lo = lo + rng.normal(scale=0.3, size=lo.shape)
    new_hi = new_lo + rng.uniform(0, 0.2, size=lo.shape)
    tree.refit(new_lo, new_hi)
    for node in range(tree.n_nodes):
        prims = tree.order[tree.start[node]: tree.start[node] + tree.count[node]]
        np.testing.assert_array_equal(tree.node_lo[node], new_lo[prims].min(axis=0))
        np.testing.assert_array_equal(tree.node_hi[node], new_hi[prims].max(axis=0))


def test_refit_in_place_equals_refit():
    rng = np.random.default_rng(3)
    lo = rng.normal(size=(300, 3))
    a, b = aabb.AABBTree.build(lo, lo + 0.1), aabb.AABBTree.build(lo, lo + 0.1)
    new_lo = lo + rng.normal(scale=0.3, size=lo.shape)
    a.refit(new_lo, new_lo + 0.05)
    b.lo[...], b.hi[...] = new_lo, new_lo + 0.05
    b.refit_in_place()
    np.testing.assert_array_equal(a.node_lo[:a.n_nodes], b.node_lo[:b.n_nodes])
    np.testing.assert_array_equal(a.node_hi[:a.n_nodes], b.node_hi[:b.n_nodes])


@pytest.mark.parametrize("reach", [0.0, 0.004])
def test_tool_query_boxes_equal_the_numpy_reference(reach):
    """The kernels' boxes, and the validating wrappers aabb.point_boxes / segment_boxes over them,
    are bit for bit the numpy code they replaced: the swept box inflated by the reach, for inside
    nodes also around the point their entry normal and depth lead back to."""
    rng = np.random.default_rng(5)
    k = 31
    tool0, tool1, tool2 = rng.normal(size=(k, 3)), rng.normal(size=(k, 3)), rng.normal(size=(k, 3))
    inside = (rng.uniform(size=k) < 0.3).astype(np.int8)
    normal, depth = rng.normal(size=(k, 3)), rng.uniform(0, 0.01, size=2 * k - 1)  # depth: nodes, then segments

    def inflated(lo, hi):
        return (lo - reach, hi + reach) if reach > 0 else (lo, hi)

    want_lo, want_hi = inflated(np.minimum(tool0, tool1), np.maximum(tool0, tool1))
    np.testing.assert_array_equal(aabb.point_boxes(tool0, positions_end=tool1, radius=reach), (want_lo, want_hi))
    np.testing.assert_array_equal(aabb.point_boxes(tool0, radius=reach), inflated(tool0, tool0))
    at = np.flatnonzero(inside)
    back = tool1[at] + normal[at] * depth[at, None]
    want_lo[at] = np.minimum(want_lo[at], back - reach)
    want_hi[at] = np.maximum(want_hi[at], back + reach)
    lo, hi = np.empty((k, 3)), np.empty((k, 3))
    aabb_kernels.swept_point_boxes(tool0, tool1, reach, inside, normal, depth, lo, hi)
    np.testing.assert_array_equal(lo, want_lo)
    np.testing.assert_array_equal(hi, want_hi)

    a, b, c, d = tool1[:-1], tool1[1:], tool2[:-1], tool2[1:]
    np.testing.assert_array_equal(aabb.segment_boxes(tool1, radius=reach),
                                  inflated(np.minimum(a, b), np.maximum(a, b)))
    np.testing.assert_array_equal(
        aabb.segment_boxes(tool1, positions_end=tool2, radius=reach),
        inflated(np.minimum(np.minimum(a, b), np.minimum(c, d)), np.maximum(np.maximum(a, b), np.maximum(c, d))))


def test_unsorted_query_finds_the_same_pairs():
    rng = np.random.default_rng(6)
    lo = rng.uniform(0, 1, size=(500, 3))
    tree = aabb.AABBTree.build(lo, lo + 0.05)
    q_lo = rng.uniform(0, 1, size=(40, 3))
    pairs = tree.query_boxes(q_lo, q_lo + 0.1, check=False, sort=False)
    assert pairs.shape[0] > 40
    np.testing.assert_array_equal(pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))], tree.query_boxes(q_lo, q_lo + 0.1))


def test_patch_slots_and_longest_row_equal_the_numpy_reference():
    rng = np.random.default_rng(7)
    ids = rng.permutation(200)[:12]
    local_vertices = np.sort(rng.permutation(200)[:60])
    slot = np.empty(60, np.int64)
    rendering_kernels.patch_slots(ids, local_vertices, slot)
    order = np.argsort(ids)  # the searchsorted version the kernel replaced
    at = np.minimum(np.searchsorted(ids[order], local_vertices), ids.size - 1)
    want = np.where(ids[order][at] == local_vertices, order[at], -1)
    np.testing.assert_array_equal(slot, want)
    assert (slot >= 0).sum() == np.isin(local_vertices, ids).sum()
    ptr = np.cumsum(np.concatenate([[0], rng.integers(0, 9, 30)]))
    assert rendering_kernels.longest_row(ptr) == np.diff(ptr).max()
    assert rendering_kernels.longest_row(np.zeros(1, np.int64)) == 0


def test_query_boxes_finds_every_overlap_however_many():
    """The query's buffer is sized by the query boxes and grows when they meet many primitives."""
    rng = np.random.default_rng(2)
    lo = rng.uniform(0, 1, size=(2000, 3))
    tree = aabb.AABBTree.build(lo, lo + 0.01)
    q_lo, q_hi = np.zeros((2, 3)), np.ones((2, 3))  # two boxes over everything: 4000 pairs
    pairs = tree.query_boxes(q_lo, q_hi, check=False)
    assert pairs.shape == (4000, 2)
    np.testing.assert_array_equal(pairs, tree.query_boxes(q_lo, q_hi))


def test_the_compliance_block_is_the_symmetric_part_of_the_named_slots():
    rng = np.random.default_rng(4)
    a = rng.normal(size=(15, 15))
    w = a @ a.T * 1e-4
    w += 1e-13 * rng.normal(size=w.shape)  # asymmetric within the tolerance
    nodes = np.array([7, -1, 3, 12, -1])
    ids, block, where = check_compliance(w, nodes, 100, 16)
    cols = (3 * where[:, None] + np.arange(3)).reshape(-1)
    b = w[np.ix_(cols, cols)]
    np.testing.assert_array_equal(ids, [7, 3, 12])
    np.testing.assert_array_equal(block, 0.5 * (b + b.T))
    with pytest.raises(rendering.ComplianceError, match="row 4, column 2"):
        w_bad = w.copy()
        w_bad[cols[4], cols[2]] = np.nan
        check_compliance(w_bad, nodes, 100, 16)


@pytest.mark.parametrize("ids, status", [([3, -1, 5], 0), ([3, -2], 1), ([3, 100], 1), ([1, 2, 3], 2),
                                         ([4, -1, 4], 3), ([], 0)])
def test_patch_id_status(ids, status):
    ids = np.asarray(ids, np.int64)
    assert rendering_kernels.patch_id_status(ids, 100, 2 if status == 2 else 16, np.empty(ids.size, np.int64)) == status
