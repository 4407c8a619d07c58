"""Matches a period off the scene's largest planes, aligned by the intensities, moved onto them (beyond the paper).

On texture that repeats along the lines (stripes) SGM's cost has a minimum at every period,
and a patch of a striped surface can settle a whole period off (generated seed 294's
striped wall: 12,308 matches a median 10 px off). No window the size of SGM's block tells
the periods apart. Summed over a whole plane, the faint texture under the stripes does: the
plane aligned by the intensities (:func:`.plane_align.align_plane`, whose coarser blur
averages the stripes away) and started 10 px off on that wall converges to the truth
(median 0.00 px over its 34,380 pixels).

So the largest planes among the matches (the plane fill's RANSAC over a plane's 3 parameters
under the pose, :data:`MAX_PLANES`, each with :data:`MIN_PLANE_SHARE` of the matches within
1 px) are aligned by the intensities on a sample of their matches, kept where their halves
agree and image 2 bears them out (as the plain regions' aligned planes,
:func:`.planes._aligned_surface`). Where
image 2 warped by such a plane matches image 1 over the normalisation's window
(:func:`.plane_align.agreement` at least :data:`.plane_align.FILL_ZNCC`), and that area
reaches the plane's own matches, a match more than :data:`MOVE_PX` off the plane moves onto
it where image 2 under the plane correlates better with image 1 over the window than image 2
at the matches' own partners (:func:`_window_agreement`, over the matched pixels: a plane
slid along a striped surface's lines correlates better there than the patch a period off,
the faint texture beneath the stripes agreeing too), and where it lies in a patch of such
matches of at least :data:`MIN_PATCH_SHARE` of the view and one window. The area is eroded
by the window first: about a surface in front of the plane, the windows of its edge hold
the plane's texture and agree with it. Its windows lie inside the image and off every area
of one value (a turned image's fill, whose edge is no edge of the scene).

The same planes give back what the repeat check (:mod:`.periodic`) dropped: on a striped
surface without other texture it drops every estimate, right or not, since no window tells
the periods apart (generated seed 192's striped floor, 0.68 of coverage against DIS's 0.69).
So do they what the left-right check dropped on such texture (:func:`.sgm.repeating_drops`):
its second SGM, at half size, can go a period off on fine stripes (seed 240's wall, 0.76 of
coverage against DIS's 0.79).
Those candidates join the matches for the step's own test (a plane's own correlation and
the matches' window agreement), and come back where they lie in a kept plane's area: as
SGM left them within :data:`MOVE_PX` of it, moved onto it where the move's test above holds.
The planes are found among the matches alone: a striped floor's candidates lie a period off
in patches that are planes too, and without other texture such a plane agrees with image 2
as well as the true one (seed 192's floor given back a period off: 0.74 at 1 px).
"""

from __future__ import annotations

from functools import partial
from types import SimpleNamespace
from typing import NamedTuple

import cv2
import numpy as np
from numba import njit

from .checks import flat_windows
from .plane_align import (ALIGNED_ZNCC, FILL_ZNCC, NORM_RADIUS, SIGMAS, _sample, agreement, align_images, align_plane,
                          halves_agree, masked_zncc, normalised_region)
from .planes import MAX_ALIGN_PIXELS, _homography, _median_over, _on_plane, _plane_support, _pose
from .stereo_sgbm import SPECKLE_SHARE

__all__ = ["DominantMoves", "move_onto_dominant_planes"]

#: Images larger than this (px, the longer side) are judged on copies reduced to it: the size
#: the step was measured at (the generated scenes), and the alignment's cost stays that of
#: 1000x750 (at 2000x1500, judged at full size, it took 6 s and 0.7 GB).
ALIGN_SIDE = 1000
#: Planes tried, largest first: a scene's floor, walls and the large faces in front of them.
#: Each costs an alignment (about 0.1 s at 1000x750).
MAX_PLANES = 4
#: A plane holds at least this share of the matches: below it the plane is one object's
#: face, whose stripes the objects' edges anchor.
MIN_PLANE_SHARE = 0.05
#: A match this many px off an aligned plane is a gross error if the plane is its surface
#: (a period off); within it, the slant and noise SGM's median and sub-pixel steps handle.
MOVE_PX = 3.0
#: The moved matches come in patches of at least this share of the view, the speckle
#: filter's bar for a surface (:data:`.stereo_sgbm.SPECKLE_SHARE`), and of at least one
#: normalisation window: a smaller patch is judged by windows that mostly hold other
#: pixels (real pair Rocks1 rect: a band of 441 matches, 10 rows high, all right, moved 3 px
#: and more off by the test alone).
MIN_PATCH_SHARE = SPECKLE_SHARE


