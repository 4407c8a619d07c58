"""Multi-view consistent fusion of the point clouds of several image pairs.

As COLMAP's stereo fusion does it, a point is judged by the *other* views, not by
its neighbours in space:

1. **depth maps**: every posed image gets a z-buffer (nearest depth, and the
   normal of that point) of the points of every pair it takes part in, at the
   pixels where it observed them;
2. **judging**: each point of each pair is projected into every other posed
   view. A view *agrees* when its depth map holds, within ``WINDOW_PX`` of the
   projection, a depth within ``max_depth_error`` (relative) of the point's with
   a normal within ``NORMAL_TOL_DEG``; it *contradicts* the point when it sees a
   surface behind it there (the point floats in space that view saw through: a
   free-space violation), or when it matched nothing within
   ``BACKGROUND_RADIUS_PX`` although it was paired with an image in which the
   point is visible (the point lands on unmatched background). A view that
   sees a nearer surface hides the point; one it lies outside says nothing.
   A point is kept when at least ``min_views - 2`` (and at least one) other
   views agree and fewer contradict than agree. With ``min_views`` 2, a point
   that only its own pair sees is kept too, where no view contradicts it or
   hides it (a point that only one pair sees although another view looks at
   the place must be behind something there); with 3 (the default, as COLMAP
   keeps no point fewer than its ``min_num_pixels`` views see) it is dropped;
3. **merging**: a kept point joins the fused point that already owns its pixel
   (at a consistent depth) in one of the views that observe it, else starts
   one, and claims its pixels in those views; a fused point is the mean of its
   observations and its track is the set of views that observed or agreed with it.

The pairs are read back from disk block by block (``read_blocks``), twice: once
for the depth maps, once for judging and merging. Memory: per view a float32
depth map, an int8x3 normal map, an owner and a depth of the fused points (14
bytes a pixel), plus the fused points (about 90 bytes each) and one block.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator, NamedTuple

import numpy as np
from numba import njit

log = logging.getLogger(__name__)

__all__ = ["FusedCloud", "FusionView", "fuse_pairs", "orient_normals", "project"]

#: A view agrees when one of its observations lies within this many pixels of the projection
#: (a 3x3 window: the matches' sub-pixel positions fall into the neighbouring pixel half the time).
WINDOW_PX = 1
#: Largest angle between a point's normal and an agreeing observation's: per-pair normals come from
#: 1-px grid differences and scatter by 10-20 degrees on real photos; COLMAP's 10 would reject good points.
NORMAL_TOL_DEG = 30.0
#: A view that matched nothing within this radius sees background there: holes up to 16 px wide inside
#: a matched surface (a specularity, a texture-less patch) are not taken for background.
BACKGROUND_RADIUS_PX = 8
#: Points read and judged at a time: a block's projections into 16 views take ~50 MB.
BLOCK_POINTS = 1 << 18


@dataclass
class FusionView:
    """A posed image: ``camera`` a pycolmap.Camera, pose x_cam = R X + t."""

    camera: object
    R: np.ndarray
    t: np.ndarray

    @property
    def width(self) -> int:
        return int(self.camera.width)

    @property
    def height(self) -> int:
        return int(self.camera.height)

    @property
    def centre(self) -> np.ndarray:
        return -np.asarray(self.R).T @ np.asarray(self.t)


@dataclass
class FusedCloud:
    xyz: np.ndarray  #: (N, 3) float64
    rgb: np.ndarray  #: (N, 3) uint8
    normals: np.ndarray  #: (N, 3) float64 unit normals, facing the cameras
    support: np.ndarray  #: (N,) number of views in the point's track
    tracks: np.ndarray = field(default_factory=lambda: np.zeros((0, 1), np.uint64))  #: (N, words) view bit masks
    observations: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))  #: (N,) pair points merged
    stats: dict = field(default_factory=dict)

    def track(self, i: int) -> list[int]:
        """The views (indices into the fusion's ``views``) in point ``i``'s track."""
        bits = self.tracks[i]
        return [64 * w + b for w in range(len(bits)) for b in range(64) if (int(bits[w]) >> b) & 1]


def orient_normals(normals: np.ndarray, view_dirs: np.ndarray) -> np.ndarray:
    """Flip each normal so that it points along ``view_dirs`` (towards its cameras)."""
    flip = np.einsum("ij,ij->i", normals, view_dirs) < 0
    out = normals.copy()
    out[flip] *= -1.0
    return out


def project(view: FusionView, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flat pixel index (row-major, -1 outside the image or behind the camera) and depth of points in a view."""
    Xc = np.asarray(xyz, np.float64) @ np.asarray(view.R, np.float64).T + np.asarray(view.t, np.float64)
    z = Xc[:, 2]
    front = z > 1e-12
    pix = np.full(len(z), -1, np.int64)
    if front.any():
        uv = np.asarray(view.camera.img_from_cam(Xc[front]), np.float64).reshape(-1, 2)
        with np.errstate(invalid="ignore"):
            x = np.floor(uv[:, 0])
            y = np.floor(uv[:, 1])
        ok = np.isfinite(x) & np.isfinite(y) & (x >= 0) & (y >= 0) & (x < view.width) & (y < view.height)
        idx = np.full(len(uv), -1, np.int64)
        idx[ok] = y[ok].astype(np.int64) * view.width + x[ok].astype(np.int64)
        pix[front] = idx
    return pix, z.astype(np.float32)


def _quantise_normals(nrm: np.ndarray | None, n: int) -> np.ndarray:
    if nrm is None:
        return np.zeros((n, 3), np.int8)
    unit = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    return np.clip(np.rint(unit * 127.0), -127, 127).astype(np.int8)


def _blocks(read_blocks: Callable[[int], Iterable], k: int) -> Iterator[tuple]:
    for xyz, rgb, nrm in read_blocks(k):
        xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
        ok = np.isfinite(xyz).all(1)
        if nrm is not None:
            nrm = np.asarray(nrm, np.float64).reshape(-1, 3)
            ok &= np.isfinite(nrm).all(1)
        if not ok.all():
            xyz, rgb = xyz[ok], rgb[ok]
            nrm = None if nrm is None else nrm[ok]
        if len(xyz):
            yield xyz, np.asarray(rgb, np.uint8).reshape(-1, 3), nrm


def fuse_pairs(
    views: list[FusionView],
    pairs: list[tuple[int, int]],
    read_blocks: Callable[[int], Iterable[tuple[np.ndarray, np.ndarray, np.ndarray | None]]],
    min_views: int = 3,
    max_depth_error: float = 0.01,
) -> FusedCloud:
    """Fuse the world-frame points of image pairs into one multi-view consistent cloud.

    Args:
        views: every posed image (a point is checked against all of them).
        pairs: per pair, the indices into ``views`` of its two images.
        read_blocks: ``read_blocks(k)`` yields pair ``k``'s points as blocks of
            ``(xyz (n, 3), rgb (n, 3) uint8, normals (n, 3) or None)``; called twice per pair.
        min_views: views (the pair's two included) that must agree with a point (at least 3: one other
            view); 2 keeps a pair's point that no other view agrees with where no view contradicts or hides it.
            At most the number of views that take part in a pair counts (one pair: its points stay).
        max_depth_error: relative depth difference within which two observations agree.

    Returns:
        The fused cloud; ``stats``: ``input_points``, ``kept`` (pair points kept), ``kept_unconfirmed``
        (kept with no other view agreeing), ``dropped_free_space``, ``dropped_background``,
        ``dropped_hidden`` (seen by too few views, hidden in another), ``dropped_unconfirmed`` (too few
        views agree, none contradicts), ``merged``,
        ``points``, ``mean_track_length`` and ``track_lengths`` (a histogram, index = views).
    """
    if not max_depth_error > 0:
        raise ValueError(f"max_depth_error must be positive, got {max_depth_error}")
    V = len(views)
    sizes = np.array([v.width * v.height for v in views], np.int64)
    offs = np.r_[0, np.cumsum(sizes)].astype(np.int64)
    widths = np.array([v.width for v in views], np.int64)
    heights = np.array([v.height for v in views], np.int64)
    total = int(offs[-1])
    depth = np.full(total, np.inf, np.float32)
    nmap = np.zeros((total, 3), np.int8)
    adj = np.zeros((V, V), np.bool_)
    have_normals = True
    n_in = 0
    # 1. depth maps
    for k, (a, b) in enumerate(pairs):
        adj[a, b] = adj[b, a] = True
        for xyz, _rgb, nrm in _blocks(read_blocks, k):
            n_in += len(xyz)
            have_normals &= nrm is not None
            nq = _quantise_normals(nrm, len(xyz))
            for j in (a, b):
                pix, z = project(views[j], xyz)
                pix[pix >= 0] += offs[j]
                _zbuffer_insert(depth, nmap, pix, z, nq)
    near = np.zeros(total, np.uint8)
    import cv2

    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * BACKGROUND_RADIUS_PX + 1,) * 2)
    for j in range(V):
        m = np.isfinite(depth[offs[j]:offs[j + 1]]).reshape(heights[j], widths[j]).astype(np.uint8)
        near[offs[j]:offs[j + 1]] = cv2.dilate(m, kernel).reshape(-1)
    cos_min = float(np.cos(np.radians(NORMAL_TOL_DEG))) if have_normals else -2.0

    # 2. judge and merge
    owner = np.full(total, -1, np.int32)
    fdepth = np.zeros(total, np.float32)
    words = (V + 63) // 64
    cap = 0
    sxyz = np.zeros((0, 3))
    srgb = np.zeros((0, 3))
    snrm = np.zeros((0, 3))
    nobs = np.zeros(0, np.int32)
    track = np.zeros((0, words), np.uint64)
    n_fused = np.zeros(1, np.int64)
    counts = np.zeros(7, np.int64)
    # only views in a pair have depth to agree with: with fewer of them than min_views, all of them are asked
    # (a workspace of two views, or --pairs naming one pair: its points, where no view contradicts them)
    paired = int(np.sum(adj.any(1)))
    min_agree = max(0, min(int(min_views), paired) - 2)
    maps = _Maps(depth, nmap, near, offs, widths, heights, adj)
    judge = _Judge(float(max_depth_error), cos_min, WINDOW_PX, min_agree)
    for k, (a, b) in enumerate(pairs):
        for xyz, rgb, nrm in _blocks(read_blocks, k):
            need = int(n_fused[0]) + len(xyz)
            if need > cap:  # grow the accumulators (geometric, so copies stay rare)
                cap = max(need, int(cap * 1.5), 1 << 16)
                grow = lambda arr, shape: np.concatenate([arr, np.zeros((cap - len(arr),) + shape, arr.dtype)])  # noqa: E731
                sxyz, srgb, snrm = grow(sxyz, (3,)), grow(srgb, (3,)), grow(snrm, (3,))
                nobs, track = grow(nobs, ()), grow(track, (words,))
            proj = [project(v, xyz) for v in views]
            pix = np.stack([p for p, _ in proj])
            z = np.stack([zz for _, zz in proj])
            del proj
            nq = _quantise_normals(nrm, len(xyz))
            nrm_w = np.zeros((len(xyz), 3)) if nrm is None else nrm
            _fuse_block(_Block(a, b, pix, z, xyz, rgb.astype(np.float64), nrm_w, nq), maps,
                        _Fused(owner, fdepth, sxyz, srgb, snrm, nobs, track, n_fused, counts), judge)
    del depth, nmap, near, owner, fdepth, maps
    n = int(n_fused[0])
    cnt = np.maximum(nobs[:n], 1).astype(np.float64)[:, None]
    fx = sxyz[:n] / cnt
    frgb = np.clip(np.rint(srgb[:n] / cnt), 0, 255).astype(np.uint8)
    tracks = track[:n].copy()
    support = np.zeros(n, np.int64)
    view_dir = np.zeros((n, 3))
    centres = np.stack([v.centre for v in views]) if V else np.zeros((0, 3))
    for j in range(V):
        inj = ((tracks[:, j // 64] >> np.uint64(j % 64)) & np.uint64(1)).astype(bool)
        support += inj
        d = centres[j] - fx[inj]
        view_dir[inj] += d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    normals = snrm[:n].copy()
    if not have_normals:
        normals = view_dir.copy()
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    normals = orient_normals(normals, view_dir)
    hist = np.bincount(support, minlength=V + 1)
    stats = {
        "input_points": int(n_in),
        "kept": int(counts[0]),
        "kept_unconfirmed": int(counts[1]),
        "dropped_free_space": int(counts[2]),
        "dropped_background": int(counts[3]),
        "dropped_hidden": int(counts[5]),
        "dropped_unconfirmed": int(counts[6]),
        "merged": int(counts[4]),
        "points": n,
        "mean_track_length": round(float(support.mean()), 3) if n else 0.0,
        "track_lengths": [int(h) for h in hist],
        "min_views": int(min_views),
        "max_depth_error": float(max_depth_error),
    }
    log.info("fused %d points of %d pairs into %d (%d dropped: %d in free space, %d on background, %d hidden in "
             "another view, %d confirmed by too few views; mean track %.2f views)", n_in, len(pairs), n,
             n_in - counts[0], counts[2], counts[3], counts[5], counts[6], stats["mean_track_length"])
    return FusedCloud(fx, frgb, normals, support, tracks, nobs[:n].copy(), stats)


# ------------------------------------------------------------------ numba kernels


class _Block(NamedTuple):
    """One block of pair (``a``, ``b``)'s points: ``pix``/``z`` (V, n) each point's flat pixel
    (-1 outside or behind) and depth in every view; ``xyz``, ``rgb``, ``nrm`` (n, 3) float64;
    ``nq`` (n, 3) int8 quantised normals."""

    a: int
    b: int
    pix: np.ndarray
    z: np.ndarray
    xyz: np.ndarray
    rgb: np.ndarray
    nrm: np.ndarray
    nq: np.ndarray


class _Maps(NamedTuple):
    """Every view's maps, concatenated (view ``j``'s pixels start at ``offs[j]``): ``depth``
    float32 nearest depth, ``nmap`` its int8 normal, ``near`` uint8 a match within
    :data:`BACKGROUND_RADIUS_PX`; ``widths``, ``heights`` (V,); ``adj`` (V, V) bool, paired."""

    depth: np.ndarray
    nmap: np.ndarray
    near: np.ndarray
    offs: np.ndarray
    widths: np.ndarray
    heights: np.ndarray
    adj: np.ndarray


class _Fused(NamedTuple):
    """The fused points so far: per view pixel its ``owner`` (-1 none) and that point's depth
    ``fdepth`` there; per fused point the sums ``sxyz``, ``srgb``, ``snrm``, its ``nobs``
    observations and ``track`` (view bit masks); ``n_fused`` (1,) their count; ``counts`` (7,)
    the outcomes (:func:`fuse_pairs`' stats)."""

    owner: np.ndarray
    fdepth: np.ndarray
    sxyz: np.ndarray
    srgb: np.ndarray
    snrm: np.ndarray
    nobs: np.ndarray
    track: np.ndarray
    n_fused: np.ndarray
    counts: np.ndarray


class _Judge(NamedTuple):
    """How views judge a point: relative depth ``tol``, the normals' ``cos_min`` (-2: no
    normals), the window's radius ``r`` (px), ``min_agree`` other views needed."""

    tol: float
    cos_min: float
    r: int
    min_agree: int


@njit(cache=True)
def _zbuffer_insert(depth, nmap, pix, z, nq):
    """Keep the nearest depth (and its quantised normal) of each pixel; ``pix`` -1 = not in the view."""
    for k in range(pix.shape[0]):
        p = pix[k]
        if p >= 0 and z[k] < depth[p]:
            depth[p] = z[k]
            nmap[p, 0] = nq[k, 0]
            nmap[p, 1] = nq[k, 1]
            nmap[p, 2] = nq[k, 2]


@njit(cache=True)
def _window(maps, j, p, z, nq, tol, cos_min, r):
    """Around pixel ``p`` of view ``j``: (an agreeing depth found, nearest depth in the window)."""
    depth, nmap = maps.depth, maps.nmap
    off, w, h = maps.offs[j], maps.widths[j], maps.heights[j]
    x0 = p % w
    y0 = p // w
    agree = False
    wmin = np.inf
    for dy in range(-r, r + 1):
        y = y0 + dy
        if y < 0 or y >= h:
            continue
        for dx in range(-r, r + 1):
            x = x0 + dx
            if x < 0 or x >= w:
                continue
            q = off + y * w + x
            d = depth[q]
            if d < wmin:
                wmin = d
            if abs(d - z) <= tol * z:
                if cos_min > -1.0:
                    dot = (np.float64(nmap[q, 0]) * nq[0] + np.float64(nmap[q, 1]) * nq[1]
                           + np.float64(nmap[q, 2]) * nq[2]) / (127.0 * 127.0)
                    if dot < cos_min:
                        continue
                agree = True
    return agree, wmin


@njit(cache=True)
def _fuse_block(blk, maps, acc, judge):
    """Judge and merge one block of a pair's points (:class:`_Block`) against every view's
    depth map (:class:`_Maps`) into the fused points (:class:`_Fused`), by :class:`_Judge`.

    ``blk.pix``/``blk.z`` (V, n): each point's pixel (flat, -1 outside or behind) and depth
    in every view. A point is kept when at least ``max(min_agree, 1)`` other views
    agree and fewer contradict than agree; with ``min_agree`` 0 also when no view
    agrees, contradicts or hides it. A kept point
    joins the fused point that already owns its pixel in one of its views (at a
    consistent depth), else starts one; it then claims its pixels in those views.
    ``counts``: [kept, kept without other views, free-space drops, background
    drops, merged into an existing point, drops hidden in another view, drops
    with too few agreeing views].
    """
    a, b, pix, z, xyz, rgb, nrm, nq = blk
    depth, near, offs, adj = maps.depth, maps.near, maps.offs, maps.adj
    owner, fdepth, sxyz, srgb, snrm, nobs, track, n_fused, counts = acc
    tol, cos_min, r, min_agree = judge
    V = pix.shape[0]
    n = pix.shape[1]
    inview = np.zeros(V, np.bool_)
    for k in range(n):
        agree = 0
        contra = 0
        freesp = 0
        hidden = 0
        for j in range(V):
            inview[j] = False
        inview[a] = pix[a, k] >= 0
        inview[b] = pix[b, k] >= 0
        for j in (a, b):  # a nearer surface at the very pixel that observed the point: another pair saw through it
            if inview[j] and depth[offs[j] + pix[j, k]] < z[j, k] * (1.0 - tol):
                contra += 1
                freesp += 1
        for j in range(V):
            p = pix[j, k]
            if j == a or j == b or p < 0:
                continue
            zj = z[j, k]
            ok, wmin = _window(maps, j, p, zj, nq[k], tol, cos_min, r)
            if ok:
                agree += 1
                inview[j] = True
            elif wmin < np.inf:
                if wmin > zj * (1.0 + tol):  # the view sees a surface behind the point: free space
                    contra += 1
                    freesp += 1
                elif wmin < zj * (1.0 - tol):  # the view sees a surface in front of it: hidden there
                    hidden += 1
            elif near[offs[j] + p] == 0:
                # nothing matched anywhere near: background, if a pair of this view could have matched it
                for m in range(V):
                    if adj[j, m] and pix[m, k] >= 0:
                        pm = pix[m, k]
                        _, wmin2 = _window(maps, m, pm, z[m, k], nq[k], tol, -2.0, r)
                        if not (wmin2 < z[m, k] * (1.0 - tol)):  # not hidden in the partner view
                            contra += 1
                            break
        # confirmed by enough views: fewer may contradict it than agree; a pair's point alone (min_agree 0):
        # no view may contradict or hide it
        if not ((agree >= max(min_agree, 1) and contra < agree)
                or (min_agree == 0 and agree == 0 and contra == 0 and hidden == 0)):
            if freesp > 0:
                counts[2] += 1
            elif contra > 0:
                counts[3] += 1
            elif hidden > 0:
                counts[5] += 1
            else:
                counts[6] += 1
            continue
        counts[0] += 1
        if agree == 0:
            counts[1] += 1
        # merge: the fused point that observed the same pixel of one of this point's two images, at a consistent
        # depth (an agreeing view adds to the track; merging there too made 35 % fewer points on fountain-P11)
        fid = -1
        for j in (a, b):
            if not inview[j]:
                continue
            q = offs[j] + pix[j, k]
            o = owner[q]
            if o >= 0 and abs(fdepth[q] - z[j, k]) <= tol * z[j, k]:
                fid = o
                break
        if fid < 0:
            fid = n_fused[0]
            n_fused[0] += 1
        else:
            counts[4] += 1
        for c in range(3):
            sxyz[fid, c] += xyz[k, c]
            srgb[fid, c] += rgb[k, c]
            snrm[fid, c] += nrm[k, c]
        nobs[fid] += 1
        for j in range(V):
            if not inview[j]:
                continue
            track[fid, j // 64] |= np.uint64(1) << np.uint64(j % 64)
            if j != a and j != b:  # an agreeing view joins the track; only observing views claim pixels
                continue
            q = offs[j] + pix[j, k]
            if owner[q] < 0:
                owner[q] = fid
                fdepth[q] = z[j, k]
