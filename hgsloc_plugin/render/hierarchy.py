"""A map's level-of-detail hierarchy, built once, and its cut for a view.

Levels ``l = 0 .. L`` of cubic cells (world axes, one origin) of side ``s_l = s_0 2^l`` scene units (``s_0``: the
power of two at or below the map's 1st-percentile Gaussian size ``smax``; the top level's side spans the map). A
Gaussian takes part from its *size level* (the finest level whose side is at least its ``smax``) up; the node of a
cell merges the Gaussians taking part whose centres lie in it (``lod.merge_groups``: moment-matched position,
covariance, colour and opacity, footprints weighed at one cell side per pixel), or is that Gaussian itself when
it is alone. A map's hierarchy is cached on disk by its content (:func:`hierarchy_for`).

A cut (:meth:`Hierarchy.cut`) for a focal length ``f`` (pixels) and a region of poses (a centre pose, a
camera-centre shift): a cell is *small* when its side projects to at most ``tau_px`` pixels at the nearest depth
any pose of the region gets to its bounding sphere, and then so is every cell inside it. The cut draws the node of
each small cell whose parent is not small, and each Gaussian whose size-level cell is not small as itself: every
Gaussian of the map is drawn exactly once, merged or as it is. Cells no pose of the region can see are left out
(a conservative test with ``kernels/cull.py``'s planes). Approximate where it merges: accuracy and speed in
``benchmarks/map_scale.md`` (1 px kept refined poses within 0.01 % of the depth on every real map measured).
"""

from __future__ import annotations

import functools
import hashlib
import io
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.camera import Camera
from ..core.fileio import atomic_write_bytes
from ..core.pose import Pose
from ..kernels import RasterConfig, cull
from .lod import DILATION_PX2, merge_groups

logger = logging.getLogger(__name__)

FORMAT = 2  # bump when the build or the file changes
SIZE_PERCENTILE = 1.0  # s_0 from this percentile of the Gaussians' smax
MAX_LEVELS = 20  # cells are packed in 21 bits per axis
HALF_DIAGONAL = math.sqrt(3.0) / 2.0
FIELDS = ("means", "cov3d", "opacities", "sh", "smax")
#: the hierarchy's arrays besides the leaves and the merged Gaussians (as saved)
ARRAYS = ("source", "level_start", "side", "centre", "parent", "first", "node", "own_cell", "extent")
#: a merged Gaussian's covariance gains (COVER * side)^2 on its diagonal: moment matching alone leaves each cell's
#: merge compact (a standard deviation of 0.29 side for members spread over the cell), so neighbouring merges of
#: a surface leave gaps the members covered. Chosen 2026-12-06 on the room split 20 times and the real snow_sharp
#: photos (the change to refined poses against the exact map at 2 px, % of the depth: 0 -> 0.026 / 0.012, 0.2 ->
#: 0.011 / 0.008, 0.3 -> 0.008 / 0.005, 0.4 -> 0.005 / 0.018), checked on lego and the snow.ply photos, not used
#: to choose it (0.3 against 0.4: 0.032 / 0.010 against 0.134 / 0.017 at 2 px; 0.006 / 0.009 against 0.009 /
#: 0.010 at 1 px): benchmarks/map_scale.md
COVER = 0.3
#: the levels (counted down from the top) whose cells a cut tests for visibility before the cells it draws; the
#: cut is the same (tests/test_hierarchy.py). With 4 alone, 456k cells were tested to draw 73k on the room split
#: 20 times at 320x240 (23 ms of a 58 ms cut); with 4 and 7 the cut takes 45 ms (2026-12-06, this CPU)
PREFILTER = (4, 7)