class DominantMoves(NamedTuple):
    """Matches moved onto an aligned plane."""

    moved: np.ndarray  #: (M,) int64 indices of the moved matches
    uv2: np.ndarray  #: (M, 2) their new partners, COLMAP positions of image 2
    xyz: np.ndarray  #: (M, 3) their new points, camera 1's frame
    planes: int  #: planes aligned, kept and moved onto
    restored: np.ndarray  #: (K,) int64 indices of the candidates given back (moved onto a plane or as they were)
    restored_uv2: np.ndarray  #: (K, 2) their partners
    restored_xyz: np.ndarray  #: (K, 3) their points


def _window_agreement(one: np.ndarray, two: np.ndarray, index: np.ndarray, uv2: np.ndarray) -> np.ndarray:
    """The ZNCC, over the normalisation's window about each pixel of image 1 (:data:`NORM_RADIUS`),
    between image 1 and image 2 sampled at the partners ``uv2`` (N, 2) of the matches, over the
    matched pixels alone: how well those partners explain image 2 there. ``one`` (H, W) and
    ``two`` (H2, W2): the float32 images blurred at the finer blur of :data:`SIGMAS`;
    ``index``: (H, W) int64, each pixel's match (-1: none). (H, W) float32, -1 where under half
    the window is matched."""
    ys, xs = np.nonzero(index >= 0)
    at2 = np.zeros(one.shape, np.float32)
    at2[ys, xs] = _sample(two, uv2[index[ys, xs]])
    return np.nan_to_num(masked_zncc(one, at2, index >= 0), nan=-1.0)


def _largest_planes(pose, uv1: np.ndarray, uv2: np.ndarray, z: np.ndarray, rng: np.random.Generator,
                    found_on: np.ndarray | None = None):
    """Up to :data:`MAX_PLANES` planes of the scene (:func:`.planes._plane_support`: RANSAC over
    the 3 parameters the pose leaves a plane, as the plane fill's) and the indices of the
    matches within 1 px of each (the precision the matches are judged at), largest first,
    none under :data:`MIN_PLANE_SHARE` of the matches. ``pose``: the pair's
    (:func:`.planes._pose`); ``uv1``, ``uv2``: (N, 2) the matches; ``z``: (N,) their depths;
    ``found_on``: (N,) bool, the matches the planes are found among (default all)."""
    left = np.ones(len(uv1), bool) if found_on is None else found_on.copy()
    total = np.count_nonzero(left)
    for _ in range(MAX_PLANES):
        cand = np.flatnonzero(left)
        if len(cand) < MIN_PLANE_SHARE * total or len(cand) < 3:
            return
        abc, on = _plane_support(pose, uv1, uv2, z, cand, rng)
        inliers = cand[on]
        if abc is None or len(inliers) < MIN_PLANE_SHARE * total:
            return
        left[inliers] = False
        yield abc, inliers


