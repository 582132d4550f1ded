"""Numba kernels of the axis-aligned bounding-box (AABB) tree used as CCD broad phase.

Flat layout (no objects, numba-friendly): node arrays `node_lo`, `node_hi` (n_nodes, 3), `left`,
`right` (child ids, -1 for a leaf), `start`, `count` (a leaf holds primitives
order[start:start+count]). Nodes are created breadth-first, so every child id is larger than its
parent's: a reverse sweep over the node ids is a valid bottom-up order for refitting.
Boxes are closed: two boxes overlap when lo_a <= hi_b and lo_b <= hi_a on every axis.
"""
import numpy as np
from numba import njit

# Median splits give depth <= ceil(log2(m)) + 1 <= 65 for any m < 2**63; a pairwise traversal
# stack grows by at most one entry per level of each tree.
STACK_SIZE = 256


@njit(cache=True)
def build_tree(lo, hi, leaf_size, order, node_lo, node_hi, left, right, start, count):
    """Top-down median split on the widest centroid axis, then the node boxes by `refit_tree`.
    Arrays sized for 2m nodes; returns n_nodes."""
    m = lo.shape[0]
    for i in range(m):
        order[i] = i
    start[0] = 0
    count[0] = m
    n_nodes = 1
    node = 0
    keys = np.empty(m)
    tmp = np.empty(m, dtype=np.int64)
    while node < n_nodes:
        s = start[node]
        c = count[node]
        if c <= leaf_size:
            left[node] = -1
            right[node] = -1
            node += 1
            continue
        # widest axis of the primitive centres (sums, not means: same ordering, one rounding less)
        best_axis = 0
        best_extent = -1.0
        for a in range(3):
            c_lo = np.inf
            c_hi = -np.inf
            for k in range(s, s + c):
                x = lo[order[k], a] + hi[order[k], a]
                c_lo = min(c_lo, x)
                c_hi = max(c_hi, x)
            if c_hi - c_lo > best_extent:
                best_extent = c_hi - c_lo
                best_axis = a
        for k in range(c):
            p = order[s + k]
            keys[k] = lo[p, best_axis] + hi[p, best_axis]
        perm = np.argsort(keys[:c], kind="mergesort")
        for k in range(c):
            tmp[k] = order[s + perm[k]]
        for k in range(c):
            order[s + k] = tmp[k]
        half = c // 2
        left[node] = n_nodes
        right[node] = n_nodes + 1
        start[n_nodes] = s
        count[n_nodes] = half
        start[n_nodes + 1] = s + half
        count[n_nodes + 1] = c - half
        n_nodes += 2
        node += 1
    refit_tree(lo, hi, order, n_nodes, node_lo, node_hi, left, right, start, count)  # the boxes, bottom-up
    return n_nodes


@njit(cache=True)
def refit_tree(lo, hi, order, n_nodes, node_lo, node_hi, left, right, start, count):
    """Recompute node boxes bottom-up for new primitive boxes, same topology: O(m).

    Boxes are finite (the callers validate them), so plain comparisons stand for min and max:
    each node's box is built in registers and written once (faster than updating it in place entry
    by entry; this runs at every tissue frame inside the 1 kHz loop)."""
    for node in range(n_nodes - 1, -1, -1):
        l = left[node]
        if l < 0:  # a leaf (the root of an empty tree has no primitives: an empty box)
            x0 = x1 = x2 = np.inf
            y0 = y1 = y2 = -np.inf
            for k in range(start[node], start[node] + count[node]):
                p = order[k]
                x0 = x0 if x0 < lo[p, 0] else lo[p, 0]
                x1 = x1 if x1 < lo[p, 1] else lo[p, 1]
                x2 = x2 if x2 < lo[p, 2] else lo[p, 2]
                y0 = y0 if y0 > hi[p, 0] else hi[p, 0]
                y1 = y1 if y1 > hi[p, 1] else hi[p, 1]
                y2 = y2 if y2 > hi[p, 2] else hi[p, 2]
        else:
            r = right[node]
            x0 = node_lo[l, 0] if node_lo[l, 0] < node_lo[r, 0] else node_lo[r, 0]
            x1 = node_lo[l, 1] if node_lo[l, 1] < node_lo[r, 1] else node_lo[r, 1]
            x2 = node_lo[l, 2] if node_lo[l, 2] < node_lo[r, 2] else node_lo[r, 2]
            y0 = node_hi[l, 0] if node_hi[l, 0] > node_hi[r, 0] else node_hi[r, 0]
            y1 = node_hi[l, 1] if node_hi[l, 1] > node_hi[r, 1] else node_hi[r, 1]
            y2 = node_hi[l, 2] if node_hi[l, 2] > node_hi[r, 2] else node_hi[r, 2]
        node_lo[node, 0], node_lo[node, 1], node_lo[node, 2] = x0, x1, x2
        node_hi[node, 0], node_hi[node, 1], node_hi[node, 2] = y0, y1, y2


@njit(cache=True)
def _overlap(alo, ahi, i, blo, bhi, j):
    for a in range(3):
        if alo[i, a] > bhi[j, a] or blo[j, a] > ahi[i, a]:
            return False
    return True