@dataclass(frozen=True)
class Hierarchy:
    """The cells of every level, concatenated (level ``l``'s at ``level_start[l]:level_start[l + 1]``).

    Attributes:
        leaves: the map's Gaussians as ``Renderer.arrays()`` [n]; source [n]: their scene indices.
        side [C]: each cell's side (scene units); centre [C, 3]: its centre; parent [C]: the index of the cell
            of the next level holding it (-1 at the top); first [C]: its first member (a leaf index); node [C]:
            its merged Gaussian's index in ``merged`` (-1 when the cell has one member: the leaf ``first``).
        own_cell [n]: each leaf's cell at its size level (-1 when it is larger than the top level's side).
        extent [C]: the largest ``smax`` of a cell's members and of its and its descendants' merged Gaussians.
        merged: the merged Gaussians of every cell with more than one member, as ``leaves`` [m].
        build_seconds: the build's time (0 when loaded).
    """

    leaves: dict[str, np.ndarray]
    source: np.ndarray
    level_start: np.ndarray
    side: np.ndarray
    centre: np.ndarray
    parent: np.ndarray
    first: np.ndarray
    node: np.ndarray
    own_cell: np.ndarray
    extent: np.ndarray
    merged: dict[str, np.ndarray]
    build_seconds: float = 0.0

    @property
    def n(self) -> int:
        """Gaussians of the map (leaves)."""
        return len(self.source)

    @property
    def levels(self) -> int:
        """Levels of cells (L + 1)."""
        return len(self.level_start) - 1

    @property
    def nbytes(self) -> int:
        """Bytes held beyond the leaves (cells and merged Gaussians)."""
        cells = sum(a.nbytes for a in (self.side, self.centre, self.parent, self.first, self.node, self.own_cell,
                                       self.extent))
        return cells + sum(a.nbytes for a in self.merged.values())

    def prefilter_levels(self, prefilter: tuple[int, ...] = ()) -> tuple[int, ...]:
        """The levels ``prefilter`` names (counted down from the top, ``PREFILTER``), coarsest first."""
        return tuple(sorted({max(0, self.levels - d) for d in prefilter}, reverse=True))

    @functools.cached_property
    def _ancestors(self) -> dict[int, np.ndarray]:
        return {}

    def ancestor_at(self, level: int) -> np.ndarray:
        """[C]: each cell's cell at ``level`` (itself at or above it); computed once per level."""
        if level not in self._ancestors:
            anc = np.arange(len(self.side))
            for lv in range(level - 1, -1, -1):
                a, b = self.level_start[lv], self.level_start[lv + 1]
                anc[a:b] = anc[self.parent[a:b]]
            self._ancestors[level] = anc
        return self._ancestors[level]

    def small_cells(self, f: float, pose: Pose, max_shift: float, tau_px: float, near: float) -> np.ndarray:
        """[C] bool: the cells whose side projects to at most ``tau_px`` pixels (focal ``f``) at the nearest depth
        any camera within ``max_shift`` of ``pose``'s centre gets to their bounding sphere; closed downwards
        (a cell inside a small one is small)."""
        d = self.centre @ pose.R[2] + pose.tvec[2] - HALF_DIAGONAL * self.side - max_shift
        small = (d > near) & (self.side * f <= tau_px * d)
        for lv in range(self.levels - 2, -1, -1):  # exact arithmetic implies it; rounding must not break it
            a, b = self.level_start[lv], self.level_start[lv + 1]
            small[a:b] |= small[self.parent[a:b]]
        return small

    def cut(self, cameras: list[Camera], pose: Pose, max_shift: float, max_rotation_deg: float, tau_px: float,
            config: RasterConfig | None = None, prefilter: tuple[int, ...] = PREFILTER
            ) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """The cut for ``cameras`` (merging at ``tau_px`` pixels of the largest focal length) over the poses within
        ``max_shift`` (scene units) and ``max_rotation_deg`` of ``pose`` (see the module docstring), without the
        cells no pose of that region can see (a conservative test on each cell's bounding sphere, widened by
        what its Gaussians reach: ``kernels/cull.py``'s planes), first at the levels ``prefilter`` names (a cell
        whose ancestor there is out of view is out of view; the same cut, fewer tests).

        Returns:
            (arrays as ``Renderer.arrays()`` [k], in the order of each drawn Gaussian's first leaf; source [k]:
            the scene index of each, -1 for a merged one).
        """
        if not tau_px > 0:
            raise ValueError(f"tau_px must be > 0, got {tau_px}")
        config = config or RasterConfig()
        near = max(config.near_plane, 1e-6)
        f = max(max(c.fx, c.fy) for c in cameras)
        small = self.small_cells(f, pose, max_shift, tau_px, near)
        top = self.level_start[-2]
        parent_small = np.zeros_like(small)
        parent_small[:top] = small[self.parent[:top]]
        cells = np.flatnonzero(small & ~parent_small)
        own = self.own_cell
        alone = np.flatnonzero(own < 0)
        candidates = np.flatnonzero(~small[np.maximum(own, 0)] & (own >= 0))
        tested = np.zeros(len(small), bool)  # the visibility test only where it decides
        tested[cells] = True
        tested[own[candidates]] = True
        tested = np.flatnonzero(tested)
        view = (cameras, pose, max_shift, max_rotation_deg, config)
        near_view = np.zeros(len(small), bool)  # tested first: a cell outside its ancestor there is outside
        below, upper = len(small), None
        for lv in self.prefilter_levels(prefilter):  # coarsest first: a level's cells under the last level's seen
            cand = np.arange(self.level_start[lv], below)  # ones (seen there implies seen at every coarser level)
            if upper is not None:
                cand = cand[near_view[self.ancestor_at(upper)[cand]]]
            near_view[cand] = self._seen(cand, *view)
            below, upper = self.level_start[lv], lv
        if upper is not None:  # the finest prefilter level decides for every cell (those above it: their own test)
            tested = tested[near_view[self.ancestor_at(upper)[tested]]]
        seen = np.zeros(len(small), bool)
        seen[tested] = self._seen(tested, *view)
        cells = cells[seen[cells]]
        kept = np.concatenate([alone, candidates[seen[own[candidates]]]])
        as_leaf = cells[self.node[cells] < 0]
        as_node = cells[self.node[cells] >= 0]
        leaf_idx = np.concatenate([kept, self.first[as_leaf]])
        node_idx = self.node[as_node]
        place = np.concatenate([leaf_idx, self.first[as_node]])
        order = np.argsort(place, kind="stable")
        out = {k: np.concatenate([self.leaves[k][leaf_idx], self.merged[k][node_idx]])[order] for k in FIELDS}
        source = np.concatenate([self.source[leaf_idx], np.full(len(node_idx), -1, np.int64)])[order]
        return out, source

    def _seen(self, cells: np.ndarray, cameras: list[Camera], pose: Pose, max_shift: float, max_rotation_deg: float,
              config: RasterConfig) -> np.ndarray:
        """[len(cells)] bool: which of ``cells`` some pose of the region may see. The Gaussians a cell or its
        descendants draw lie within ``HALF_DIAGONAL * side`` of its centre, with ``smax`` at most its
        ``extent``; a plane of ``cull.planes`` is failed when even the region's best pose leaves the cell's sphere
        outside it by more than they reach."""
        rows, fac = cull.planes(cameras, config)
        q = self.centre[cells] @ pose.R.T + pose.tvec  # camera frame of the region's centre pose
        side, extent = self.side[cells], self.extent[cells]
        turn = np.sqrt(np.einsum("ij,ij->i", q, q)) * 2.0 * math.sin(min(math.radians(max_rotation_deg), math.pi) / 2.0)
        turn += max_shift + HALF_DIAGONAL * side
        rows = np.asarray(rows, np.float64)
        margin = q @ rows[:, :3].T + rows[:, 3] + turn[:, None] + extent[:, None] * np.asarray(fac, np.float64)
        return np.all(margin >= 0, axis=1)

    def save(self, path: Path) -> None:
        """Write to ``path`` (npz) atomically, readable by others as the umask allows (``atomic_write_bytes``)."""
        data = {f"leaf_{k}": v for k, v in self.leaves.items()} | {f"merged_{k}": v for k, v in self.merged.items()}
        data |= {k: getattr(self, k) for k in ARRAYS}
        buffer = io.BytesIO()
        np.savez(buffer, format=np.int64(FORMAT), **data)
        atomic_write_bytes(Path(path), buffer.getvalue())

    @classmethod
    def load(cls, path: Path) -> Hierarchy:
        """Read a file written by :meth:`save`; ValueError naming it when it is of another format."""
        with np.load(path) as z:
            if int(z["format"]) != FORMAT:
                raise ValueError(f"{path}: hierarchy format {int(z['format'])}, expected {FORMAT}")
            leaves = {k: z[f"leaf_{k}"] for k in FIELDS}
            merged = {k: z[f"merged_{k}"] for k in FIELDS}
            rest = {k: z[k] for k in ARRAYS}
        return cls(leaves=leaves, merged=merged, **rest)


