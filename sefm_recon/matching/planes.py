"""Plain surfaces filled from their own matches (``sgm.planes``), an addition beyond the paper.

Semi-global matching leaves much of a plain surface unmatched: its windows carry too
little signal for the uniqueness test, or only ties (:func:`.checks.drop_range_ends`).
Where such a surface is one plane and enough of it did match, the plane is known:
the matches on it, each a plain window of the same surface, fit one plane of the scene
(:func:`_plane_support`: 3 parameters with the pose given). Image 1 is cut into plain
regions at its intensity edges (:func:`plain_regions`); in each large region whose
matches mostly agree on a plane (:func:`fill_planes`), the plane is aligned by the
images' intensities where its halves agree on it and image 2 under it bears it out
(:mod:`.plane_align`, :data:`.plane_align.ALIGNED_ZNCC`), and the unmatched
pixels among the plane's matches (:data:`MIN_HOLE_SUPPORT`), and those of an aligned plane
where image 2 under it matches image 1 (:data:`.plane_align.FILL_ZNCC`) and, if aligned on
these alone it converges onto another plane, where the two planes agree
(:func:`_realigned_apart`), take the partner that plane gives, unless a nearer surface's
match already lands there in image 2 (the pixel is hidden in view 2).

A region whose matches are few (:data:`MIN_MATCHED_SHARE`), or split over several
depths (a wrong patch of the matcher, a curved or folded surface), is not filled from
them: the fill extends what the matcher found. Where they cover over half of it but
lie too little on one plane (:data:`MIN_PLANE_SUPPORT`), it is filled only where the
plane RANSAC finds is aligned by the intensities (:mod:`.plane_align`), and its matches
stay. Where they cover under half of it and lie too little on one plane, SGM's
estimates may follow the noise of a weakly textured plane, which the intensities of all
its pixels align (:mod:`.plane_align`): then its matches near it move onto it, the
others are dropped, but for a large patch in front of it where image 2 does not bear the
plane out (an object standing before the plain surface, :func:`_nearer_surface`), and its
holes are filled. The matches it would drop may be a second surface the region holds
with no intensity edge between them (:func:`_second_surface`): a plain floor around a
pillar's plain face, whose matches lie on one plane while the floor's scatter, so that the
face's plane is the one aligned. They are one where as large a share of them lie on one
homography as of the region's matches on its plane (or half), and where image 2 under that
homography agrees with image 1 better than under the aligned plane over the pixels nearer
to its matches than to the plane's (the median over those where either agrees,
:data:`.plane_align.FILL_ZNCC`). Those pixels are the second surface's: its matches there
(within :data:`RIM_SNAP_PX` of it, and nearer to it than to the plane) stay as SGM left
them, and the aligned plane fills none of them. Else, with most of them off any one
plane, the matcher found no surface there at all, and they are dropped (:data:`MAX_SCATTERED_SUPPORT`);
the estimates the repeat check dropped there (:mod:`.periodic`) count in that test with them.
So are those of a mostly unmatched region whose plane is the first parallax of the search,
where OpenCV breaks the ties of a cost without a minimum (:data:`TIE_COLUMNS`).
Where they do mostly lie on one plane, the ones off it face the same test: patches carried
over the plain surface on no one plane, or on one within SGM's wave about the first, are
dropped, a second surface in the region stays (:data:`MIN_OFF_PLANE`).

Where a region is one plane all through (nearly all its matches within
:data:`SNAP_PX` of one plane of the scene), its matches on windows without signal
(:data:`SNAP_LEVELS`) move onto the plane as well: there SGM's cost is flat and
its winner is set by the smoothness penalties alone, so that a slanted plain
surface comes out as a wave of fronto-parallel steps around the plane (Plastic's
box face: 1-1.7 px off over runs of 20-40 px, more than the local plane fit of
:func:`.surfaces.fit_plain_surfaces` spans). Where a mostly matched region's plane is
aligned, its matches 1-3 px off it, amid matches on it, move onto it too where image 2
under it agrees (:func:`_noise_about`: SGM's blotches on a weakly textured floor).

Small plain regions (:func:`_rim_planes`) hold too few matches of their own for a
plane, but their rim, the intensity edge around them, is texture SGM matches well:
where the rim's matches lie on one plane, the region's unmatched pixels enclosed by
them take that plane, and the region's own matches, set by the smoothness penalties
rather than by a signal, move onto it (the checker squares of a slanted floor: 1-3 px
off, and left unmatched in part), with the rim's own plain band between the region and
its edge.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import cv2
import numpy as np
from numba import njit

from ..arrays import quiet_windows
from .lines import LineGrid, match_parallax
from .plane_align import (AGREE_PX, ALIGNED_ZNCC, FILL_ZNCC, MIN_HALF_PIXELS, NORM_RADIUS, agreement,
                          align_images, align_plane, halves_agree, median_apart, normalised_region, partners_apart)
from .stereo_sgbm import SPECKLE_SHARE
from .surfaces import plain_windows

__all__ = ["PlaneFill", "SearchStart", "fill_planes", "plain_regions"]

#: Intensity edges cut the regions: a pixel whose gradient (Sobel, after a Gaussian of 1 px
#: that takes out most of the sensor noise) exceeds this many grey levels per pixel is an
#: edge. An 8-bit photo's noise leaves 0.3-0.5 there; a visible edge or texture, several.
EDGE_GREY_PER_PX = 2.0
#: Regions smaller than this share of image 1 are left alone: a plane from a small region's
#: matches says little beyond them, and small regions are mostly texture, which SGM matches.
MIN_REGION_SHARE = 0.01
#: ...and those where fewer than this share of the pixels matched: the plane must come from
#: the surface itself, not from a patch. Monopoly's black background: 6-12 % matched, a few
#: wrong patches on one plane (filled from a tenth, its rect pair lost 0.010 of precision).
#: The plain walls SGM leaves mostly unmatched hold 24-37 % (Midd1, Midd2, Plastic's lower
#: left corner), and how much a wall gets swings with the pose's last tenths of a pixel
#: (Midd1 conv's wall: 24 % with the true pose, 27 % with the tool's own; rect 37 % and
#: 30 %): a fifth fills them all. At half, these walls stayed 0.03-0.05 of coverage at 1 px
#: below what their fills give them, at no cost in precision (real pairs 0.9526 / 0.8756 ->
#: 0.9529 / 0.8806, p@1 / cov@1), and the own pose's Midd1 rect wall went unfilled (0.031
#: of coverage behind the true pose's). From a quarter: the same, but Midd1 conv's true
#: pose unfilled.
MIN_MATCHED_SHARE = 0.2
#: A region under this share matched is mostly unmatched: its matches are dropped where
#: they lie on no one plane (:data:`MAX_SCATTERED_SUPPORT`).
MOSTLY_UNMATCHED_SHARE = 0.5
#: ...and those whose matches do not mostly lie on one plane: within 1 px of the plane
#: (RANSAC's threshold, the precision the matches are judged at) for at least this share.
#: Below it, a mostly unmatched region's plane is aligned by the intensities instead
#: (:func:`_aligned_surface`): generated seed 88's floor, 13 % matched and 53 % of that on one
#: plane, was neither filled nor dropped (0.637 of coverage at 1 px, DIS 0.641; aligned, 0.704).
#: A mostly matched region's is aligned for the fill alone: seed 21's floor, 55 % matched and
#: 59 % of that on one plane, stayed as SGM left it (0.784, SGBM 0.804; filled, 0.805).
MIN_PLANE_SUPPORT = 0.6
#: A region under :data:`MOSTLY_UNMATCHED_SHARE` matched whose matches mostly lie off one plane
#: (under this share within 1 px of the plane RANSAC finds) holds no surface the matcher
#: found: its matches are patches at several depths, each carried over a plain surface by the
#: aggregation paths from its own noise, and they are dropped. The generated scenes' plain
#: floors under sensor noise: 8-23 % matched, 11-37 % on one plane, their matches 14-16 %
#: right at 1 px (seed 16: 52,279 matches, 0.155 at 1 px and 0.399 at 3 px); Plastic's plain
#: box top: 36 % matched, 33-37 % on one plane. Half: the matches on the plane are no
#: majority. A mostly unmatched region on one plane keeps its matches (Midd1's back wall:
#: 24-37 % matched, 78-89 % on one plane, right), as does one mostly matched over several surfaces.
#: Against 0.6, the fill's own bar (MIN_PLANE_SUPPORT): generated pair 4's wall and floor,
#: one region 41 % matched, 53 % on one plane, lost 0.114 of coverage (its matches 56 % right
#: at 1 px, 92 % at 3 px).
MAX_SCATTERED_SUPPORT = 0.5
#: A region under :data:`MOSTLY_UNMATCHED_SHARE` matched whose plane's matches lie mostly
#: (over half) within this many columns of the first parallax SGM searched holds no surface
#: the matcher found either: OpenCV breaks the ties of a cost without a minimum at its first
#: parallax, the check of the search's ends (:func:`.checks.drop_range_ends`) drops those
#: within a column of it, and the smoothness penalty for a column's step lets a plain surface's
#: ties spread a column or two from there, all on one plane (the first parallax's). Unseen
#: generated seed 148's plain floor under uneven light: 13,125 matches, 8,944 of them on one
#: plane 1.0-2.8 columns from the first parallax (median 1.7), every one over 3 px off, and
#: the fill carried that plane over 17,861 more pixels (the pair 0.896 / 0.939 -> 0.936 /
#: 0.981 at 1 / 3 px). Monopoly's black background: 1.0-3.2 columns, and dropped, its
#: precision at 1 px +0.001-0.006 at the same coverage. The real walls beyond the SIFT points,
#: whose parallax is that far end (Midd1, Midd2: 24-37 % matched, on one plane), lie 5.0-8.1
#: columns from it (medians); seeds 0-99 hold no region on the ties.
TIE_COLUMNS = 3.0
#: In a region under :data:`MOSTLY_UNMATCHED_SHARE` matched whose matches do lie on one plane,
#: the matches off it face the same test: on a second plane (at least
#: :data:`MAX_SCATTERED_SUPPORT` of them within 1 px of one homography) they are a second
#: surface and stay, else they are patches carried over the plain surface and are dropped
#: (their pixels become holes of the plane). Real pairs' back walls (Midd1 conv, Midd2 rect:
#: 21-30 % matched, 80-84 % on one plane): their off-plane matches 1-9 % right at 1 px, 33-39 %
#: on a second plane; a region over a lampshade and the wall beside it (Lampshade2 rect: 46 %
#: matched, 61 % on one plane): its off-plane matches 99 % right, 68 % on a second plane.
#: A second plane within :data:`SNAP_PX` of the first (median over the matches off it) is no
#: second surface but SGM's wave about the first, and its matches go as the patches do (Midd1
#: rect's wall with the tool's own pose: 4,728 matches off the plane, 62 % on a plane 1.35 px
#: from it; kept, they failed the wall's snap, 0.911 / 0.720 at 1 px against the true pose's
#: 0.944 / 0.755; the lampshade beside Lampshade2's wall lies 4.5 px off it).
#: Fewer than this many matches off the plane are too few for a homography (4 points fix one,
#: and RANSAC needs some to spare) and stay.
MIN_OFF_PLANE = 8
#: A mostly unmatched region whose plane the intensities align keeps the matches within
#: :data:`RIM_SNAP_PX` of it and drops the others as SGM's noise about it, except those in
#: front of the plane that join into a patch of at least this share of image 1 (8-neighbours)
#: where image 2 under the plane does not match image 1 (:func:`_nearer_surface`): an object
#: standing before the plain surface with no intensity edge between them. The share is the
#: speckle filter's bar (:data:`.stereo_sgbm.SPECKLE_SHARE`: a patch of under 1/500 of the
#: view is more often a wrong minimum than a surface); matches behind the plane would be seen
#: through it. Generated seeds 1, 8, 29, 66, 68, 75, 76 and 78 (true pose; those of 0-99
#: where such patches are found), the matches off such planes: behind them none right at 1
#: px; in front, in smaller patches 0.00-0.07 (seeds 75, 76 and 78: 0.33-0.65), in patches
#: of that size 0.48-1.00 where the plane's agreement over the patch (its median) was -0.31
#: to 0.71 (seed 66's plain box faces on a plain floor of the same grey: 37,122 matches), and
#: 0.00-0.01 where it was 0.84-0.96 (SGM's blotches on seeds 68's and 78's floors). One patch
#: on seed 78's dark sphere (agreement 0.03, 2,491 matches, none right) stays.
NEARER_SURFACE_SHARE = SPECKLE_SHARE
#: Matches a region's plane (or homography) is fitted from at most (a seeded random subset):
#: it has 3 parameters (8); thousands fix it, millions only cost RANSAC's time.
MAX_FIT_MATCHES = 5000
#: A pixel is filled only inside the plane's matches, not beyond them: where at least this
#: share of the region's pixels within :data:`HOLE_WINDOW` px of it hold a match on the plane.
#: Without it, a plain face that did not match took the plane of the floor it touched (a
#: generated forward pair: 0.849 -> 0.809 at 1 px); at half, Plastic's rectified pair gained
#: half the coverage (+0.018 against +0.035 at 1 px) and less precision (0.816 against 0.820).
#: A tenth: SGM's matches on a plain wall lie in patches over 24-37 % of it, and at a quarter
#: the gaps between patches where the share fell under it stayed open, other gaps with
#: another pose (Midd1 rect: 0.726 of coverage at 1 px with the true pose, 0.700 with the
#: tool's own; at a tenth 0.748 and 0.739). Beyond the matches' reach (half the window) the
#: share is 0 whatever the bar. Real pairs 0.9529 / 0.8806 -> 0.9526 / 0.8844 at 1 px (true
#: pose), generated 0.9222 / 0.6933 -> 0.9225 / 0.6971.
MIN_HOLE_SUPPORT = 0.1
#: ...over a window three matching windows (:data:`.stereo_sgbm.BLOCK`) across.
HOLE_WINDOW = 15
#: Fills that would add fewer than this share of the matches are left out (before the
#: occlusion test, the costliest step): they move no figure at three decimals, and appending
#: them copies every match (0.1-0.2 s for the 2.7 million of the bench pair, which has 589
#: holes to fill).
MIN_FILL_SHARE = 0.001
#: Pixels whose match in image 2 lies this close (px) to where another, nearer match lands
#: are hidden in view 2 and get no fill...
OCCLUSION_PX = 1
#: ...nearer by more than this share of the depth: neighbours on one slanted surface that land
#: on the same pixel of image 2 differ by far less; a surface in front, by more (1 px of
#: parallax is 1.4-6 % of the depth on the real pairs).
HIDDEN_DEPTH_SHARE = 0.01
#: A region is one plane where at least :data:`SNAP_SHARE` of its matches lie within this
#: many px of its plane (:func:`_snap_plane`): SGM's wave around a plain slanted plane reaches 1.7 px
#: (Plastic's box face); a match farther off is another surface's and keeps its own.
SNAP_PX = 2.0
#: ...this share: nearly all. A folded or curved surface that a plane fits in part falls
#: short (Midd1's and Midd2's lampshade: 79-80 %, Bowling1's cloth 74 %; Plastic's box
#: face: 99.7 %). Without this test (every region the fill trusts) the real pairs' means at
#: 1 px came 0.9492 / 0.8823 -> 0.9458 / 0.8793 (Lampshade2 and Bowling1 conv -0.034 to
#: -0.049 of precision).
SNAP_SHARE = 0.95
#: Only matches whose window (:data:`SNAP_WINDOW` square) in image 1 has a grey-value
#: standard deviation below this many levels move: sensor noise and quantisation alone, no
#: signal SGM's cost could follow (Plastic's box face, the Middlebury walls: 0.4-0.5).
#: Where a plain surface still has faint grain (the flower pots' clay, a book's page:
#: 1.3-1.6), SGM follows its curvature, which a plane would flatten (without this test
#: Flowerpots lost 0.004-0.010 of precision at 1 px).
SNAP_LEVELS = 1.0
#: ...the window of SGM's matching cost (:data:`.stereo_sgbm.BLOCK`).
SNAP_WINDOW = 5
#: The plane is fitted again from the matches near the last fit this many times (the first
#: fit from RANSAC's inliers within 1 px): in the test's wave (steps and runs 1.2 px either
#: side) the plane came 0.19 px off at the region's ends after one, 0.03 (least squares' own)
#: after two and three.
SNAP_FITS = 2
#: Plain regions from this many pixels (a 10 px square) up to the large ones
#: (:data:`MIN_REGION_SHARE`) are judged by their rim (:func:`_rim_planes`); smaller ones lie
#: within the 9 x 9 window of the local plane fit (:func:`.surfaces.fit_plain_surfaces`).
MIN_RIM_REGION = 100
#: The rim: the pixels within this many px outside the region. The regions stop a pixel
#: short of their edges (:func:`plain_regions`), so 3 px reach across a 1-2 px edge.
RIM_PX = 3
#: At least this share of the rim must hold a match: a rim matched in part (an occlusion
#: edge, a partner beyond image 2) gives a plane of one side only.
MIN_RIM_MATCHED = 0.5
#: ...and this share of the rim's matches must lie within :data:`SNAP_PX` of their plane: a rim
#: along a depth edge holds two surfaces. SGM's matches along a slanted rim wave about its
#: plane as on a slanted plain surface; within 1 px (the precision judged) the checker squares
#: of a floor seen while moving forward mostly failed it and kept SGM's fronto-parallel
#: patches (forward seed 70: 84 of its 132 small regions; 71 of them with 70-90 % of their
#: rims' matches within 1 px of their plane and 95 % within 2 px, their own matches 32 %
#: within 1 px of the truth).
MIN_RIM_SUPPORT = 0.9
#: The region's own matches within this many px of the rim's plane are on it and move onto it
#: (SGM's matches on a slanted plain region lie 1-3 px off, the generated converging floors'
#: checker squares, often as one fronto-parallel patch: a plane of its own, the wrong one)...
RIM_SNAP_PX = 3.0
#: ...and where fewer than this share of them are, the region holds another surface (a hole
#: showing what lies behind): it is left alone.
MIN_RIM_INNER = 0.5


class PlaneFill(NamedTuple):
    """What :func:`fill_planes` added, and the matches it moved onto their plane."""

    uv1: np.ndarray  #: (N, 2) pixels of image 1 that had no match (COLMAP positions)
    uv2: np.ndarray  #: (N, 2) their partners on the region's plane, on their epipolar lines
    xyz: np.ndarray  #: (N, 3) their points, camera 1's frame
    regions: int  #: regions filled
    moved: np.ndarray  #: (M,) indices of the given matches moved onto their region's plane
    moved_uv2: np.ndarray  #: (M, 2) their new partners in image 2, on their epipolar lines
    moved_xyz: np.ndarray  #: (M, 3) their new points, camera 1's frame
    dropped: np.ndarray  #: (D,) indices of the given matches on no surface (:data:`MAX_SCATTERED_SUPPORT`)


class SearchStart(NamedTuple):
    """Where SGM's search began, for :data:`TIE_COLUMNS`."""

    grid: LineGrid  #: the line images' grid (:func:`.lines.match_parallax` of the matches)
    first: float  #: the first parallax searched (columns, the shifted line image 2's 0)


