"""Axis-aligned bounding-box (AABB) tree over simplices, in flat arrays (numba).

Layout (see docs/spatial.md). A binary tree over ``n`` elements (triangles or tetrahedra,
given as vertex coordinates ``points`` (nv, 3) and connectivity ``cells`` (n, k)):

* ``order`` (n,): element indices in tree order; every node covers a contiguous range
  ``order[start : start + count]``. ``cells_sorted = cells[order]`` and ``elem_box`` (n, 6)
  (lo xyz, hi xyz) are kept in the same order, so leaves read memory sequentially.
* Nodes are numbered in pre-order: the left child of internal node ``i`` is ``i + 1``, the
  right child is ``node_right[i]`` (``-1`` marks a leaf). Children therefore always have larger
  indices than their parent, and a refit is one reverse sweep over the node arrays.
* ``node_box`` (n_nodes, 6), ``node_start``, ``node_count`` (n_nodes,).

Build: top-down, split at the median of the box centres along the axis of greatest centre
extent (quickselect, O(n) per level), leaves of at most ``leaf_size`` elements.

Refit: element boxes from new vertex positions, then leaf and internal boxes bottom-up, O(n),
topology unchanged. Its quality is measured by the summed surface area of the internal node
boxes divided by the surface area of the root box (the expected number of internal nodes a
query visits, up to a constant: a box is entered with probability roughly proportional to its
area). Translation, uniform scaling and (nearly) rotation leave it unchanged; vertices drifting
away from their build-time neighbours inflate the inner boxes and raise it. A refitted tree
*needs a rebuild* when the ratio exceeds ``REBUILD_FACTOR`` times its value right after the
last build.

Queries: all (query box, element box) overlaps as flat pair arrays, with an optional margin that
inflates the query boxes; nearest triangle to points with exact point-triangle distance
(branch and bound, seeded with the previous point's answer, which makes spatially ordered
queries cheap).

Element boxes and the pair filters made of them are in `fenics_matdepth.geometry.boxes`.

Lengths are in the unit of ``points``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fenics_matdepth._constants import INDEX
from fenics_matdepth.geometry.boxes import as_points, element_box_rows, rows_overlap, share_vertex
from fenics_matdepth.geometry.distance import point_box_dist2, point_triangle_dist2

__all__ = [
    "LEAF_SIZE",
    "REBUILD_FACTOR",
    "AABBTree",
]

#: Maximum number of elements per leaf (few, since leaf tests are cheap and deep trees prune well).
LEAF_SIZE = 4

#: Rebuild when the refit quality ratio (summed internal-box area / root-box area) has grown by
#: this factor since the last build: queries then visit about that many times more nodes.
REBUILD_FACTOR = 2.0

#: Traversal stack depth; a median-split tree over 2**60 elements is 61 levels deep, and a
#: depth-first traversal holds at most one pending sibling per level plus the current node.
_STACK_SIZE = 256


# ------------------------------------------------------------------------------------------
# small helpers
# ------------------------------------------------------------------------------------------


@njit(inline="always")
def _box_area(b):
    """Surface area of box b = (lo xyz, hi xyz); well defined for flat boxes."""
    dx = b[3] - b[0]
    dy = b[4] - b[1]
    dz = b[5] - b[2]
    return 2.0 * (dx * dy + dy * dz + dz * dx)


@njit(inline="always")
def _push_pair(out_q, out_e, m, q, e):
    """Append (q, e) at position m, doubling the buffers when full; returns the buffers."""
    if m == out_q.shape[0]:
        cap = 2 * m
        new_q = np.empty(cap, dtype=np.int64)
        new_e = np.empty(cap, dtype=np.int64)
        new_q[:m] = out_q[:m]
        new_e[:m] = out_e[:m]
        out_q = new_q
        out_e = new_e
    out_q[m] = q
    out_e[m] = e
    return out_q, out_e


@njit(inline="always")
def _swap(order, cent, i, j):
    t = order[i]
    order[i] = order[j]
    order[j] = t
    for k in range(3):
        c = cent[i, k]
        cent[i, k] = cent[j, k]
        cent[j, k] = c


@njit(inline="always")
def _select(order, cent, lo, hi, nth, axis):
    """Partially sort order[lo:hi] (and cent rows with it) so position nth holds the median key.

    Quickselect with a median-of-three pivot and Hoare partitioning (equal keys stop both
    scans, so structured meshes with many equal centres stay O(n)).
    """
    left = lo
    right = hi - 1
    while right > left:
        mid = (left + right) // 2
        # median of three moved to `mid`
        if cent[mid, axis] < cent[left, axis]:
            _swap(order, cent, mid, left)
        if cent[right, axis] < cent[left, axis]:
            _swap(order, cent, right, left)
        if cent[right, axis] < cent[mid, axis]:
            _swap(order, cent, right, mid)
        pivot = cent[mid, axis]
        i = left
        j = right
        while i <= j:
            while cent[i, axis] < pivot:
                i += 1
            while cent[j, axis] > pivot:
                j -= 1
            if i <= j:
                _swap(order, cent, i, j)
                i += 1
                j -= 1
        if nth <= j:
            right = j
        elif nth >= i:
            left = i
        else:
            return


@njit(cache=True)
def _count_nodes(n, leaf_size):
    """Number of nodes of the median-split tree over n elements (its shape depends on n only)."""
    if n == 0:
        return 0
    stack = np.empty(_STACK_SIZE, dtype=np.int64)
    top = 0
    stack[top] = n
    top += 1
    total = 0
    while top > 0:
        top -= 1
        c = stack[top]
        total += 1
        if c > leaf_size:
            stack[top] = c // 2
            stack[top + 1] = c - c // 2
            top += 2
    return total


# ------------------------------------------------------------------------------------------
# build and refit
# ------------------------------------------------------------------------------------------


@njit(cache=True)
def _build(points, cells, leaf_size):
    """Build the tree topology (top-down median split) and its boxes.

    Returns:
        order, cells_sorted, node_start, node_count, node_right, elem_box, node_box,
        summed internal-box area, root-box area.
    """
    n = cells.shape[0]
    box = element_box_rows(points, cells)
    cent = np.empty((n, 3), dtype=points.dtype)
    for e in range(n):
        for d in range(3):
            cent[e, d] = 0.5 * (box[e, d] + box[e, d + 3])
    order = np.arange(n).astype(np.int64)
    n_nodes = _count_nodes(n, leaf_size)
    node_start = np.empty(n_nodes, dtype=np.int64)
    node_count = np.empty(n_nodes, dtype=np.int64)
    node_right = np.full(n_nodes, -1, dtype=np.int64)

    # Depth-first, right child pushed before left: pop order is pre-order, so the left child
    # of a node is always the next node; the right child patches its parent's pointer.
    st_start = np.empty(_STACK_SIZE, dtype=np.int64)
    st_count = np.empty(_STACK_SIZE, dtype=np.int64)
    st_parent = np.empty(_STACK_SIZE, dtype=np.int64)
    top = 0
    if n > 0:
        st_start[0] = 0
        st_count[0] = n
        st_parent[0] = -1
        top = 1
    node = 0
    while top > 0:
        top -= 1
        s = st_start[top]
        c = st_count[top]
        parent = st_parent[top]
        if parent >= 0:
            node_right[parent] = node
        node_start[node] = s
        node_count[node] = c
        if c > leaf_size:
            lo0 = np.inf
            lo1 = np.inf
            lo2 = np.inf
            hi0 = -np.inf
            hi1 = -np.inf
            hi2 = -np.inf
            for i in range(s, s + c):
                lo0 = min(lo0, cent[i, 0])
                lo1 = min(lo1, cent[i, 1])
                lo2 = min(lo2, cent[i, 2])
                hi0 = max(hi0, cent[i, 0])
                hi1 = max(hi1, cent[i, 1])
                hi2 = max(hi2, cent[i, 2])
            ex0 = hi0 - lo0
            ex1 = hi1 - lo1
            ex2 = hi2 - lo2
            axis = 0
            if ex1 > ex0 and ex1 >= ex2:
                axis = 1
            elif ex2 > ex0 and ex2 > ex1:
                axis = 2
            half = c // 2
            _select(order, cent, s, s + c, s + half, axis)
            # right child (parent pointer patched when popped), then left child on top
            st_start[top] = s + half
            st_count[top] = c - half
            st_parent[top] = node
            st_start[top + 1] = s
            st_count[top + 1] = half
            st_parent[top + 1] = -1
            top += 2
        node += 1

    cells_sorted = np.empty_like(cells)
    for i in range(n):
        cells_sorted[i] = cells[order[i]]
    elem_box = np.empty((n, 6), dtype=points.dtype)
    node_box = np.empty((n_nodes, 6), dtype=points.dtype)
    a_int, a_root = _refit(
        points, cells_sorted, node_start, node_count, node_right, elem_box, node_box
    )
    return (
        order,
        cells_sorted,
        node_start,
        node_count,
        node_right,
        elem_box,
        node_box,
        a_int,
        a_root,
    )


@njit(cache=True)
def _refit(points, cells_sorted, node_start, node_count, node_right, elem_box, node_box):
    """Recompute element and node boxes from new vertex positions, in place, O(n).

    Returns:
        (summed surface area of the internal node boxes, surface area of the root box).
    """
    n = cells_sorted.shape[0]
    k = cells_sorted.shape[1]
    for e in range(n):
        v = cells_sorted[e, 0]
        x0 = points[v, 0]
        y0 = points[v, 1]
        z0 = points[v, 2]
        x1 = x0
        y1 = y0
        z1 = z0
        for j in range(1, k):
            v = cells_sorted[e, j]
            x = points[v, 0]
            y = points[v, 1]
            z = points[v, 2]
            x0 = min(x0, x)
            y0 = min(y0, y)
            z0 = min(z0, z)
            x1 = max(x1, x)
            y1 = max(y1, y)
            z1 = max(z1, z)
        elem_box[e, 0] = x0
        elem_box[e, 1] = y0
        elem_box[e, 2] = z0
        elem_box[e, 3] = x1
        elem_box[e, 4] = y1
        elem_box[e, 5] = z1
    a_int = 0.0
    for i in range(node_start.shape[0] - 1, -1, -1):
        r = node_right[i]
        if r < 0:
            s = node_start[i]
            for d in range(6):
                node_box[i, d] = elem_box[s, d]
            for e in range(s + 1, s + node_count[i]):
                for d in range(3):
                    node_box[i, d] = min(node_box[i, d], elem_box[e, d])
                    node_box[i, d + 3] = max(node_box[i, d + 3], elem_box[e, d + 3])
        else:
            left = i + 1
            for d in range(3):
                node_box[i, d] = min(node_box[left, d], node_box[r, d])
                node_box[i, d + 3] = max(node_box[left, d + 3], node_box[r, d + 3])
            a_int += _box_area(node_box[i])
    a_root = _box_area(node_box[0]) if node_box.shape[0] > 0 else 0.0
    return a_int, a_root


# ------------------------------------------------------------------------------------------
# queries
# ------------------------------------------------------------------------------------------


@njit(cache=True)
def _query_boxes(
    qbox, margin, order, node_start, node_count, node_right, elem_box, node_box, qcells, ecells
):
    """All pairs (query box q, element e) whose boxes overlap (q inflated by ``margin``),
    leaving out those whose cells share a vertex where ``qcells`` has rows (one per query;
    ``ecells`` one per element, the same vertex numbering).

    Returns:
        (q (m,), e (m,)) int64, grouped by q in increasing order; e is the original element
        index.
    """
    nq = qbox.shape[0]
    apart = qcells.shape[0] > 0
    cap = max(16, 8 * nq)
    out_q = np.empty(cap, dtype=np.int64)
    out_e = np.empty(cap, dtype=np.int64)
    m = 0
    stack = np.empty(_STACK_SIZE, dtype=np.int64)
    if node_start.shape[0] == 0:
        return out_q[:0], out_e[:0]
    for q in range(nq):
        if not rows_overlap(qbox, q, node_box, 0, margin):
            continue
        stack[0] = 0
        top = 1
        while top > 0:
            top -= 1
            i = stack[top]
            r = node_right[i]
            if r < 0:
                s = node_start[i]
                for e in range(s, s + node_count[i]):
                    if rows_overlap(qbox, q, elem_box, e, margin):
                        k = order[e]
                        if apart and share_vertex(qcells, q, ecells, k):
                            continue
                        out_q, out_e = _push_pair(out_q, out_e, m, q, k)
                        m += 1
            else:
                # test children before pushing: halves the stack traffic
                if rows_overlap(qbox, q, node_box, r, margin):
                    stack[top] = r
                    top += 1
                if rows_overlap(qbox, q, node_box, i + 1, margin):
                    stack[top] = i + 1
                    top += 1
    return out_q[:m].copy(), out_e[:m].copy()


@njit(cache=True)
def _nearest_triangle(points, x, order, cells_sorted, node_start, node_count, node_right, node_box):
    """Nearest triangle (tree over triangles) to each point, with exact distance.

    Branch and bound: a node is skipped when its box is no nearer than the best triangle found
    so far; the nearer child is visited first. The best distance starts from the previous
    point's nearest triangle, a valid upper bound that is tight for spatially ordered points.

    Returns:
        (original triangle index (n,), squared distance (n,)); -1 and inf for an empty tree.
    """
    n = points.shape[0]
    idx = np.full(n, -1, dtype=np.int64)
    dist2 = np.full(n, np.inf, dtype=x.dtype)
    if node_start.shape[0] == 0:
        return idx, dist2
    stack = np.empty(_STACK_SIZE, dtype=np.int64)
    hint = 0  # tree position of the previous answer
    for p_i in range(n):
        p = points[p_i]
        best_k = hint
        best = point_triangle_dist2(
            p, x, cells_sorted[hint, 0], cells_sorted[hint, 1], cells_sorted[hint, 2]
        )
        stack[0] = 0
        top = 1
        while top > 0:
            top -= 1
            i = stack[top]
            if point_box_dist2(p, node_box[i, :3], node_box[i, 3:]) >= best:
                continue
            r = node_right[i]
            if r < 0:
                s = node_start[i]
                for e in range(s, s + node_count[i]):
                    d2 = point_triangle_dist2(
                        p, x, cells_sorted[e, 0], cells_sorted[e, 1], cells_sorted[e, 2]
                    )
                    if d2 < best:
                        best = d2
                        best_k = e
            else:
                dl = point_box_dist2(p, node_box[i + 1, :3], node_box[i + 1, 3:])
                dr = point_box_dist2(p, node_box[r, :3], node_box[r, 3:])
                # push the farther child first so the nearer one is explored first
                if dl <= dr:
                    if dr < best:
                        stack[top] = r
                        top += 1
                    if dl < best:
                        stack[top] = i + 1
                        top += 1
                else:
                    if dl < best:
                        stack[top] = i + 1
                        top += 1
                    if dr < best:
                        stack[top] = r
                        top += 1
        idx[p_i] = order[best_k]
        dist2[p_i] = best
        hint = best_k
    return idx, dist2


# ------------------------------------------------------------------------------------------
# Python API
# ------------------------------------------------------------------------------------------


class AABBTree:
    """AABB tree over triangles or tetrahedra (flat arrays, numba kernels).

    Args:
        points: (nv, 3) vertex coordinates (L).
        cells: (n, k) vertex indices of the elements (k = 3 triangles, k = 4 tetrahedra).
        leaf_size: maximum number of elements per leaf.

    Example:
        >>> tree = AABBTree(x, tets)
        >>> tree.refit(x + u)
        >>> if tree.needs_rebuild():
        ...     tree.rebuild()
        >>> q, e = tree.query_boxes(*element_boxes(x + u, triangles), margin=h / 10)
    """

    def __init__(self, points: np.ndarray, cells: np.ndarray, leaf_size: int = LEAF_SIZE):
        cells = np.ascontiguousarray(cells, dtype=INDEX)
        if cells.ndim != 2 or cells.shape[1] < 1:
            raise ValueError(f"cells must have shape (n, k), got {cells.shape}")
        if leaf_size < 1:
            raise ValueError(f"leaf_size must be >= 1, got {leaf_size}")
        self._cells = cells
        self.leaf_size = int(leaf_size)
        self.rebuild(points)

    # -- construction -------------------------------------------------------------------

    def rebuild(self, points: np.ndarray | None = None) -> None:
        """Rebuild the tree topology from scratch (at ``points``, default: the last positions).

        Args:
            points: (nv, 3) vertex coordinates (L), or None to reuse the last ones.
        """
        if points is not None:
            self._points = as_points(points)
        p = self._points
        if self._cells.size and (self._cells.min() < 0 or self._cells.max() >= p.shape[0]):
            raise ValueError("cells reference vertices outside points")
        (
            self._order,
            self._cells_sorted,
            self._node_start,
            self._node_count,
            self._node_right,
            self._elem_box,
            self._node_box,
            a_int,
            a_root,
        ) = _build(p, self._cells, self.leaf_size)
        self._quality_at_build = self._ratio(a_int, a_root)
        self._quality = self._quality_at_build

    def refit(self, points: np.ndarray) -> None:
        """Recompute all boxes at new vertex positions, keeping the topology (O(n)).

        Args:
            points: (nv, 3) vertex coordinates (L), same numbering as at construction.
        """
        p = as_points(points)
        if p.shape[0] != self._points.shape[0]:
            raise ValueError(
                f"refit got {p.shape[0]} points, the tree was built over {self._points.shape[0]}"
            )
        self._points = p
        a_int, a_root = _refit(
            p,
            self._cells_sorted,
            self._node_start,
            self._node_count,
            self._node_right,
            self._elem_box,
            self._node_box,
        )
        self._quality = self._ratio(a_int, a_root)

    @staticmethod
    def _ratio(a_int: float, a_root: float) -> float:
        return a_int / a_root if a_root > 0.0 else 0.0

    @property
    def quality(self) -> float:
        """Current summed internal-box area / root-box area (lower is better)."""
        return self._quality

    @property
    def quality_growth(self) -> float:
        """Current quality ratio divided by its value right after the last build."""
        if self._quality_at_build <= 0.0:
            return 1.0
        return self._quality / self._quality_at_build

    def needs_rebuild(self, factor: float = REBUILD_FACTOR) -> bool:
        """True when refits have degraded the tree by more than ``factor`` (see module doc)."""
        return self.quality_growth > factor

    # -- sizes ----------------------------------------------------------------------------

    @property
    def num_elements(self) -> int:
        """Number of elements in the tree."""
        return self._cells.shape[0]

    @property
    def num_nodes(self) -> int:
        """Number of tree nodes."""
        return self._node_start.shape[0]

    @property
    def points(self) -> np.ndarray:
        """Vertex coordinates of the last build or refit (L)."""
        return self._points

    @property
    def order(self) -> np.ndarray:
        """(n,) the element indices in tree order (read-only; a rebuild changes it). A query
        lists each query box's elements in this order."""
        view = self._order.view()
        view.flags.writeable = False
        return view

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) corners of the root box (L)."""
        if self.num_nodes == 0:
            return np.full(3, np.inf), np.full(3, -np.inf)
        return self._node_box[0, :3].copy(), self._node_box[0, 3:].copy()

    # -- queries --------------------------------------------------------------------------

    def query_boxes(
        self,
        lo: np.ndarray,
        hi: np.ndarray,
        margin: float = 0.0,
        apart: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """All (query box, element) pairs whose boxes overlap.

        Boxes are closed: touching boxes overlap. Each query box is inflated by ``margin`` on
        every side first (use it to catch pairs that come into contact within a step).

        Args:
            lo: (nq, 3) lower query-box corners (L).
            hi: (nq, 3) upper query-box corners (L).
            margin: inflation of the query boxes (L), >= 0.
            apart: (query cells (nq, a), element cells (ne, b)), vertex indices in one
                numbering: the pairs whose cells share a vertex are left out as they are found,
                the others kept in order (what
                :func:`~fenics_matdepth.geometry.boxes.exclude_shared_vertex_pairs` keeps of
                the whole answer, without writing the pairs it drops: on the knee a third of
                the 527k a search finds).

        Returns:
            (query index (m,), element index (m,)), int64, grouped by query index.
        """
        lo = as_points(lo)
        hi = as_points(hi)
        if lo.shape != hi.shape:
            raise ValueError(f"lo {lo.shape} and hi {hi.shape} differ in shape")
        if margin < 0.0:
            raise ValueError(f"margin must be >= 0, got {margin}")
        qbox = np.ascontiguousarray(np.hstack((lo, hi)))
        if apart is None:
            qcells = ecells = np.empty((0, 1), dtype=INDEX)
        else:
            qcells, ecells = (np.ascontiguousarray(c, dtype=INDEX) for c in apart)
            if qcells.shape[0] != qbox.shape[0] or ecells.shape[0] != self._order.shape[0]:
                raise ValueError(
                    f"apart needs a cell per query box ({qbox.shape[0]}) and per element "
                    f"({self._order.shape[0]}), got {qcells.shape[0]} and {ecells.shape[0]}"
                )
        return _query_boxes(
            qbox,
            float(margin),
            self._order,
            self._node_start,
            self._node_count,
            self._node_right,
            self._elem_box,
            self._node_box,
            qcells,
            ecells,
        )

    def nearest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest triangle to each point, with the exact point-triangle distance.

        Args:
            points: (n, 3) query points (L). Spatially ordered points are answered faster.

        Returns:
            (triangle index (n,), distance (n,) in L); -1 and inf for an empty tree.

        Raises:
            TypeError: if the tree is not over triangles.
        """
        idx, d2 = self.nearest_squared(points)
        return idx, np.sqrt(d2)

    def nearest_squared(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`nearest`, returning squared distances (L^2)."""
        if self._cells.shape[1] != 3:
            raise TypeError(
                f"nearest() needs a tree over triangles (3 vertices per cell), this one has "
                f"{self._cells.shape[1]}: build an AABBTree over the boundary triangles"
            )
        return _nearest_triangle(
            as_points(points),
            self._points,
            self._order,
            self._cells_sorted,
            self._node_start,
            self._node_count,
            self._node_right,
            self._node_box,
        )