def build_hierarchy(arrays: dict[str, np.ndarray], source: np.ndarray, eps2d: float = DILATION_PX2) -> Hierarchy:
    """The hierarchy of the Gaussians ``arrays`` (as ``Renderer.arrays()`` [n]) with scene indices ``source`` [n]."""
    t0 = time.perf_counter()
    means = arrays["means"].astype(np.float64)
    smax = arrays["smax"].astype(np.float64)
    n = len(means)
    if n == 0:
        raise ValueError("no Gaussians")
    positive = smax[smax > 0]
    s0 = 2.0 ** math.floor(math.log2(np.percentile(positive, SIZE_PERCENTILE))) if positive.size else 1.0
    origin = means.min(axis=0)
    extent = float(np.max(means.max(axis=0) - origin))
    L = int(min(MAX_LEVELS - 1, max(0, math.ceil(math.log2(max(extent, s0) / s0)))))
    with np.errstate(divide="ignore"):
        size_level = np.ceil(np.log2(np.maximum(smax, 1e-30) / s0))
    size_level = np.clip(size_level, 0, L + 1).astype(np.int64)
    own_cell = np.full(n, -1, np.int64)
    sides, centres, parents, firsts, nodes, extents, starts = [], [], [], [], [], [], [0]
    merged_parts: dict[str, list[np.ndarray]] = {k: [] for k in FIELDS}
    m_total, prev_cells = 0, None
    for lv in range(L + 1):
        s = s0 * 2.0 ** lv
        mem = np.flatnonzero(size_level <= lv)
        c = np.floor((means[mem] - origin) / s).astype(np.int64)
        key = (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]
        uk, idx, inv = np.unique(key, return_index=True, return_inverse=True)
        C = len(uk)
        count = np.bincount(inv, minlength=C)
        cell = np.column_stack([uk >> 42, (uk >> 21) & 0x1FFFFF, uk & 0x1FFFFF])
        multi = count > 1
        node = np.full(C, -1, np.int64)
        M = int(multi.sum())
        node[multi] = m_total + np.arange(M)
        if M:
            dense = np.cumsum(multi) - 1
            in_multi = multi[inv]
            g = dense[inv[in_multi]]
            members = mem[in_multi]
            mu, cov, op, sh, sm = merge_groups(arrays, members, g, M, np.full(len(members), s), eps2d)
            cov[:, [0, 3, 5]] += (COVER * s) ** 2
            sm = np.sqrt(cov[:, [0, 3, 5]].sum(axis=1))
            for k, v in zip(FIELDS, (mu, cov, op, sh, sm)):
                merged_parts[k].append(v.astype(np.float32))
        ext = np.zeros(C)
        np.maximum.at(ext, inv, smax[mem])
        if M:
            ext[multi] = np.maximum(ext[multi], sm)
        m_total += M
        own = size_level[mem] == lv
        own_cell[mem[own]] = starts[-1] + inv[own]
        if prev_cells is not None:  # the previous level's cells lie in this level's: parent = half the cell
            pk = ((prev_cells[:, 0] >> 1) << 42) | ((prev_cells[:, 1] >> 1) << 21) | (prev_cells[:, 2] >> 1)
            parents[-1] = starts[-1] + np.searchsorted(uk, pk)
        extents.append(ext)
        sides.append(np.full(C, s))
        centres.append(origin + (cell + 0.5) * s)
        parents.append(np.full(C, -1, np.int64))
        firsts.append(mem[idx])
        nodes.append(node)
        starts.append(starts[-1] + C)
        prev_cells = cell
    extent = np.concatenate(extents)
    parent_all = np.concatenate(parents)
    for lv in range(L):  # bottom-up: a cell reaches as far as its descendants' merges
        a, b = starts[lv], starts[lv + 1]
        np.maximum.at(extent, parent_all[a:b], extent[a:b])
    empty = {"means": (0, 3), "cov3d": (0, 6), "opacities": (0,), "sh": (0,) + arrays["sh"].shape[1:], "smax": (0,)}
    merged = {k: np.concatenate(v) if v else np.zeros(empty[k], np.float32) for k, v in merged_parts.items()}
    h = Hierarchy(leaves={k: np.ascontiguousarray(arrays[k]) for k in FIELDS},
                  source=np.asarray(source, np.int64), level_start=np.asarray(starts, np.int64),
                  side=np.concatenate(sides), centre=np.concatenate(centres), parent=parent_all,
                  first=np.concatenate(firsts), node=np.concatenate(nodes), own_cell=own_cell, extent=extent,
                  merged=merged,
                  build_seconds=time.perf_counter() - t0)
    logger.info("level-of-detail hierarchy of %d Gaussians: %d levels, %d cells, %d merged, %.1f s", n, L + 1,
                len(h.side), m_total, h.build_seconds)
    return h