@njit(cache=True)
def query_tree_tree(a_lo, a_hi, a_order, a_node_lo, a_node_hi, a_left, a_right, a_start, a_count,
                    b_lo, b_hi, b_order, b_node_lo, b_node_hi, b_left, b_right, b_start, b_count, out):
    """Primitive pairs (i of a, j of b) with overlapping boxes, by simultaneous descent.

    Writes up to out.shape[0] pairs; returns the total count (rerun with a larger out if bigger).
    """
    capacity = out.shape[0]
    found = 0
    stack = np.empty((STACK_SIZE, 2), dtype=np.int64)
    stack[0, 0] = 0
    stack[0, 1] = 0
    top = 1
    while top > 0:
        top -= 1
        na = stack[top, 0]
        nb = stack[top, 1]
        if not _overlap(a_node_lo, a_node_hi, na, b_node_lo, b_node_hi, nb):
            continue
        a_leaf = a_left[na] < 0
        b_leaf = b_left[nb] < 0
        if a_leaf and b_leaf:
            for ka in range(a_start[na], a_start[na] + a_count[na]):
                i = a_order[ka]
                for kb in range(b_start[nb], b_start[nb] + b_count[nb]):
                    j = b_order[kb]
                    if _overlap(a_lo, a_hi, i, b_lo, b_hi, j):
                        if found < capacity:
                            out[found, 0] = i
                            out[found, 1] = j
                        found += 1
        elif b_leaf or (not a_leaf and a_count[na] >= b_count[nb]):
            # descend the larger (or the only inner) node
            stack[top, 0] = a_left[na]
            stack[top, 1] = nb
            stack[top + 1, 0] = a_right[na]
            stack[top + 1, 1] = nb
            top += 2
        else:
            stack[top, 0] = na
            stack[top, 1] = b_left[nb]
            stack[top + 1, 0] = na
            stack[top + 1, 1] = b_right[nb]
            top += 2
    return found


@njit(cache=True)
def query_tree_boxes(lo, hi, order, node_lo, node_hi, left, right, start, count, q_lo, q_hi, out):
    """Pairs (primitive i of the tree, query box j) with overlapping boxes; returns the total count."""
    capacity = out.shape[0]
    found = 0
    stack = np.empty(STACK_SIZE, dtype=np.int64)
    for j in range(q_lo.shape[0]):
        stack[0] = 0
        top = 1
        while top > 0:
            top -= 1
            node = stack[top]
            if not _overlap(node_lo, node_hi, node, q_lo, q_hi, j):
                continue
            if left[node] < 0:
                for k in range(start[node], start[node] + count[node]):
                    i = order[k]
                    if _overlap(lo, hi, i, q_lo, q_hi, j):
                        if found < capacity:
                            out[found, 0] = i
                            out[found, 1] = j
                        found += 1
            else:
                stack[top] = left[node]
                stack[top + 1] = right[node]
                top += 2
    return found


@njit(cache=True)
def triangle_boxes(pos, end, use_end, tri, lo, hi):
    """Boxes of the triangles over pos (and end, when use_end: the box of both) into lo, hi (t,3)."""
    for f in range(tri.shape[0]):
        for d in range(3):
            mn = pos[tri[f, 0], d]
            mx = mn
            for j in range(3):
                x = pos[tri[f, j], d]
                mn = min(mn, x)
                mx = max(mx, x)
                if use_end:
                    x = end[tri[f, j], d]
                    mn = min(mn, x)
                    mx = max(mx, x)
            lo[f, d] = mn
            hi[f, d] = mx


@njit(cache=True)
def swept_point_boxes(p0, p1, reach, covers, back_dir, back_len, lo, hi):
    """Boxes of points swept from p0 to p1 (k,3), inflated by reach (when > 0), into lo, hi (k,3);
    where covers[i] != 0 the box also covers p1[i] + back_dir[i] * back_len[i] (reach around it).
    The contact model's tool-node query boxes: a node inside the tissue reaches back along its
    entry normal by its depth, so the faces it entered through stay in the local model."""
    for i in range(p0.shape[0]):
        for a in range(3):
            mn = min(p0[i, a], p1[i, a])
            mx = max(p0[i, a], p1[i, a])
            if reach > 0.0:
                mn = mn - reach
                mx = mx + reach
            if covers[i] != 0:
                back = p1[i, a] + back_dir[i, a] * back_len[i]
                mn = min(mn, back - reach)
                mx = max(mx, back + reach)
            lo[i, a] = mn
            hi[i, a] = mx


@njit(cache=True)
def polyline_segment_boxes(points, reach, lo, hi):
    """Boxes of the k-1 segments of a polyline points (k,3), inflated by reach (when > 0), into
    lo, hi (k-1,3)."""
    for i in range(points.shape[0] - 1):
        for a in range(3):
            mn = min(points[i, a], points[i + 1, a])
            mx = max(points[i, a], points[i + 1, a])
            if reach > 0.0:
                mn = mn - reach
                mx = mx + reach
            lo[i, a] = mn
            hi[i, a] = mx