def plain_regions(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Regions of ``gray`` (H, W) uint8 between its intensity edges (:data:`EDGE_GREY_PER_PX`),
    4-connected: ``(labels (H, W) int32, stats (n, 5))``, label 0 the edges (area 0); ``stats``
    as OpenCV's ``connectedComponentsWithStats`` gives them (left, top, width, height, area)."""
    g = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), 1.0)
    # Sobel's 3x3 kernels weigh 8 grey levels per unit slope
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0) / 8.0
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1) / 8.0
    edge = (cv2.magnitude(gx, gy) > EDGE_GREY_PER_PX).astype(np.uint8)
    edge = cv2.dilate(edge, np.ones((3, 3), np.uint8))  # regions stop a pixel short of the edge
    n, labels, stats, _ = cv2.connectedComponentsWithStats(1 - edge, connectivity=4)
    stats[0, cv2.CC_STAT_AREA] = 0  # the background label of connectedComponents is the edges
    return labels, stats


@njit(cache=True)
def _region_of_matches(uv1, labels):
    """The region label of each match's pixel in image 1 (N,) and the (H, W) int32 index of the
    match at each pixel, -1 where none."""
    h, w = labels.shape
    lab = np.empty(uv1.shape[0], np.int32)
    index = np.full((h, w), -1, np.int32)
    for i in range(uv1.shape[0]):
        x = int(uv1[i, 0])
        y = int(uv1[i, 1])
        lab[i] = labels[y, x]
        index[y, x] = i
    return lab, index


