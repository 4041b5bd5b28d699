"""Binary search tree over the regions of a piecewise-affine law (Tøndel, Johansen, Bemporad,
"Evaluation of piecewise affine control via binary search tree", Automatica 2003).

Each internal node holds one hyperplane a'p = b taken from the region facets (the facets on
the parameter box are not used: the box is checked before the descent); the point goes left
when a'p <= b, right otherwise. Each node stands for a polyhedral cell (the box cut by the
hyperplanes on its path) and the set I of regions whose interior meets that cell. A node
becomes a leaf as soon as every region of I has the same law (the leaf stores that law's
index) or I is empty (the leaf says "no region": a gap in the partition). A partition that
is not known to cover the box is split further at single-law nodes until each leaf cell lies
inside a region or meets none, so gaps are found, not filled with a neighbour's law.

Choice of the hyperplane at a node, as in the paper: minimise the larger of the two child
sets, then their sum; the sets are counted first in distinct laws (the paper's index sets of
affine functions: regions sharing a law need no separating), then in regions. Which child a
region belongs to is exact only inside the cell: a table, computed once, says on which side of
each hyperplane every region lies in the whole box (Chebyshev ball, bounding box, else LPs),
which bounds every candidate's score from above (regions cut somewhere count on both sides)
and from below (they count on neither). Candidates are scored exactly (one LP per region the
hyperplane cuts: does it reach the cell on that side?) in the order of their upper bounds,
skipping those whose lower bound cannot win, until ``candidates_per_node`` have been scored.
A hyperplane is used at most once on a path, so the tree is finite; its depth is the number
of hyperplane tests on the longest path.

:class:`SequentialSearch` is the flat alternative (test the regions one after the other) the
tree is verified and benchmarked against. Both return a law index, ``NOT_FOUND`` (-1) or
``OUTSIDE_BOX`` (-2).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hil.controllers.errors import SolverError
from hil.controllers.servo.mpqp import LinearProgram

NOT_FOUND = -1
OUTSIDE_BOX = -2
BOX_TOL = 1e-9  # relative to the box half-width
_PLANE_TOL = 1e-8  # two facets are the same hyperplane within this (unit normals, normalised box)
_INTERIOR_TOL = 1e-7  # a region meets a cell when a ball this large fits in both


@dataclass(frozen=True)
class Polyhedron:
    """{p : A p <= b}; ``boundary`` flags rows that are facets of the parameter box."""

    A: np.ndarray
    b: np.ndarray
    boundary: np.ndarray


class _Box:
    """p = centre + half_width * t with t in [-1, 1]^n."""

    def __init__(self, lower: np.ndarray, upper: np.ndarray) -> None:
        self.lower = np.asarray(lower, float)
        self.upper = np.asarray(upper, float)
        self.centre = 0.5 * (self.upper + self.lower)
        self.half = 0.5 * (self.upper - self.lower)

    def contains(self, p: np.ndarray) -> bool:
        slack = BOX_TOL * self.half
        return bool(np.all(p >= self.lower - slack) and np.all(p <= self.upper + slack))

    def to_t(self, A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Half-spaces A p <= b as unit-norm rows in t."""
        At = A * self.half[None, :]
        bt = b - A @ self.centre
        norms = np.linalg.norm(At, axis=1)
        return At / norms[:, None], bt / norms

    def to_p(self, At: np.ndarray, bt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        A = At / self.half[None, :]
        return A, bt + A @ self.centre


@dataclass(frozen=True)
class SearchTree:
    """The tree as flat arrays (what the C export writes out).

    Node 0 is the root. ``plane[n]`` is the hyperplane index of node n (-1 for a leaf),
    ``left``/``right`` its children (a'p <= b goes left), ``label[n]`` the law index of a
    leaf (NOT_FOUND when the leaf is a hole). Hyperplanes: ``A p <= b`` rows in the
    caller's coordinates.
    """

    A: np.ndarray
    b: np.ndarray
    plane: np.ndarray
    left: np.ndarray
    right: np.ndarray
    label: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    build_s: float
    lps: int

    @property
    def nodes(self) -> int:
        return int(self.plane.size)

    @property
    def leaves(self) -> int:
        return int(np.count_nonzero(self.plane < 0))

    @property
    def depth(self) -> int:
        """Hyperplane tests on the longest root-to-leaf path."""
        depth = np.zeros(self.nodes, dtype=int)
        for n in range(self.nodes):  # children always come after their parent
            if self.plane[n] >= 0:
                depth[self.left[n]] = depth[self.right[n]] = depth[n] + 1
        return int(depth.max())

    @property
    def planes_used(self) -> int:
        return int(np.unique(self.plane[self.plane >= 0]).size)

    def evaluator(self) -> TreeEvaluator:
        return TreeEvaluator(self)


class TreeEvaluator:
    """Fast Python descent: the box, every hyperplane and (optionally) every law in one
    matrix product, then the walk over plain lists (numpy indexing per node would cost more
    than the whole walk).

    ``gains``/``offsets``: one affine law per label (rows); :meth:`law` then returns the
    law's value at the point as well.
    """

    def __init__(self, tree: SearchTree, gains: np.ndarray | None = None,
                 offsets: np.ndarray | None = None) -> None:
        n = tree.lower.size
        slack = BOX_TOL * 0.5 * (tree.upper - tree.lower)
        laws = np.zeros((0, n)) if gains is None else np.asarray(gains, float)
        self._M = np.ascontiguousarray(np.vstack([tree.A, np.eye(n), -np.eye(n), laws]))
        self._c = np.concatenate([tree.b, tree.upper + slack, -(tree.lower - slack)])
        self._tests = self._c.size
        self._planes = tree.b.size
        self._offsets = [] if offsets is None else np.asarray(offsets, float).tolist()
        self._plane = tree.plane.tolist()
        self._left = tree.left.tolist()
        self._right = tree.right.tolist()
        self._label = tree.label.tolist()

    def _descend(self, values: np.ndarray) -> int:
        below = (values[: self._tests] <= self._c).tolist()  # NaN compares False: outside
        if not all(below[self._planes:]):
            return OUTSIDE_BOX
        plane, left, right = self._plane, self._left, self._right
        node = 0
        j = plane[0]
        while j >= 0:
            node = left[node] if below[j] else right[node]
            j = plane[node]
        return self._label[node]

    def __call__(self, p: np.ndarray) -> int:
        """Law index at ``p``, NOT_FOUND, or OUTSIDE_BOX (also for NaN)."""
        return self._descend(self._M @ p)

    def law(self, p: np.ndarray) -> tuple[int, float]:
        """(law index, its value at ``p``), or (NOT_FOUND / OUTSIDE_BOX, nan)."""
        values = self._M @ p
        code = self._descend(values)
        if code < 0:
            return code, float("nan")
        return code, float(values[self._tests + code]) + self._offsets[code]


class SequentialSearch:
    """The regions tested one after the other (first region containing the point wins),
    written as one stacked matrix product and a per-region reduction."""

    def __init__(self, regions: Sequence[Polyhedron], labels: Sequence[int],
                 lower: np.ndarray, upper: np.ndarray, tol: float = 1e-9) -> None:
        self._A = np.vstack([r.A for r in regions])
        self._b = np.concatenate([r.b for r in regions]) + tol
        sizes = [r.A.shape[0] for r in regions]
        self._starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        self._labels = np.asarray(labels)
        self._box = _Box(lower, upper)

    def __call__(self, p: np.ndarray) -> int:
        if not self._box.contains(p):
            return OUTSIDE_BOX
        inside = np.logical_and.reduceat(self._A @ p <= self._b, self._starts)
        hits = np.flatnonzero(inside)
        return int(self._labels[hits[0]]) if hits.size else NOT_FOUND


class _Builder:
    def __init__(self, regions: Sequence[Polyhedron], labels: Sequence[int] | np.ndarray,
                 box: _Box, covered: bool) -> None:
        self.box = box
        self.covered = covered
        self.labels = np.asarray(labels, dtype=int)
        self.lp = LinearProgram()
        self.regions_t: list[tuple[np.ndarray, np.ndarray]] = []
        planes: list[np.ndarray] = []  # rows [a_t, b_t]
        self.facets: list[dict[int, int]] = []  # region -> {plane: side}
        for region in regions:
            At, bt = box.to_t(region.A, region.b)
            self.regions_t.append((At, bt))
            sides: dict[int, int] = {}
            for a, b in zip(At[~region.boundary], bt[~region.boundary], strict=True):
                j, flipped = self._plane_index(planes, a, b)
                sides[j] = 1 if flipped else -1
            self.facets.append(sides)
        self.planes = np.array(planes).reshape(-1, box.half.size + 1)
        self.sign = self._sign_table()

    @staticmethod
    def _plane_index(planes: list[np.ndarray], a: np.ndarray, b: float) -> tuple[int, bool]:
        """Index of the hyperplane a't = b (added if new); True if stored with flipped sign."""
        lead = np.flatnonzero(np.abs(a) > 1e-6)[0]
        flipped = a[lead] < 0
        row = -np.append(a, b) if flipped else np.append(a, b)
        if planes:
            dist = np.abs(np.asarray(planes) - row).max(axis=1)
            j = int(np.argmin(dist))
            if dist[j] <= _PLANE_TOL:
                return j, bool(flipped)
        planes.append(row)
        return len(planes) - 1, bool(flipped)

    def _sign_table(self) -> np.ndarray:
        """sign[j, i]: -1 region i lies in a_j't <= b_j, +1 in >=, 0 cut by hyperplane j.
        Facets are known; a hyperplane through the Chebyshev ball cuts the region; the
        region's bounding box puts it on one side; otherwise LPs decide."""
        n_planes, n = self.planes.shape[0], self.box.half.size
        sign = np.zeros((n_planes, len(self.regions_t)), dtype=int)
        A_pl, b_pl = self.planes[:, :n], self.planes[:, n]
        eye = np.eye(n)
        for i, (At, bt) in enumerate(self.regions_t):
            centre, radius = self.lp.chebyshev(At, bt)
            bounds = self.lp.minima(At, bt, np.vstack([eye, -eye]))
            if bounds is None or radius <= 0:
                raise SolverError("empc tree: a region is empty (inconsistent partition)")
            lo, hi = bounds[:n], -bounds[n:]
            mid = A_pl @ (0.5 * (hi + lo)) - b_pl
            reach = np.abs(A_pl) @ (0.5 * (hi - lo))
            sign[mid + reach <= 0, i] = -1
            sign[mid - reach >= 0, i] = 1
            at_centre = A_pl @ centre - b_pl
            undecided = (mid + reach > 0) & (mid - reach < 0) & (np.abs(at_centre) >= radius)
            undecided[list(self.facets[i])] = False
            rows = np.flatnonzero(undecided)
            if rows.size:
                ext = self.lp.minima(At, bt, np.vstack([A_pl[rows], -A_pl[rows]]))
                if ext is None:
                    raise SolverError("empc tree: a region is empty (inconsistent partition)")
                low, high = ext[: rows.size], -ext[rows.size:]
                sign[rows, i] = np.where(high <= b_pl[rows] + _INTERIOR_TOL, -1, np.where(
                    low >= b_pl[rows] - _INTERIOR_TOL, 1, 0))
            for j, side in self.facets[i].items():
                sign[j, i] = side
        return sign

    def _meets(self, i: int, cell_A: np.ndarray, cell_b: np.ndarray) -> bool:
        """Does region i have interior points in the cell?"""
        At, bt = self.regions_t[i]
        _, radius = self.lp.chebyshev(np.vstack([At, cell_A]), np.concatenate([bt, cell_b]))
        return radius > _INTERIOR_TOL

    def _split(self, j: int, members: np.ndarray, cell_A: np.ndarray,
               cell_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact (left, right) member sets of hyperplane j inside the cell."""
        n = self.box.half.size
        a, b = self.planes[j, :n], self.planes[j, n]
        left, right = [], []
        for i in members:
            s = self.sign[j, i]
            if s <= 0 and (s < 0 or self._meets(i, np.vstack([cell_A, a]),
                                                np.append(cell_b, b))):
                left.append(i)
            if s >= 0 and (s > 0 or self._meets(i, np.vstack([cell_A, -a]),
                                                np.append(cell_b, -b))):
                right.append(i)
        return np.array(left, dtype=int), np.array(right, dtype=int)

    @staticmethod
    def _score(left: np.ndarray, right: np.ndarray, onehot: np.ndarray) -> np.ndarray:
        """Per candidate (rows of the member masks): (max, sum) of the distinct laws on the
        two sides, then (max, sum) of the regions."""
        laws_l = (left.astype(int) @ onehot > 0).sum(axis=1)
        laws_r = (right.astype(int) @ onehot > 0).sum(axis=1)
        n_l, n_r = left.sum(axis=1), right.sum(axis=1)
        return np.stack([np.maximum(laws_l, laws_r), laws_l + laws_r,
                         np.maximum(n_l, n_r), n_l + n_r], axis=1)

    def build(self, candidates_per_node: int) -> tuple[list[int], list[int], list[int],
                                                        list[int]]:
        n = self.box.half.size
        plane: list[int] = []
        left: list[int] = []
        right: list[int] = []
        label: list[int] = []
        # Breadth-first, so children always have larger indices than their parent.
        queue: list[tuple[np.ndarray, np.ndarray, np.ndarray, frozenset[int]]] = [
            (np.arange(len(self.regions_t)), np.zeros((0, n)), np.zeros(0), frozenset())]
        head = 0
        while head < len(queue):
            members, cell_A, cell_b, used = queue[head]
            head += 1
            plane.append(-1)
            left.append(-1)
            right.append(-1)
            label.append(NOT_FOUND)
            node = len(plane) - 1
            laws = np.unique(self.labels[members])
            if laws.size <= 1:
                # One law left: a leaf, unless the cell may reach a gap between the regions
                # (then a facet of a member cuts the cell and carves the gap off).
                choice = None if self.covered else self._carve(members, cell_A, cell_b, used)
                if choice is None:
                    label[node] = int(laws[0]) if laws.size else NOT_FOUND
                    continue
            else:
                choice = self._choose(members, cell_A, cell_b, used, candidates_per_node)
            if choice is None:
                raise SolverError(f"empc tree: regions with laws {laws.tolist()} cannot be "
                               "separated by their facets (degenerate partition)")
            j, members_left, members_right = choice
            plane[node] = j
            a, b = self.planes[j, :n], self.planes[j, n]
            left[node] = len(queue)
            queue.append((members_left, np.vstack([cell_A, a]), np.append(cell_b, b),
                          used | {j}))
            right[node] = len(queue)
            queue.append((members_right, np.vstack([cell_A, -a]), np.append(cell_b, -b),
                          used | {j}))
        return plane, left, right, label

    def _carve(self, members: np.ndarray, cell_A: np.ndarray, cell_b: np.ndarray,
               used: frozenset[int]) -> tuple[int, np.ndarray, np.ndarray] | None:
        """A facet of a member region that cuts the cell (None: every member contains it)."""
        n = self.box.half.size
        for i in members:
            for j, side in self.facets[i].items():
                if j in used:
                    continue
                a, b = self.planes[j, :n] * side, self.planes[j, n] * side
                # Region i lies in a't <= b: is there cell beyond the facet?
                _, radius = self.lp.chebyshev(np.vstack([cell_A, -a]), np.append(cell_b, -b))
                if radius > _INTERIOR_TOL:
                    return (j, *self._split(j, members, cell_A, cell_b))
        return None

    def _choose(self, members: np.ndarray, cell_A: np.ndarray, cell_b: np.ndarray,
                used: frozenset[int], candidates_per_node: int,
                ) -> tuple[int, np.ndarray, np.ndarray] | None:
        """The hyperplane minimising (max, sum) of the child set sizes (Tøndel et al.)."""
        planes = sorted({j for i in members for j in self.facets[i]} - used)
        if not planes:
            return None
        sign = self.sign[np.ix_(planes, members)]
        onehot = self.labels[members][:, None] == np.unique(self.labels[members])[None, :]
        # Bounds on each candidate's score inside the cell: the regions cut by a hyperplane
        # somewhere in the box may or may not reach its sides within the cell.
        upper = self._score(sign <= 0, sign >= 0, onehot)
        lower = self._score(sign < 0, sign > 0, onehot)
        best, best_score, tried = None, None, 0
        size = members.size
        for pos in np.lexsort(upper.T[::-1]):
            if best_score is not None and tuple(lower[pos]) >= best_score:
                continue
            j = planes[pos]
            sides = self._split(j, members, cell_A, cell_b)
            if (sides[0].size == size and sides[1].size == size) or 0 in (sides[0].size,
                                                                          sides[1].size):
                continue  # cuts no region inside this cell, or misses the cell
            score = tuple(self._score(np.isin(members, sides[0])[None, :],
                                      np.isin(members, sides[1])[None, :], onehot)[0])
            if best_score is None or score < best_score:
                best, best_score = (j, *sides), score
            tried += 1
            if tried >= candidates_per_node:
                break
        return best


def build_tree(regions: Sequence[Polyhedron], labels: Sequence[int] | np.ndarray,
               lower: np.ndarray,
               upper: np.ndarray, covered: bool = False,
               candidates_per_node: int = 4) -> SearchTree:
    """The search tree of regions (with their law labels) in the box.

    ``covered``: the caller knows that the regions cover the box (e.g.
    :attr:`~hil.controllers.servo.mpqp.MpqpSolution.covers_box`); a node whose regions share one law
    is then a leaf. Otherwise such a node is split further by the regions' facets until its
    cell lies inside a region or meets none (a NOT_FOUND leaf), so a gap in the partition is
    reported, never given a neighbour's law.

    ``candidates_per_node``: how many hyperplanes are scored exactly at each node before the
    best is taken (4: on the servo problems, more gives the same depth for more build time).
    """
    start = time.perf_counter()
    box = _Box(lower, upper)
    builder = _Builder(regions, labels, box, covered)
    plane, left, right, label = builder.build(candidates_per_node)
    n = box.half.size
    A, b = builder.planes[:, :n], builder.planes[:, n]
    A_p, b_p = box.to_p(A, b) if A.size else (np.zeros((0, n)), np.zeros(0))
    return SearchTree(A=A_p, b=b_p, plane=np.array(plane), left=np.array(left),
                      right=np.array(right), label=np.array(label), lower=box.lower,
                      upper=box.upper, build_s=time.perf_counter() - start,
                      lps=builder.lp.count)