def content_key(arrays: dict[str, np.ndarray], source: np.ndarray) -> str:
    """A digest of the Gaussians and the build's format: the cache file's name."""
    digest = hashlib.sha256(f"hierarchy {FORMAT} {SIZE_PERCENTILE} {DILATION_PX2} {COVER}".encode())
    for k in FIELDS:
        a = np.ascontiguousarray(arrays[k])
        digest.update(f"{k}{a.dtype}{a.shape}".encode())
        digest.update(a.data)
    digest.update(np.ascontiguousarray(source, np.int64).data)
    return digest.hexdigest()[:32]


def hierarchy_for(arrays: dict[str, np.ndarray], source: np.ndarray, cache_dir: Path | None) -> Hierarchy:
    """The hierarchy of ``arrays``, read from ``cache_dir`` when built before (keyed by :func:`content_key`), else
    built and written there (None: not cached). An unreadable cache file is rebuilt, with a warning."""
    if cache_dir is None:
        return build_hierarchy(arrays, source)
    path = Path(cache_dir) / f"{content_key(arrays, source)}.npz"
    if path.exists():
        try:
            return Hierarchy.load(path)
        except (OSError, ValueError, KeyError) as exc:
            logger.warning("level-of-detail cache %s unreadable (%s); building it again", path, exc)
    h = build_hierarchy(arrays, source)
    try:
        h.save(path)
    except OSError as exc:
        logger.warning("level-of-detail cache %s not written (%s)", path, exc)
    return h