@njit(cache=True)
def _nearest_depth(uv2, X, R, t, w2, h2, skip, uv2_more, X_more):
    """Per pixel of image 2 (h2, w2), the smallest camera-2 depth (``R X + t``) of the matches
    landing in it: ``uv2``, ``X`` (N, 2), (N, 3) but those of the indices ``skip`` (sorted),
    and ``uv2_more``, ``X_more`` (the skipped ones where they land now; no copy of the N)."""
    zbuf = np.full((h2, w2), np.inf, np.float32)
    _add_depths(zbuf, uv2_more, X_more, R, t, np.zeros(0, np.int64))
    _add_depths(zbuf, uv2, X, R, t, skip)
    return zbuf


@njit(cache=True)
def _add_depths(zbuf, uv2, X, R, t, skip):
    """Lower ``zbuf`` (h2, w2) to the camera-2 depths of the matches ``uv2``, ``X`` landing in
    it, in place, but those of the indices ``skip`` (sorted)."""
    h2, w2 = zbuf.shape
    k = 0
    for i in range(uv2.shape[0]):
        if k < len(skip) and skip[k] == i:
            k += 1
            continue
        x = int(uv2[i, 0])
        y = int(uv2[i, 1])
        if 0 <= x < w2 and 0 <= y < h2:
            z = R[2, 0] * X[i, 0] + R[2, 1] * X[i, 1] + R[2, 2] * X[i, 2] + t[2]
            if z < zbuf[y, x]:
                zbuf[y, x] = z


@njit(cache=True)
def _hidden(uv2, z2, zbuf, rel):
    """Whether a nearer surface's match lands within :data:`OCCLUSION_PX` of each ``uv2``
    (nearer: by more than ``rel`` of the depth, :data:`HIDDEN_DEPTH_SHARE`)."""
    h2, w2 = zbuf.shape
    out = np.zeros(uv2.shape[0], np.bool_)
    r = OCCLUSION_PX
    for i in range(uv2.shape[0]):
        x = int(uv2[i, 0])
        y = int(uv2[i, 1])
        for dy in range(-r, r + 1):
            for dx in range(-r, r + 1):
                xx = x + dx
                yy = y + dy
                if 0 <= xx < w2 and 0 <= yy < h2 and zbuf[yy, xx] < z2[i] * (1.0 - rel):
                    out[i] = True
    return out


def _on_lines(F: np.ndarray, uv1: np.ndarray, uv2: np.ndarray) -> np.ndarray:
    """``uv2`` moved to the nearest point of the epipolar line ``F uv1`` (COLMAP positions)."""
    l = np.column_stack([uv1, np.ones(len(uv1))]) @ F.T
    s = (np.einsum("ij,ij->i", l[:, :2], uv2) + l[:, 2]) / np.maximum(np.einsum("ij,ij->i", l[:, :2], l[:, :2]), 1e-300)
    return uv2 - s[:, None] * l[:, :2]


def _homography_support(uv1: np.ndarray, uv2: np.ndarray, idx: np.ndarray, rng: np.random.Generator,
                        seed: int) -> tuple[np.ndarray | None, np.ndarray]:
    """The homography RANSAC finds for the matches ``idx`` (of ``uv1``, ``uv2``: (N, 2)) from
    at most :data:`MAX_FIT_MATCHES` of them, and which of them lie within 1 px of it ((len(idx),)
    bool); (None, all False) where RANSAC finds none. Its 8 parameters follow a gently curved
    surface too (a lampshade): the test of whether matches form a surface at all
    (:func:`_scattered_with`, the second surface of :data:`MIN_OFF_PLANE`), where the plane of
    the scene's 3 (:func:`_plane_support`) would count a curved one as scattered."""
    fit = idx if len(idx) <= MAX_FIT_MATCHES else rng.choice(idx, MAX_FIT_MATCHES, replace=False)
    cv2.setRNGSeed(seed)
    H, _ = cv2.findHomography(uv1[fit], uv2[fit], cv2.RANSAC, 1.0)
    if H is None:
        return None, np.zeros(len(idx), bool)
    return H, _homography_distance(H, uv1[idx], uv2[idx]) <= 1.0


def _homography_distance(H: np.ndarray, uv1: np.ndarray, uv2: np.ndarray) -> np.ndarray:
    """(N,) px: how far each partner ``uv2`` (N, 2) lies from where the homography ``H`` (3, 3)
    takes its pixel ``uv1`` (N, 2) (COLMAP positions)."""
    return np.linalg.norm(cv2.perspectiveTransform(uv1.reshape(-1, 1, 2), H).reshape(-1, 2) - uv2, axis=1)


def _plane_support(pose: _Pose, uv1: np.ndarray, uv2: np.ndarray, z: np.ndarray, idx: np.ndarray,
                   rng: np.random.Generator) -> tuple[np.ndarray | None, np.ndarray]:
    """The plane of the scene (:func:`_inverse_depth_plane`) that RANSAC finds for the matches
    ``idx`` (of ``uv1``, ``uv2``: (N, 2), at camera-1 depths ``z``: (N,)) from at most
    :data:`MAX_FIT_MATCHES` of them, and which of them lie within 1 px of it ((len(idx),)
    bool); (None, all False) where none is found.

    The pose fixes all but 3 of a plane's homography's 8 parameters (:func:`_inverse_depth_plane`):
    fitted with all 8, a plain floor's matches, clustered in a band of it, gave a homography
    within 1 px of the truth on that band only (generated seed 29: 22 % of the floor), and the
    floor's matches counted as scattered over several surfaces."""
    fit = idx if len(idx) <= MAX_FIT_MATCHES else rng.choice(idx, MAX_FIT_MATCHES, replace=False)
    f1, f2 = np.ascontiguousarray(uv1[fit], np.float64), np.ascontiguousarray(uv2[fit], np.float64)
    w = 1.0 / z[fit]
    good = np.flatnonzero(w > 0)
    if len(good) < 3:
        return None, np.zeros(len(idx), bool)
    draws = rng.integers(0, len(good), size=(RANSAC_DRAWS, 3))
    abc = _ransac_plane(f1, f2, w, good[draws], 1.0, *pose)
    if np.isnan(abc[0]):
        return None, np.zeros(len(idx), bool)
    on = _plane_distance(pose, f1, f2, abc) <= 1.0
    refit = _inverse_depth_plane(f1[on], 1.0 / w[on]) if np.count_nonzero(on) >= 3 else None
    if refit is not None and np.count_nonzero(_plane_distance(pose, f1, f2, refit) <= 1.0) >= np.count_nonzero(on):
        abc = refit
    return abc, _plane_distance(pose, uv1[idx], uv2[idx], abc) <= 1.0


def _homography(pose: _Pose, abc: np.ndarray) -> np.ndarray:
    """(3, 3) the homography from image 1 to image 2 that the plane ``abc`` induces (COLMAP positions)."""
    H = pose.K2 @ (pose.R @ pose.K1inv + np.outer(pose.t, abc))
    return H / H[2, 2]


#: Draws of three matches RANSAC tries: a plane among a third of a region's matches (the
#: rest patches at other depths) is drawn with 0.999 confidence in 252 (1 - (1/3)^3 per draw).
RANSAC_DRAWS = 256


@njit(cache=True)
def _ransac_plane(uv1, uv2, w, draws, px, K1inv, R, t, K2):
    """The plane ``(a, b, c)`` (1 / z = a u + b v + c) through three matches of ``draws``
    (D, 3) indices with the most matches within ``px`` of it (NaNs where every draw is
    degenerate)."""
    best = np.full(3, np.nan)
    most = -1
    abc = np.empty(3)
    for d in range(draws.shape[0]):
        i, j, k = draws[d, 0], draws[d, 1], draws[d, 2]
        # w = a u + b v + c through the three, by Cramer's rule on their differences from the first
        du1, dv1, dw1 = uv1[j, 0] - uv1[i, 0], uv1[j, 1] - uv1[i, 1], w[j] - w[i]
        du2, dv2, dw2 = uv1[k, 0] - uv1[i, 0], uv1[k, 1] - uv1[i, 1], w[k] - w[i]
        det = du1 * dv2 - du2 * dv1
        if abs(det) < 1.0:  # (px^2: three pixels on one line)
            continue
        abc[0] = (dw1 * dv2 - dw2 * dv1) / det
        abc[1] = (du1 * dw2 - du2 * dw1) / det
        abc[2] = w[i] - abc[0] * uv1[i, 0] - abc[1] * uv1[i, 1]
        dist = _distance_to_plane(uv1, uv2, abc, K1inv, R, t, K2)
        count = np.count_nonzero(dist <= px)
        if count > most:
            most, best = count, abc.copy()
    return best


def _scattered_with(uv1: np.ndarray, uv2: np.ndarray, repeats: tuple[np.ndarray, np.ndarray], mine: np.ndarray,
                    area: int, seed: int) -> bool:
    """Whether a region's matches (``uv1``, ``uv2``: (N, 2)) and the ``repeats`` of the region
    (``mine``: (M,) bool over them) are together fewer than :data:`MOSTLY_UNMATCHED_SHARE` of
    its ``area`` and under :data:`MAX_SCATTERED_SUPPORT` of them on one plane (RANSAC's
    homography, :func:`_homography_support`, its subset drawn by a generator of its own: the other
    regions' draws stay as they were); False where the region holds no repeat."""
    if not mine.any() or len(uv1) + np.count_nonzero(mine) >= MOSTLY_UNMATCHED_SHARE * area:
        return False
    all1, all2 = np.concatenate([uv1, repeats[0][mine]]), np.concatenate([uv2, repeats[1][mine]])
    _, on = _homography_support(all1, all2, np.arange(len(all1)), np.random.default_rng(seed), seed)
    return bool(np.mean(on) < MAX_SCATTERED_SUPPORT)