def _eligible_areas(gray1: np.ndarray, gray2: np.ndarray, tv, uv1: np.ndarray, uv2: np.ndarray, z: np.ndarray,
                    rng: np.random.Generator, off_px: float, found_on: np.ndarray | None = None):
    """For each of the largest planes (:func:`_largest_planes`) aligned, and borne out by image 2,
    its ``abc``, the (H, W) bool pixels of image 1 where a match off it may move onto it (in the
    area where image 2 under it agrees, eroded by the window and joined to its own matches, and
    where its correlation beats the matches' own: the module's docstring; where the match lies
    over ``off_px`` px off it), that area, (H, W) bool, and a callable asking whether its halves
    agree. Arguments as
    :func:`move_onto_dominant_planes`'s, ``z`` (N,) the matches' depths, ``found_on`` as
    :func:`_largest_planes`'."""
    h, w = gray1.shape
    pose = _pose(tv)
    A, e = pose.warp()
    g2 = np.asarray(gray2, np.float32)
    px = uv1.astype(np.int64)
    index = np.full((h, w), -1, np.int64)
    index[px[:, 1], px[:, 0]] = np.arange(len(uv1))
    own = None  # (computed once, when a plane is kept)
    erode = np.ones((2 * NORM_RADIUS + 1, 2 * NORM_RADIUS + 1), np.uint8)
    whole = np.ones((h, w), bool)
    normed1 = normalised_region(gray1, 0, 0, whole)  # (image 1 as every plane's agreement compares it)
    # areas of one value of at least a window (a turned image's fill): their edge is no edge
    # of the scene, and correlates with image 2's own under a wrong plane (real pair Wood2
    # conv: 812 right matches beside it moved 3 px and more off). The generated scenes' specks
    # of one value (0.1-1 % of the pixels in 5x5 windows of one value, :func:`.checks.flat_windows`)
    # are none: eroded by the window they took 7-17 % of the view.
    flat = flat_windows(gray1).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(flat, connectivity=8)
    flat = (stats[:, cv2.CC_STAT_AREA] >= erode.size)[labels] & (flat > 0)
    for abc, on in _largest_planes(pose, uv1, uv2, z, rng, found_on):
        sample = uv1[np.sort(rng.choice(on, min(len(on), MAX_ALIGN_PIXELS), replace=False))]
        images = align_images(gray1, g2, sample)
        abc = align_plane(images, A, e, sample, abc)
        H = _homography(pose, abc)
        mine = np.zeros((h, w), bool)
        mine[px[on, 1], px[on, 0]] = True
        z_all, z_mine = agreement(gray1, g2, H, 0, 0, whole, (whole, mine), image1=normed1)
        if not _median_over(z_mine, mine) >= ALIGNED_ZNCC:
            continue
        agree = cv2.erode(((z_all >= FILL_ZNCC) & ~flat).astype(np.uint8), erode)
        n, labels = cv2.connectedComponents(agree, connectivity=4)
        reached = np.zeros(n, bool)
        reached[labels[mine & (agree > 0)]] = True
        reached[0] = False
        if own is None:
            blurred = (cv2.GaussianBlur(gray1.astype(np.float32), (0, 0), SIGMAS[-1]),
                       cv2.GaussianBlur(g2, (0, 0), SIGMAS[-1]))
            own = _window_agreement(*blurred, index, uv2)
        # the matches there over off_px off the plane (measured at those pixels alone)
        area = reached[labels]
        ys, xs = np.nonzero(area & (z_all > own) & (index >= 0))
        at = index[ys, xs]
        eligible = np.zeros((h, w), bool)
        if len(at):  # (OpenCV returns no array for no points)
            q = cv2.perspectiveTransform(uv1[at].reshape(-1, 1, 2), H).reshape(-1, 2)
            off = np.linalg.norm(q - uv2[at], axis=1) > off_px
            eligible[ys[off], xs[off]] = True
        # (the halves test, four more alignments, asked only where matches would move)
        yield abc, eligible, area, partial(halves_agree, images, A, e, sample, abc)


@njit(cache=True)
def _reduced_pixels(uv1, f, w, h):
    """Each match's pixel of the image reduced by ``f`` to ``w`` x ``h`` (row-major index; the
    matches ``uv1`` (N, 2) COLMAP positions scaled and truncated) and the first match in each
    pixel that holds one, in the pixels' order: (N,) and (M,) int64."""
    n = uv1.shape[0]
    pixel = np.empty(n, np.int64)
    first = np.full(w * h, -1, np.int64)
    for i in range(n):
        k = min(int(uv1[i, 1] * f), h - 1) * w + min(int(uv1[i, 0] * f), w - 1)
        pixel[i] = k
        if first[k] < 0:
            first[k] = i
    return pixel, first[first >= 0]