class CutSelection:
    """A :class:`~hgsloc_plugin.render.working_set.WorkingSet`'s selections from a cut: called as
    ``Renderer.working_set`` is, it renders the cut of ``hierarchy`` for the region (at the largest focal length
    of the cameras given, merging at ``tau_px`` pixels), culled to what the region's poses can see. With
    ``WorkingSet(per_camera=True)`` each image size gets its own cut.

    Args:
        renderer: the map's exact renderer (its config, kernels and pool serve the cuts); hierarchy: its
            :class:`Hierarchy`; tau_px: the cut's threshold in pixels of the finest camera.
    """

    def __init__(self, renderer, hierarchy: Hierarchy, tau_px: float):
        if not (tau_px > 0 and math.isfinite(tau_px)):
            raise ValueError(f"tau_px must be a positive number, got {tau_px!r}")
        self.renderer, self.hierarchy, self.tau_px = renderer, hierarchy, float(tau_px)

    def __call__(self, cameras: list[Camera], pose: Pose, max_shift: float, max_rotation_deg: float):
        arrays, source = self.hierarchy.cut(cameras, pose, max_shift, max_rotation_deg, self.tau_px,
                                            self.renderer.config)
        return self.renderer.derived(arrays, source).working_set(cameras, pose, max_shift, max_rotation_deg)