def _same_plane(H: np.ndarray, H_off: np.ndarray, uv1: np.ndarray) -> bool:
    """Whether the homographies ``H`` and ``H_off`` give the pixels ``uv1`` (N, 2) of image 1
    partners a median of :data:`SNAP_PX` or less apart: one surface, the second fitted to
    SGM's wave about it (:data:`MIN_OFF_PLANE`)."""
    a, b = (cv2.perspectiveTransform(uv1.reshape(-1, 1, 2), m).reshape(-1, 2) for m in (H, H_off))
    return bool(np.median(np.linalg.norm(a - b, axis=1)) <= SNAP_PX)


def _inverse_depth_plane(uv1: np.ndarray, z: np.ndarray) -> np.ndarray | None:
    """``(a, b, c)``: the plane through the points seen at ``uv1`` (N, 2) at depths ``z`` (N,),
    as the inverse depth 1 / z = a u + b v + c (exact for a plane; least squares in inverse
    depth, to which parallax is proportional); ``None`` where they lie on one line."""
    abc = _fit_inverse_depth(np.ascontiguousarray(uv1, np.float64), np.ascontiguousarray(z, np.float64))
    return None if np.isnan(abc[0]) else abc


@njit(cache=True)
def _fit_inverse_depth(uv1, z):
    """:func:`_inverse_depth_plane`'s least squares about the points' mean; NaNs where they
    lie on one line (the 2 x 2 covariance of the pixels singular)."""
    n = uv1.shape[0]
    out = np.full(3, np.nan)
    if n < 3:
        return out
    mu = mv = mw = 0.0
    for i in range(n):
        mu += uv1[i, 0]
        mv += uv1[i, 1]
        mw += 1.0 / z[i]
    mu, mv, mw = mu / n, mv / n, mw / n
    cuu = cvv = cuv = cuw = cvw = 0.0
    for i in range(n):
        du, dv, dw = uv1[i, 0] - mu, uv1[i, 1] - mv, 1.0 / z[i] - mw
        cuu += du * du
        cvv += dv * dv
        cuv += du * dv
        cuw += du * dw
        cvw += dv * dw
    det = cuu * cvv - cuv * cuv
    if not det > 1e-12 * cuu * cvv:  # (and a zero spread)
        return out
    out[0] = (cuw * cvv - cvw * cuv) / det
    out[1] = (cvw * cuu - cuw * cuv) / det
    out[2] = mw - out[0] * mu - out[1] * mv
    return out