def move_onto_dominant_planes(gray1: np.ndarray, gray2: np.ndarray, tv, uv1: np.ndarray, uv2: np.ndarray,
                              X: np.ndarray, *, candidates: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                              seed: int = 0) -> DominantMoves:
    """The matches a period off the scene's largest aligned planes, moved onto them (the module's
    docstring). ``gray1``: (H, W) uint8 image 1; ``gray2``: (H2, W2) uint8 image 2; ``tv``: the
    pair's geometry (``K1``, ``K2``, ``R``, ``t``); ``uv1``, ``uv2``: (N, 2) the matches, COLMAP
    positions, at most one per pixel of image 1; ``X``: (N, 3) their points (camera 1's frame).
    ``candidates``: ``(uv1, uv2, X)`` of M more matches on pixels without one, that the step
    judges with the others (in the matches' window agreement; the planes are found among the
    matches alone) and gives back where they lie in a kept plane's area within :data:`MOVE_PX`
    of it, or moved onto it
    (:attr:`DominantMoves.restored`: the estimates the repeat check dropped, :mod:`.periodic`, and
    those the left-right check dropped on repeating texture).
    Images over :data:`ALIGN_SIDE` are judged on copies reduced to it (one match a reduced
    pixel), and the matches moved at their own size. The arguments are not changed."""
    h, w = gray1.shape
    n_own = len(uv1)
    if candidates is not None and len(candidates[0]):
        uv1, uv2, X = (np.concatenate([a, c]) for a, c in zip((uv1, uv2, X), candidates))
    none = DominantMoves(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 3)), 0,
                         np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 3)))
    if len(uv1) < 8:
        return none
    rng = np.random.default_rng(seed)
    f = min(1.0, ALIGN_SIDE / max(h, w))
    px = uv1.astype(np.int64)
    is_cand = np.arange(len(uv1)) >= n_own
    # (the planes found among the matches alone: on stripes without other texture a plane a
    # period off agrees with image 2 as well as the true one)
    found_on = ~is_cand if is_cand.any() else None
    if f < 1.0:
        size1 = (max(1, round(w * f)), max(1, round(h * f)))
        size2 = (max(1, round(gray2.shape[1] * f)), max(1, round(gray2.shape[0] * f)))
        small1 = cv2.resize(gray1, size1, interpolation=cv2.INTER_AREA)
        small2 = cv2.resize(gray2, size2, interpolation=cv2.INTER_AREA)
        S = np.diag([f, f, 1.0])  # (COLMAP positions scale about the corner)
        small_tv = SimpleNamespace(K1=S @ tv.K1, K2=S @ tv.K2, R=tv.R, t=tv.t)
        at, one = _reduced_pixels(np.ascontiguousarray(uv1, np.float64), f, *size1)  # (a match a reduced pixel)
        areas = _eligible_areas(small1, small2, small_tv, uv1[one] * f, uv2[one] * f, X[one, 2], rng, MOVE_PX * f,
                                None if found_on is None else found_on[one])
    else:
        at = px[:, 1] * w + px[:, 0]
        areas = _eligible_areas(gray1, gray2, tv, uv1, uv2, X[:, 2], rng, MOVE_PX, found_on)
    done = np.zeros(len(uv1), bool)  # moved, or given back where they lie
    to_idx, to_uv2, to_xyz, kept = [], [], [], 0
    min_patch = max(MIN_PATCH_SHARE * h * w, (2 * NORM_RADIUS + 1) ** 2 / (f * f))
    for abc, eligible, area, halves in areas:
        abc = abc * np.array([f, f, 1.0])  # (the plane in the matches' own pixels)
        move = eligible.ravel()[at] & ~done
        stay = area.ravel()[at] & is_cand & ~done & ~move  # (candidates on the plane: given back as they are)
        if not (move.any() or stay.any()):  # (no match to look up)
            continue
        cand = np.flatnonzero(move | stay)
        new2, newX, ok = _on_plane(tv, uv1[cand], abc)
        off = np.linalg.norm(new2 - uv2[cand], axis=1) > MOVE_PX
        go = ok & np.where(move[cand], off, ~off)
        cand, off, new2, newX = cand[go], off[go, None], new2[go], newX[go]
        new2, newX = np.where(off, new2, uv2[cand]), np.where(off, newX, X[cand])
        if not len(cand):
            continue
        patch = np.zeros((h, w), np.uint8)
        patch[px[cand, 1], px[cand, 0]] = 1
        n, labels, stats, _ = cv2.connectedComponentsWithStats(patch, connectivity=8)
        large = stats[:, cv2.CC_STAT_AREA] >= min_patch
        large[0] = False
        go = large[labels[px[cand, 1], px[cand, 0]]]
        if not go.any() or not halves():
            continue
        kept += 1
        done[cand[go]] = True
        to_idx.append(cand[go]), to_uv2.append(new2[go]), to_xyz.append(newX[go])
    if not to_idx:
        return none._replace(planes=kept)
    idx = np.concatenate(to_idx)
    order = np.argsort(idx)  # (the planes' moves are disjoint)
    idx, new2, newX = idx[order], np.concatenate(to_uv2)[order], np.concatenate(to_xyz)[order]
    own = idx < n_own
    return DominantMoves(idx[own], new2[own], newX[own], kept, idx[~own] - n_own, new2[~own], newX[~own])