def _on_plane(tv, uv1: np.ndarray, abc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For pixels ``uv1`` (N, 2) and their plane ``abc`` (3,), or each one's (N, 3) (:func:`_inverse_depth_plane`):
    ``(uv2, X, ok)``, the plane's point on each pixel's ray (camera 1's frame), its projection in
    image 2 and whether it lies in front of both cameras."""
    p = np.column_stack([uv1, np.ones(len(uv1))])
    w = (p * abc).sum(axis=1)
    ray = p @ np.linalg.inv(tv.K1).T
    ok = w > 0
    X = ray / np.where(ok, w, 1.0)[:, None] / ray[:, 2:3]
    x2 = (X @ tv.R.T + tv.t) @ tv.K2.T
    ok &= x2[:, 2] > 0
    uv2 = x2[:, :2] / np.where(ok, x2[:, 2], 1.0)[:, None]
    return uv2, X, ok


class _Pose(NamedTuple):
    """The pair's geometry as :func:`_distance_to_plane` takes it (camera 1's inverse once)."""

    K1inv: np.ndarray  #: (3, 3)
    R: np.ndarray  #: (3, 3) camera 2 from camera 1
    t: np.ndarray  #: (3,)
    K2: np.ndarray  #: (3, 3)

    def warp(self) -> tuple[np.ndarray, np.ndarray]:
        """``A = K2 R K1^-1`` (3, 3) and ``e = K2 t`` (3,), as :func:`.plane_align.align_plane` takes
        them: a pixel ``p`` on the plane ``abc`` has its partner at ``q ~ A p + e (p . abc)``."""
        return self.K2 @ self.R @ self.K1inv, self.K2 @ self.t


def _pose(tv) -> _Pose:
    return _Pose(np.linalg.inv(tv.K1), np.asarray(tv.R, np.float64), np.asarray(tv.t, np.float64).ravel(),
                 np.asarray(tv.K2, np.float64))


def _iterated_plane(pose: _Pose, uv1: np.ndarray, uv2: np.ndarray, z: np.ndarray, near: np.ndarray, fits: int,
                    px: float, share: float) -> tuple[np.ndarray | None, np.ndarray]:
    """The plane of the scene (:func:`_inverse_depth_plane`) of matches ``uv1``, ``uv2`` (N, 2)
    at depths ``z`` (N,), fitted from ``near`` (N,) bool, then ``fits`` times from the matches
    within ``px`` of the last plane, where at least ``share`` of them (and 8) lie there each
    time, and those matches; else ``(None, ...)``."""
    for _ in range(fits):
        plane = _inverse_depth_plane(uv1[near], z[near])
        if plane is None:
            return None, near
        near = _plane_distance(pose, uv1, uv2, plane) <= px
        if np.count_nonzero(near) < 8 or np.mean(near) < share:
            return None, near
    return _inverse_depth_plane(uv1[near], z[near]), near


def _snap_plane(pose: _Pose, uv1: np.ndarray, uv2: np.ndarray, z: np.ndarray,
                inliers: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
    """A region's plane of the scene (:func:`_inverse_depth_plane`: 3 parameters, it cannot
    bend to follow part of SGM's wave as a homography's 8 can) and its matches within
    :data:`SNAP_PX` of it, where they are at least :data:`SNAP_SHARE` of the region's matches
    ``uv1``, ``uv2`` (N, 2) at depths ``z`` (N,); else ``(None, ...)``. Fitted from
    ``inliers`` (N,) bool (RANSAC's), then :data:`SNAP_FITS` times from the matches near the
    last plane: the wave's runs beyond 1 px, left out of the first, are in the last."""
    return _iterated_plane(pose, uv1, uv2, z, inliers, SNAP_FITS, SNAP_PX, SNAP_SHARE)


def _in_front(uv1: np.ndarray, z: np.ndarray, abc: np.ndarray) -> np.ndarray:
    """Which of the points seen at ``uv1`` (N, 2) at depths ``z`` (N,) lie nearer camera 1 than
    the plane ``abc`` (:func:`_inverse_depth_plane`): their inverse depth above the plane's
    there; (N,) bool."""
    return 1.0 / z > uv1 @ abc[:2] + abc[2]


def _plane_distance(pose: _Pose, uv1: np.ndarray, uv2: np.ndarray, abc: np.ndarray) -> np.ndarray:
    """(N,) px from each match ``uv2`` to the partner the plane ``abc`` gives ``uv1`` (inf behind a camera)."""
    return _distance_to_plane(np.ascontiguousarray(uv1, np.float64), np.ascontiguousarray(uv2, np.float64),
                              np.asarray(abc, np.float64), *pose)


@njit(cache=True)
def _distance_to_plane(uv1, uv2, abc, K1inv, R, t, K2):
    """:func:`_plane_distance`, as :func:`_on_plane` finds the partners."""
    n = uv1.shape[0]
    out = np.full(n, np.inf)
    for i in range(n):
        u, v = uv1[i, 0], uv1[i, 1]
        w = abc[0] * u + abc[1] * v + abc[2]
        if not w > 0:
            continue
        # the ray's point at inverse depth w (camera 1), in camera 2's frame, in its image
        s = 1.0 / (w * (K1inv[2, 0] * u + K1inv[2, 1] * v + K1inv[2, 2]))
        X0 = (K1inv[0, 0] * u + K1inv[0, 1] * v + K1inv[0, 2]) * s
        X1 = (K1inv[1, 0] * u + K1inv[1, 1] * v + K1inv[1, 2]) * s
        X2 = (K1inv[2, 0] * u + K1inv[2, 1] * v + K1inv[2, 2]) * s
        y0 = R[0, 0] * X0 + R[0, 1] * X1 + R[0, 2] * X2 + t[0]
        y1 = R[1, 0] * X0 + R[1, 1] * X1 + R[1, 2] * X2 + t[1]
        y2 = R[2, 0] * X0 + R[2, 1] * X1 + R[2, 2] * X2 + t[2]
        x2 = K2[2, 0] * y0 + K2[2, 1] * y1 + K2[2, 2] * y2
        if x2 > 0:
            out[i] = np.hypot((K2[0, 0] * y0 + K2[0, 1] * y1 + K2[0, 2] * y2) / x2 - uv2[i, 0],
                              (K2[1, 0] * y0 + K2[1, 1] * y1 + K2[1, 2] * y2) / x2 - uv2[i, 1])
    return out


def _rim_plane(pose: _Pose, uv1: np.ndarray, uv2: np.ndarray, z: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
    """The plane of a rim's matches ``uv1``, ``uv2`` (N, 2) at depths ``z`` (N,), fitted from all,
    then :data:`SNAP_FITS` + 1 times from those within :data:`SNAP_PX` of the last, where at
    least :data:`MIN_RIM_SUPPORT` of them lie there, and those matches (N,) bool; else ``(None, ...)``."""
    return _iterated_plane(pose, uv1, uv2, z, np.ones(len(uv1), bool), SNAP_FITS + 1, SNAP_PX, MIN_RIM_SUPPORT)


def _enclosed(on: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels with a True of ``on`` (H, W) bool on each of their four sides
    along their row and column (or on themselves)."""
    def before(a, axis):
        return np.logical_or.accumulate(a, axis=axis)

    return (before(on, 1) & before(on[:, ::-1], 1)[:, ::-1] & before(on, 0) & before(on[::-1], 0)[::-1])


def _rim_planes(gray1: np.ndarray, tv, pose: _Pose, labels: np.ndarray, stats: np.ndarray, uv1: np.ndarray,
                uv2: np.ndarray, X: np.ndarray, index: np.ndarray, size2: tuple[int, int], *, fill: bool, snap: bool):
    """The small plain regions (:data:`MIN_RIM_REGION` px up to :data:`MIN_REGION_SHARE`) on
    the plane of their rim's matches (:func:`_rim_plane`): the unmatched pixels of a region
    enclosed along their row and column by matches on the plane (``fill``; a band along an
    occlusion or image 2's border is open on one side) take the plane's partner, and the
    region's own matches within :data:`RIM_SNAP_PX` of it move onto it, and so do the rim's
    matches on plain windows (:func:`.surfaces.plain_windows`) outside every region: the band
    between the region and its edge, whose windows hold no more signal than the region's
    (``snap``).

    ``gray1``: (H, W) uint8 image 1; ``tv`` and ``pose`` (:func:`_pose`) the pair's geometry;
    ``labels``, ``stats``: :func:`plain_regions`; ``uv1``, ``uv2`` (N, 2), ``X`` (N, 3) the matches; ``index``
    (H, W) the match at each pixel of image 1 (:func:`_region_of_matches`). Returns
    ``(add1, add2, moved, planes)``: lists of the pixels filled (n, 2) and their partners, of
    the indices of the matches moved and their planes (m, 3), one entry a region.
    """
    h, w = labels.shape
    areas = stats[:, cv2.CC_STAT_AREA]
    small = np.flatnonzero((areas >= MIN_RIM_REGION) & (areas < MIN_REGION_SHARE * h * w))
    add1, add2, moved, planes = [], [], [], []
    if len(small) == 0 or not (fill or snap):
        return add1, add2, moved, planes
    kernel = np.ones((2 * RIM_PX + 1, 2 * RIM_PX + 1), np.uint8)
    plain = plain_windows(gray1) if snap else None
    for k in small:
        x0, y0, bw, bh = stats[k, :4]
        xa, ya, xb, yb = max(x0 - RIM_PX, 0), max(y0 - RIM_PX, 0), min(x0 + bw + RIM_PX, w), min(y0 + bh + RIM_PX, h)
        region = labels[ya:yb, xa:xb] == k
        rim = cv2.dilate(region.view(np.uint8), kernel).view(bool) & ~region
        crop = index[ya:yb, xa:xb]
        ring = crop[rim]
        ring = ring[ring >= 0]
        if len(ring) < max(8, MIN_RIM_MATCHED * np.count_nonzero(rim)):
            continue
        plane, on_rim = _rim_plane(pose, uv1[ring], uv2[ring], X[ring, 2])
        if plane is None:
            continue
        inner = crop[region]
        inner = inner[inner >= 0]
        near = _plane_distance(pose, uv1[inner], uv2[inner], plane) <= RIM_SNAP_PX
        if len(inner) and np.mean(near) < MIN_RIM_INNER:  # another surface inside
            continue
        own = inner[near]
        if snap:  # with the rim's matches without signal outside every region (its band), judged alike
            at = (uv1[ring, 1].astype(np.int64), uv1[ring, 0].astype(np.int64))
            quiet = ring[plain[at] & (labels[at] == 0)]
            onto = np.concatenate([own, quiet[_plane_distance(pose, uv1[quiet], uv2[quiet], plane) <= RIM_SNAP_PX]])
            moved.append(onto)
            planes.append(np.broadcast_to(plane, (len(onto), 3)))
        if not fill:
            continue
        on = np.zeros(region.shape, bool)
        for i in (ring[on_rim], own):
            on[uv1[i, 1].astype(np.int64) - ya, uv1[i, 0].astype(np.int64) - xa] = True
        ys, xs = np.nonzero(region & (crop < 0) & _enclosed(on))
        if len(ys):
            p1, p2 = _fill_partners(tv, pose, plane, xs, ys, xa, ya, size2)
            add1.append(p1)
            add2.append(p2)
    return add1, add2, moved, planes


def _nearer_surface(gray1: np.ndarray, gray2: np.ndarray, pose: _Pose, abc: np.ndarray, labels: np.ndarray,
                    stats: np.ndarray, k: int, uv1: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Which of region ``k``'s matches off its aligned plane ``abc`` (:func:`_inverse_depth_plane`)
    lie on a surface in front of it: nearer than the plane at their pixel, joined (8-neighbours
    in image 1) into a patch of at least :data:`NEARER_SURFACE_SHARE` of image 1's pixels, where
    image 2 under the plane does not match image 1 (the median of :func:`.plane_align.agreement`
    over the patch under :data:`.plane_align.FILL_ZNCC`, the fill's bar: where it does, the
    plane is what both views see). ``gray1``: (H, W) uint8 image 1; ``gray2``: (H2, W2) float32
    image 2; ``labels``, ``stats``: :func:`plain_regions`;
    ``uv1`` (N, 2) COLMAP positions, ``z`` (N,) their depths; (N,) bool."""
    out = np.zeros(len(uv1), bool)
    nearer = _in_front(uv1, z, abc)
    x0, y0, bw, bh = stats[k, :4]
    px = uv1[nearer].astype(np.int64) - [x0, y0]  # (the region's matches: within its box)
    mask = np.zeros((bh, bw), np.uint8)
    mask[px[:, 1], px[:, 0]] = 1
    n, patch, sizes, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    large = np.flatnonzero(sizes[:, cv2.CC_STAT_AREA] >= NEARER_SURFACE_SHARE * gray1.size)
    large = large[large > 0]  # (0: the background)
    if len(large) == 0:
        return out
    masks = tuple(patch == j for j in large)
    region = labels[y0:y0 + bh, x0:x0 + bw] == k
    z_patches = agreement(gray1, gray2, _homography(pose, abc), x0, y0, region, masks)
    front = np.zeros(n, bool)
    front[large] = [not _median_over(zz, m) >= FILL_ZNCC for zz, m in zip(z_patches, masks)]
    out[nearer] = front[patch[px[:, 1], px[:, 0]]]
    return out


def _nearer_to(these: np.ndarray, those: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool of ``shape``: the pixels nearer to one of the pixels ``these`` (N, 2) than to any
    of ``those`` (M, 2) (COLMAP positions of image 1; Euclidean distance)."""
    def distance(uv):
        m = np.full(shape, 255, np.uint8)
        p = uv.astype(np.int64)
        m[p[:, 1], p[:, 0]] = 0
        return cv2.distanceTransform(m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return distance(these) < distance(those)


def _second_surface(gray1: np.ndarray, gray2: np.ndarray, pose: _Pose, labels: np.ndarray, stats: np.ndarray,
                    k: int, uv1: np.ndarray, uv2: np.ndarray, idx: np.ndarray, abc: np.ndarray,
                    to_plane: np.ndarray, candidates: np.ndarray, support: float,
                    seed: int) -> tuple[np.ndarray, np.ndarray] | None:
    """A second surface in mostly unmatched region ``k`` beside its aligned plane ``abc``
    (the module's docstring): ``(theirs, near)``, the pixels of image 1 nearer to its matches
    than to the plane's ((H, W) bool), and which of the region's matches ``idx`` are its:
    within :data:`RIM_SNAP_PX` of it and nearer to it than to the plane ((len(idx),) bool).
    It is sought among the ``candidates`` ((len(idx),) bool: the matches the plane would drop,
    off it and in front of it in no large patch) and fitted as the second surface of
    :data:`MIN_OFF_PLANE`. None where they are too few, lie on no one surface (under
    ``support``, the share of the region's matches on its plane, or
    :data:`MAX_SCATTERED_SUPPORT`, within 1 px of one homography: no more scattered than the
    region's matches about the plane), on the plane's wave (:func:`_same_plane`), or where
    image 2 under the plane agrees with image 1 there as well as under the surface (the
    median over its pixels where either agrees, :data:`.plane_align.FILL_ZNCC`: elsewhere
    neither says anything, hidden in view 2 or beyond it; at least one window's pixels,
    :data:`.plane_align.NORM_RADIUS`). ``to_plane``: (len(idx),) px, the matches' distances
    from the plane (:func:`_plane_distance`); ``gray1``: (H, W) uint8; ``gray2``:
    (H2, W2) float32; ``labels``, ``stats``: :func:`plain_regions`; ``uv1``, ``uv2``: (N, 2)
    the matches.

    Generated seed 26: a pillar's plain face and the plain floor it stands on are one region,
    46,280 matches, 43 % on the face's plane (RANSAC's), which aligns. The floor's 28,743
    matches scatter (25 % over 3 px off), and without this step those off the face's plane were
    dropped and its fill reached 19,165 pixels, 58 % of them over 3 px off. Over the floor's
    pixels where either agrees, image 2 under the floor's homography correlates at 0.969
    (median) against 0.696 under the face's plane. On zoom seed 47 the same test keeps the
    aligned plane (0.941 against 0.892), whose fill there is right, and on seed 66 the
    floor's (0.923 against 0.894)."""
    off = idx[candidates]
    if len(off) < MIN_OFF_PLANE:
        return None
    # (a generator of its own: the other regions' draws stay as they were)
    H_off, on_second = _homography_support(uv1, uv2, off, np.random.default_rng(seed), seed)
    if (H_off is None or np.mean(on_second) < min(MAX_SCATTERED_SUPPORT, support)
            or _same_plane(_homography(pose, abc), H_off, uv1[off])):
        return None
    to_second = _homography_distance(H_off, uv1[idx], uv2[idx])
    near = (to_second <= RIM_SNAP_PX) & (to_second < to_plane)
    theirs = _nearer_to(uv1[idx[near]], uv1[idx[(to_plane <= RIM_SNAP_PX) & ~near]], labels.shape)
    x0, y0, bw, bh = stats[k, :4]
    region = labels[y0:y0 + bh, x0:x0 + bw] == k
    part = region & theirs[y0:y0 + bh, x0:x0 + bw]
    image1 = normalised_region(gray1, x0, y0, region)
    z_plane, z_second = (agreement(gray1, gray2, H, x0, y0, region, (part,), image1=image1)[0]
                         for H in (_homography(pose, abc), H_off))
    shown = part & ((z_plane >= FILL_ZNCC) | (z_second >= FILL_ZNCC))  # (NaN: under half a window)
    if np.count_nonzero(shown) < (2 * NORM_RADIUS + 1) ** 2:  # (fewer: one window's verdict)
        return None
    if not _median_over(z_second, shown) > _median_over(z_plane, shown):
        return None
    return theirs, near


def _among_plane_matches(labels: np.ndarray, stats: np.ndarray, k: int, on1: np.ndarray):
    """Over region ``k``'s bounding box and a :data:`HOLE_WINDOW` window's reach around it:
    ``(x0, y0, region, among)``, the box's top-left pixel, which of its pixels are the
    region's, and which have at least :data:`MIN_HOLE_SUPPORT` of the region's pixels in
    their window holding one of the matches ``on1`` (N, 2) (those on its plane, image 1):
    the pixels among the plane's matches, not a surface beyond them ((h, w) bool each)."""
    h, w = labels.shape
    m = HOLE_WINDOW // 2
    x0, y0, bw, bh = stats[k, :4]
    x0, y0, x1, y1 = max(x0 - m, 0), max(y0 - m, 0), min(x0 + bw + m, w), min(y0 + bh + m, h)
    region = (labels[y0:y1, x0:x1] == k).astype(np.float32)
    on = np.zeros_like(region)
    inl = on1.astype(np.int64)
    on[inl[:, 1] - y0, inl[:, 0] - x0] = 1.0
    win = (HOLE_WINDOW, HOLE_WINDOW)
    among = (cv2.boxFilter(on, -1, win, normalize=False)
             >= MIN_HOLE_SUPPORT * cv2.boxFilter(region, -1, win, normalize=False))
    return x0, y0, region > 0, among


def _agreeing(gray1: np.ndarray, gray2: np.ndarray, pose: _Pose, abc: np.ndarray, x0: int, y0: int,
              region: np.ndarray, among: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where image 2 warped by a region's aligned plane ``abc`` matches image 1
    (:func:`.plane_align.agreement`; the box at ``(x0, y0)`` of :func:`_among_plane_matches`,
    ``region`` and ``among`` (h, w) bool over it): the pixels of the region beyond its matches
    (not ``among`` them) where it does at least :data:`.plane_align.FILL_ZNCC` over those
    pixels, provided it does so on the pixels among them (their median), and the correlation
    about each pixel over all the region's ((h, w) bool and float32). ``gray1``: the (H, W)
    uint8 image 1; ``gray2``: the (H2, W2) float32 image 2."""
    on, beyond = region & among, region & ~among
    z_on, z_beyond, z_region = agreement(gray1, gray2, _homography(pose, abc), x0, y0, region, (on, beyond, region))
    if not _median_over(z_on, on) >= FILL_ZNCC:  # (an alignment image 2 bears out less)
        return np.zeros_like(region), z_region
    return beyond & (z_beyond >= FILL_ZNCC), z_region


def _at_ties(start: SearchStart, tv, uv1: np.ndarray, uv2: np.ndarray) -> bool:
    """Whether over half of the matches ``uv1``, ``uv2`` (N, 2) lie within :data:`TIE_COLUMNS`
    of the first parallax searched (``start``)."""
    if len(uv1) == 0:
        return False
    d = match_parallax(start.grid, tv, uv1, uv2)
    return bool(np.count_nonzero(d < start.first + TIE_COLUMNS) > 0.5 * len(d))


def _median_over(z: np.ndarray, mask: np.ndarray) -> float:
    """The median of the correlations ``z`` (h, w) over ``mask``'s pixels (h, w) bool where
    they are defined (:func:`.plane_align.agreement`'s NaN: under half a window); NaN, which
    reaches no bar, where none is."""
    v = z[mask]
    v = v[~np.isnan(v)]
    return float(np.median(v)) if len(v) else np.nan


#: A match off an aligned plane is noise about it where at least this share of the region's
#: matches in the window about it (the correlation's, :data:`.plane_align.NORM_RADIUS`) lie
#: on the plane (within :data:`.plane_align.AGREE_PX`) or off it on the other side: SGM's
#: noise scatters both ways about the plane, while a curved surface leaving it goes one way,
#: most of its matches there off it on that side (Lampshade2 rect's shade, own pose: 12,000
#: right matches 1-2 px off its aligned plane, where image 2 under the plane still
#: correlates at 0.8 or more over its faint texture).
NOISE_NEIGHBOURS_ON = 0.5


def _noise_about(pose: _Pose, uv1: np.ndarray, uv2: np.ndarray, z_depth: np.ndarray, abc: np.ndarray, x0: int,
                 y0: int, shape: tuple[int, int], z: np.ndarray) -> np.ndarray:
    """Which of a mostly matched region's matches ``uv1``, ``uv2`` (N, 2, pixels of image 1
    within the box at ``(x0, y0)`` of ``shape``; ``z_depth`` (N,) their depths) are SGM's
    noise about its aligned plane ``abc``: off it by :data:`.plane_align.AGREE_PX` to
    :data:`RIM_SNAP_PX`, where image 2 under it matches image 1 about them (``z``, the box's
    correlations from :func:`_agreeing`, at least :data:`.plane_align.FILL_ZNCC`) and most
    matches about them lie on it or off it on the other side
    (:data:`NOISE_NEIGHBOURS_ON`), in a region whose matches mostly lie on it
    (:data:`MIN_PLANE_SUPPORT`): (N,) bool. On a weakly textured floor SGM leaves blotches
    1-3 px off (generated seed 13's: 19,000 matches, 1 % of them within 1 px of the truth)."""
    d = _plane_distance(pose, uv1, uv2, abc)
    on = d <= AGREE_PX
    if np.mean(on) < MIN_PLANE_SUPPORT:  # (no one plane the region's matches lie on)
        return np.zeros(len(uv1), bool)
    nearer = _in_front(uv1, z_depth, abc)  # (else farther)
    iy, ix = uv1[:, 1].astype(np.int64) - y0, uv1[:, 0].astype(np.int64) - x0
    win = (2 * NORM_RADIUS + 1, 2 * NORM_RADIUS + 1)

    def count(which):
        img = np.zeros(shape, np.float32)
        img[iy, ix] = which
        return cv2.boxFilter(img, -1, win, normalize=False)[iy, ix]

    n_on, n_near, n_far = count(on), count(~on & nearer), count(~on & ~nearer)
    # the matches on the plane and those off it on the other side: SGM's noise scatters both ways
    n_opposite = np.where(nearer, n_far, n_near)
    share = (n_on + n_opposite) / np.maximum(count(np.ones(len(uv1), bool)), 1.0)
    return ~on & (d <= RIM_SNAP_PX) & (z[iy, ix] >= FILL_ZNCC) & (share >= NOISE_NEIGHBOURS_ON)


#: Pixels a region's plane is aligned on at most (a seeded random subset of those among its
#: matches, :func:`_aligned_surface`): 3 parameters, and tens of thousands of pixels of a
#: plain floor fix them to hundredths of a pixel; every pixel would cost the time of the
#: whole image's.
MAX_ALIGN_PIXELS = 40000


#: Where a plane aligned on the pixels among a region's matches fails the halves test
#: (:func:`.plane_align.halves_agree`), the test is asked again over those pixels and the
#: region's pixels where image 2 under the plane agrees (:func:`_agreeing`), if these are at
#: least this many times as many: each half's plane is fixed by the pixels it spans, and those
#: among a mostly unmatched region's matches can be a cluster whose halves' tilts carry
#: their partners apart beyond it. Generated seed 8's floor: 15,573 pixels among the
#: matches, its halves' planes 1.17 px apart (median, over 1 px: no plane), 121,367 where
#: image 2 agrees, 0.28-0.64 px apart, the plane aligned there 0.01 px from the truth
#: (median). Twice: a set hardly wider brings no new pixels to fix the tilts. Asked again, the
#: halves also pass where each half's plane gives its own pixels the whole plane's partners
#: (``each_own`` of :func:`.plane_align.halves_agree`): seed 16's floor, at a grazing angle,
#: its halves' planes still 1.65 px apart over the 40,000 pixels, each 0.09 and 0.80 px from
#: the whole plane on its own, the plane 0.08 px from the truth. Not at the first asking: the
#: wider set fixes a better plane where its halves agree (seed 8's: 0.37 px off among the
#: matches, 0.01 px over where image 2 agrees).
WIDEN_AGREEING = 2.0


def _align_pixels(mask: np.ndarray, x0: int, y0: int, rng: np.random.Generator) -> np.ndarray:
    """The pixels of ``mask`` (h, w) bool (the box at ``(x0, y0)``) a plane is aligned on: at most
    :data:`MAX_ALIGN_PIXELS`, a seeded subset; (N, 2) COLMAP positions."""
    ys, xs = np.nonzero(mask)
    if len(ys) > MAX_ALIGN_PIXELS:
        pick = np.sort(rng.choice(len(ys), MAX_ALIGN_PIXELS, replace=False))
        ys, xs = ys[pick], xs[pick]
    return np.column_stack([xs + x0 + 0.5, ys + y0 + 0.5])


def _aligned_on(gray1: np.ndarray, gray2: np.ndarray, A: np.ndarray, e: np.ndarray, x0: int, y0: int,
                mask: np.ndarray, abc: np.ndarray, rng: np.random.Generator, *,
                each_own: bool = False) -> tuple[np.ndarray, bool]:
    """The plane ``abc`` aligned on the pixels of ``mask`` (h, w) bool (the box at ``(x0, y0)``,
    :func:`_align_pixels`) and whether its halves agree there (:func:`.plane_align.halves_agree`,
    ``each_own`` passed on)."""
    px = _align_pixels(mask, x0, y0, rng)
    images = align_images(gray1, gray2, px)
    aligned = align_plane(images, A, e, px, abc)
    return aligned, halves_agree(images, A, e, px, aligned, each_own=each_own)


def _aligned_surface(gray1: np.ndarray, gray2: np.ndarray, pose: _Pose, x0: int, y0: int,
                     region: np.ndarray, among: np.ndarray, abc: np.ndarray,
                     rng: np.random.Generator) -> np.ndarray | None:
    """A region's plane ``abc`` aligned by the images' intensities (:func:`.plane_align.align_plane`)
    on its pixels among its matches on that plane (``x0``, ``y0``, ``region``, ``among``: the
    box of :func:`_among_plane_matches`), where its halves agree on it
    (:func:`.plane_align.halves_agree`; failing that, on those pixels and where image 2 under
    it agrees, each half then on its own pixels, :data:`WIDEN_AGREEING`) and image 2 warped
    by it matches image 1 on those pixels (the median of :func:`.plane_align.agreement` at
    least :data:`.plane_align.ALIGNED_ZNCC`); else None. ``gray1``: the (H, W) uint8 grey image 1;
    ``gray2``: the (H2, W2) float32 grey image 2."""
    on = region & among
    if np.count_nonzero(on) < 2 * MIN_HALF_PIXELS:  # (matches too sparse for any pixel: no halves to compare)
        return None
    A, e = pose.warp()
    aligned, agree = _aligned_on(gray1, gray2, A, e, x0, y0, on, abc, rng)
    if not agree:
        # the pixels among the matches may span too little of the surface for its halves'
        # planes (WIDEN_AGREEING): judged again over where image 2 under the plane agrees
        wide = on | _agreeing(gray1, gray2, pose, aligned, x0, y0, region, among)[0]
        if np.count_nonzero(wide) < WIDEN_AGREEING * np.count_nonzero(on):
            return None
        aligned, agree = _aligned_on(gray1, gray2, A, e, x0, y0, wide, aligned, rng, each_own=True)
        if not agree:
            return None
    z_on, = agreement(gray1, gray2, _homography(pose, aligned), x0, y0, region, (on,))
    return aligned if _median_over(z_on, on) >= ALIGNED_ZNCC else None


#: A mostly unmatched region whose matches the matcher found no surface in (dropped: on no
#: one plane, or on the ties at the search's first parallax) may be part of a surface another
#: region shows, a floor or wall that objects standing on it cut into several regions: the
#: planes of the regions filled (:func:`_borrowed_plane`) are aligned on its pixels in turn,
#: and the one image 2 bears out best is kept where its halves agree. Generated seed 148's
#: floor right of a box: 62,193 pixels, its matches on the ties, dropped; the plane of the
#: floor left of the box, 0.69 px off there (median), aligned to 0.28 px (98 % of its pixels
#: within 1 px), image 2 under it correlating at 0.94 (median).
#: An alignment is kept where aligning it again from where it ended moves its partners by at
#: most this many px (median): a start 12 px off stopped 1.7 px from the truth after one
#: alignment (:data:`.plane_align.ITERATIONS` steps a level), correlating at 0.91 over the
#: shading of that floor, and reached 0.28 px with one more; a converged plane moves by
#: hundredths (a tenth of the precision the matches are judged at).
CONVERGED_PX = 0.1
#: ...within this many alignments after the first (else it is no plane of the region's).
MAX_REALIGN = 3


def _borrowed_plane(gray1: np.ndarray, gray2: np.ndarray, pose: _Pose, x0: int, y0: int, region: np.ndarray,
                    starts: list, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray] | None:
    """The plane of ``starts`` (each (3,), :func:`_inverse_depth_plane`) that, aligned on the
    pixels of ``region`` ((h, w) bool, the box at ``(x0, y0)``, :func:`_align_pixels`) until it
    converges (:data:`CONVERGED_PX`), has halves that agree (:func:`.plane_align.halves_agree`)
    and image 2 under it matching image 1 best there (the median of
    :func:`.plane_align.agreement`, at least :data:`.plane_align.ALIGNED_ZNCC`), with that
    agreement over the region ((h, w) float32); None where none does. Starts within
    :data:`.plane_align.AGREE_PX` of one tried are skipped. ``gray1``: (H, W) uint8;
    ``gray2``: (H2, W2) float32."""
    if np.count_nonzero(region) < 2 * MIN_HALF_PIXELS:
        return None
    px = _align_pixels(region, x0, y0, rng)
    p = np.column_stack([px, np.ones(len(px))])
    A, e = pose.warp()
    images = align_images(gray1, gray2, px)
    image1 = normalised_region(gray1, x0, y0, region)
    best, best_z, tried = None, ALIGNED_ZNCC, []  # (best: the plane and its agreement)
    for start in starts:
        if any(median_apart(A, e, p, start, t) <= AGREE_PX for t in tried):
            continue
        tried.append(start)
        cur = _converged(images, A, e, px, start)
        if cur is None or not halves_agree(images, A, e, px, cur):
            continue
        z, = agreement(gray1, gray2, _homography(pose, cur), x0, y0, region, (region,), image1=image1)
        med = _median_over(z, region)
        if med >= best_z:
            best, best_z = (cur, z), med
    return best


def _converged(images, A: np.ndarray, e: np.ndarray, px: np.ndarray, start: np.ndarray) -> np.ndarray | None:
    """The plane ``start`` (3,) aligned on the pixels ``px`` (N, 2) (``images``, ``A``, ``e`` of
    :func:`.plane_align.align_plane`) until it converges (:data:`CONVERGED_PX`, at most
    :data:`MAX_REALIGN` alignments after the first); None where it does not."""
    p = np.column_stack([px, np.ones(len(px))])
    cur = align_plane(images, A, e, px, start)
    for _ in range(MAX_REALIGN):
        nxt = align_plane(images, A, e, px, cur)
        moved, cur = median_apart(A, e, p, cur, nxt), nxt
        if moved <= CONVERGED_PX:
            return cur
    return None


def _realigned_apart(gray1: np.ndarray, gray2: np.ndarray, pose: _Pose, abc: np.ndarray, x0: int, y0: int,
                     mask: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """How far (px) the partners of the plane ``abc`` lie from those of the plane it converges
    onto when aligned on the pixels of ``mask`` (h, w) bool alone (the box at ``(x0, y0)``,
    :func:`_align_pixels`, :func:`_converged`), at each of those pixels ((n,), in the order of
    ``mask[mask]``); all zero where it does not converge (pixels too few or too thin to fix a
    plane: nothing against ``abc``). ``gray1``: (H, W) uint8; ``gray2``: (H2, W2) float32."""
    px = _align_pixels(mask, x0, y0, rng)
    A, e = pose.warp()
    own = _converged(align_images(gray1, gray2, px), A, e, px, abc)
    ys, xs = np.nonzero(mask)
    if own is None:
        return np.zeros(len(ys))
    return partners_apart(A, e, np.column_stack([xs + x0 + 0.5, ys + y0 + 0.5, np.ones(len(ys))]), abc, own)


def _fill_partners(tv, pose: _Pose, abc: np.ndarray, xs: np.ndarray, ys: np.ndarray, x0: int, y0: int,
                   size2: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The pixels ``(xs + x0, ys + y0)`` of image 1 (COLMAP positions, (N, 2)) and the partners the
    plane ``abc`` gives them on their epipolar lines, those within image 2 (``size2`` (w, h))."""
    p1 = np.column_stack([xs + x0 + 0.5, ys + y0 + 0.5])
    p2 = _on_lines(tv.F, p1, cv2.perspectiveTransform(p1.reshape(-1, 1, 2), _homography(pose, abc)).reshape(-1, 2))
    inside = (p2[:, 0] >= 0) & (p2[:, 0] < size2[0]) & (p2[:, 1] >= 0) & (p2[:, 1] < size2[1])
    return p1[inside], p2[inside]


def fill_planes(gray1: np.ndarray, size2: tuple[int, int], tv, uv1: np.ndarray, uv2: np.ndarray, X: np.ndarray,
                *, fill: bool = True, snap: bool = True, drop: bool = True, rims: bool = True,
                borrow: bool = True, two: bool = True, gray2: np.ndarray | None = None,
                repeats: tuple[np.ndarray, np.ndarray] | None = None, start: SearchStart | None = None,
                seed: int = 0) -> PlaneFill:
    """Partners for the unmatched pixels of image 1's large plain regions whose matches lie on
    one plane, or whose plane the intensities align (``fill``: among those matches, and for an
    aligned plane beyond them where image 2 under it agrees, :func:`_agreeing`), for
    the matches without signal of the regions that are one plane
    all through (``snap``, :data:`SNAP_PX`) and those 1-3 px off an aligned plane where image
    2 under it agrees (:data:`.plane_align.AGREE_PX`, :data:`RIM_SNAP_PX`), and the matches of
    the regions mostly unmatched
    whose matches lie on no one plane, and those off their plane on no second one, to drop
    (``drop``, :data:`MAX_SCATTERED_SUPPORT`, :data:`MIN_OFF_PLANE`);
    with ``rims``, the same fill and move for the small regions from their rim's plane
    (:func:`_rim_planes`); with ``two``, a second surface beside a mostly unmatched region's
    aligned plane kept apart from it (:func:`_second_surface`). A region's matches are also
    dropped where, judged together with the ``repeats`` (:data:`MAX_SCATTERED_SUPPORT`), they
    lie on no one plane, and where it is mostly unmatched and its plane is the ties at the
    ``start`` of the search (:data:`TIE_COLUMNS`).

    Args:
        gray1: (H, W) uint8 image 1 (working size).
        size2: (w, h) of image 2.
        tv: the pair's geometry (:class:`.geometry.two_view.TwoView`: ``K1``, ``K2``, ``R``, ``t``, ``F``).
        uv1, uv2: (N, 2) the matches, COLMAP positions, at most one per pixel of image 1.
        X: (N, 3) their points (camera 1's frame), for what they hide in view 2.
        repeats: (M, 2) and (M, 2), the partners SGM found that the repeat check
            (:mod:`.periodic`) dropped: part of what the matcher found on a plain region.
            Its stripes taken out, a striped plain wall's few matches left beside the objects
            in front of it lie mostly on one plane, while all that SGM found there does not.
        start: where SGM's search began (None: no test of ties).
    Returns the added matches, the moved ones and the ones to drop (:class:`PlaneFill`); the
    arguments are not changed.
    """
    from ..geometry.triangulate import triangulate

    h, w = gray1.shape
    labels, stats = plain_regions(gray1)
    areas = stats[:, cv2.CC_STAT_AREA]
    big = np.flatnonzero(areas >= MIN_REGION_SHARE * h * w)
    none2, none3 = np.zeros((0, 2)), np.zeros((0, 3))
    empty = PlaneFill(none2, none2, none3, 0, np.zeros(0, np.int64), none2, none3, np.zeros(0, np.int64))
    if len(uv1) == 0 or not (fill or snap or drop):
        return empty
    lab, index = _region_of_matches(np.ascontiguousarray(uv1), labels)
    rep_lab = _region_of_matches(np.ascontiguousarray(repeats[0]), labels)[0] if drop and repeats is not None else None
    pose = _pose(tv)
    quiet = quiet_windows(gray1, SNAP_WINDOW, SNAP_LEVELS) if snap else None
    rng = np.random.default_rng(seed)
    image2 = functools.cache(lambda: gray2.astype(np.float32))  # (for the aligned planes alone)
    add1, add2, moved, planes, dropped = [], [], [], [], []
    known, orphans = [], []  # (area, plane) of the regions filled; the regions whose matches were all dropped
    for k in big:
        idx = np.flatnonzero(lab == k)
        few = len(idx) < MOSTLY_UNMATCHED_SHARE * areas[k]
        fillable = len(idx) >= MIN_MATCHED_SHARE * areas[k]
        if (few and not drop and not fillable) or len(idx) < 4:
            continue
        abc, on_plane = _plane_support(pose, uv1, uv2, X[:, 2], idx, rng)
        if abc is None:
            continue
        support = np.mean(on_plane)  # (judged on every match of the region, before any is dropped)
        # all that SGM found there, its matches and the repeat check's drops, on no one plane:
        # no surface the matcher found, and texture repeating along the lines, where a plane
        # the intensities align can be a period off or SGM's own wrong surface (generated seed
        # 6 at 1600x1200: a floor's plane aligned at a median ZNCC of 0.991, 15 px off)
        if few and rep_lab is not None and _scattered_with(uv1[idx], uv2[idx], repeats, rep_lab == k, areas[k], seed):
            dropped.append(idx)
            orphans.append(k)
            continue
        if few and start is not None and _at_ties(start, tv, uv1[idx[on_plane]], uv2[idx[on_plane]]):
            if drop:  # its plane is the search's first parallax: ties, no surface found
                dropped.append(idx)
                orphans.append(k)
            continue
        aligned = None
        if support < MIN_PLANE_SUPPORT and gray2 is not None and (few or fill):
            # too little on one plane for the fill from the matches: the intensities may fix it
            # (a mostly matched region's only for the fill: its matches, SGM's on a surface it found, stay)
            aligned = _aligned_surface(gray1, image2(), pose,
                                       *_among_plane_matches(labels, stats, k, uv1[idx[on_plane]]),
                                       abc, np.random.default_rng(seed))  # (the other regions' draws stay)
            if aligned is not None:
                abc = aligned
        if few and support < MAX_SCATTERED_SUPPORT and aligned is None:  # no surface the matcher found
            if drop:
                dropped.append(idx)
                orphans.append(k)
            continue
        theirs = None  # (H, W) bool: a second surface's part of the region, not the aligned plane's
        if few and aligned is not None:
            # one plane under the region's noise: its matches near it move onto it, the rest go,
            # but a surface in front of the plane, off it, stays, and so does a second surface
            to_plane = _plane_distance(pose, uv1[idx], uv2[idx], abc)
            on_plane = to_plane <= RIM_SNAP_PX
            keep = on_plane.copy()
            if drop:
                off = np.flatnonzero(~on_plane)
                keep[off] = _nearer_surface(gray1, image2(), pose, abc, labels, stats, k, uv1[idx[off]],
                                            X[idx[off], 2])
            second = _second_surface(gray1, image2(), pose, labels, stats, k, uv1, uv2, idx, abc, to_plane, ~keep,
                                     support, seed) if two else None
            if second is not None:  # (its matches near it, in its part, stay as SGM left them)
                theirs, near = second
                p = uv1[idx].astype(np.int64)
                stay = near & theirs[p[:, 1], p[:, 0]]
                keep |= stay
                on_plane &= ~stay
            if drop:
                gone = uv1[idx[~keep]].astype(np.int64)
                dropped.append(idx[~keep])
                index[gone[:, 1], gone[:, 0]] = -1
                idx, on_plane = idx[keep], on_plane[keep]
            if snap:
                moved.append(idx[on_plane])
                planes.append(np.broadcast_to(abc, (int(on_plane.sum()), 3)))
        elif few and drop and np.count_nonzero(~on_plane) >= MIN_OFF_PLANE:
            # the matches off the region's plane: a second surface (kept) or patches (dropped)
            off = idx[~on_plane]
            H_off, on_second = _homography_support(uv1, uv2, off, rng, seed)
            if (H_off is None or np.mean(on_second) < MAX_SCATTERED_SUPPORT
                    or _same_plane(_homography(pose, abc), H_off, uv1[off])):
                dropped.append(off)
                idx, on_plane = idx[on_plane], on_plane[on_plane]
                gone = uv1[off].astype(np.int64)  # their pixels are holes of the plane now
                index[gone[:, 1], gone[:, 0]] = -1
        if aligned is None and not fillable:  # nothing to fill or snap: the matches stay
            continue
        if aligned is None and (support < MIN_PLANE_SUPPORT or not (fill or snap)):
            continue
        if snap and aligned is None:
            own1 = uv1[idx]  # the region's matches in image 1
            plane, near = _snap_plane(pose, own1, uv2[idx], X[idx, 2], on_plane)
            if plane is not None:
                near &= quiet[own1[:, 1].astype(np.int64), own1[:, 0].astype(np.int64)]
                moved.append(idx[near])
                planes.append(np.broadcast_to(plane, (int(near.sum()), 3)))
        if not fill:
            continue
        # holes of the plane's matches, not a surface beyond them (MIN_HOLE_SUPPORT)
        x0, y0, region, among = _among_plane_matches(labels, stats, k, uv1[idx[on_plane]])
        if theirs is not None:
            region = region & ~theirs[y0:y0 + region.shape[0], x0:x0 + region.shape[1]]
        unmatched = region & (index[y0:y0 + region.shape[0], x0:x0 + region.shape[1]] < 0)
        ys, xs = np.nonzero(unmatched & among)
        if aligned is None and gray2 is not None and len(ys) >= MIN_FILL_SHARE * len(uv1):
            # the fill's plane aligned where its halves agree (not for a fill too small to keep)
            aligned = _aligned_surface(gray1, image2(), pose, x0, y0, region, among, abc,
                                       np.random.default_rng(seed))  # (the other regions' draws stay)
            if aligned is not None:
                abc = aligned
        if aligned is not None:  # an aligned plane also beyond its matches, where image 2 under it agrees
            agree, z = _agreeing(gray1, image2(), pose, abc, x0, y0, region, among)
            beyond = unmatched & agree
            if np.count_nonzero(beyond) >= 2 * MIN_HALF_PIXELS:  # (fewer fix no plane: their fill stays)
                # those pixels, aligned on alone, may converge onto another plane (a median over the
                # precision the matches are judged at): a second surface the region holds with no
                # edge between them, whose shading correlates under the wrong plane too (generated
                # seed 3 at 1600x1200: a box's right face, 1.51 px off the left face's plane
                # realigned there, its fill 79 % over 3 px off). They are filled only where the two
                # planes agree.
                apart = _realigned_apart(gray1, image2(), pose, abc, x0, y0, beyond, np.random.default_rng(seed))
                if np.median(apart) > AGREE_PX:
                    agree[beyond] &= apart <= AGREE_PX
            ys, xs = np.nonzero(unmatched & (among | agree))
            if snap and not few:  # (a mostly unmatched region's matches near it moved above)
                near = _noise_about(pose, uv1[idx], uv2[idx], X[idx, 2], abc, x0, y0, region.shape, z)
                moved.append(idx[near])
                planes.append(np.broadcast_to(abc, (int(near.sum()), 3)))
        known.append((areas[k], abc))
        if len(ys) == 0:
            continue
        p1, p2 = _fill_partners(tv, pose, abc, xs, ys, x0, y0, size2)
        add1.append(p1)
        add2.append(p2)
    if borrow and fill and gray2 is not None and known:
        # the regions dropped whole may be part of a surface another region shows
        starts = [abc for _, abc in sorted(known, key=lambda a: -a[0])]  # (the largest surfaces first)
        for k in orphans:
            x0, y0, region, _ = _among_plane_matches(labels, stats, k, np.zeros((0, 2)))
            borrowed = _borrowed_plane(gray1, image2(), pose, x0, y0, region, starts, np.random.default_rng(seed))
            if borrowed is None:
                continue
            abc, z = borrowed
            ys, xs = np.nonzero(region & (z >= FILL_ZNCC))  # (its matches all dropped: every pixel unmatched)
            p1, p2 = _fill_partners(tv, pose, abc, xs, ys, x0, y0, size2)
            add1.append(p1)
            add2.append(p2)
    if rims:
        more = _rim_planes(gray1, tv, pose, labels, stats, uv1, uv2, X, index, size2, fill=fill, snap=snap)
        for into, part in zip((add1, add2, moved, planes), more):
            into.extend(part)
    out = empty
    if dropped:
        out = out._replace(dropped=np.concatenate(dropped))
    if moved:
        m_idx, abc = np.concatenate(moved), np.concatenate(planes)
        # a pixel of two small regions' rims (the band between them) takes the later one's plane
        last = len(m_idx) - 1 - np.unique(m_idx[::-1], return_index=True)[1]
        m_idx, abc = m_idx[last], abc[last]
        m2, mX, ok = _on_plane(tv, uv1[m_idx], abc)
        out = out._replace(moved=m_idx[ok], moved_uv2=m2[ok], moved_xyz=mX[ok])
    if not add1 or sum(map(len, add1)) < MIN_FILL_SHARE * len(uv1):
        return out
    a1, a2 = np.concatenate(add1), np.concatenate(add2)
    # hidden in view 2: a nearer surface's match lands where the fill would (the moved
    # matches where they land now, the dropped ones nowhere)
    skip = np.union1d(out.moved, out.dropped).astype(np.int64)  # sorted
    zbuf = _nearest_depth(np.ascontiguousarray(uv2), np.ascontiguousarray(X), np.ascontiguousarray(tv.R, np.float64),
                          np.asarray(tv.t, np.float64), *size2, skip,
                          np.ascontiguousarray(out.moved_uv2, np.float64),
                          np.ascontiguousarray(out.moved_xyz, np.float64))
    Xa, va, _ = triangulate(tv.K1, tv.K2, tv.R, tv.t, a1, a2)
    za = Xa @ tv.R[2] + tv.t[2]
    keep = va & ~_hidden(np.ascontiguousarray(a2), np.ascontiguousarray(za), zbuf, HIDDEN_DEPTH_SHARE)
    return out._replace(uv1=a1[keep], uv2=a2[keep], xyz=Xa[keep], regions=len(add1))
