"""Plain surfaces filled from their own matches (``sgm.planes``), an addition beyond the paper.

Semi-global matching leaves much of a plain surface unmatched: its windows carry too
little signal for the uniqueness test, or only ties (:func:`.sgm.drop_range_ends`).
Where such a surface is one plane and enough of it did match, the plane is known:
the matches on it, each a plain window of the same surface, fit one homography
between the images. Image 1 is cut into plain regions at its intensity edges
(:func:`plain_regions`); in each large region whose matches mostly agree on a plane
(:func:`fill_planes`), the unmatched pixels among the plane's matches
(:data:`MIN_HOLE_SUPPORT`) take the partner that plane gives, moved onto their
epipolar line, unless a nearer surface's match already lands there in image 2
(the pixel is hidden in view 2).

A region whose matches are few, or split over several depths (a wrong patch of
the matcher, a curved or folded surface), is left as it is: the fill only extends
what the matcher found, it never overrides a match.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np
from numba import njit

__all__ = ["PlaneFill", "fill_planes", "plain_regions"]

#: Intensity edges cut the regions: a pixel whose gradient (Sobel, after a Gaussian of 1 px
#: that takes out most of the sensor noise) exceeds this many grey levels per pixel is an
#: edge. An 8-bit photo's noise leaves 0.3-0.5 there; a visible edge or texture, several.
EDGE_GREY_PER_PX = 2.0
#: Regions smaller than this share of image 1 are left alone: a plane from a small region's
#: matches says little beyond them, and small regions are mostly texture, which SGM matches.
MIN_REGION_SHARE = 0.01
#: ...and those where fewer than this share of the pixels matched: the plane must come from
#: the surface itself, not from a patch (Monopoly's black background: 13-18 % matched, all
#: of it a few wrong patches, each on one plane).
MIN_MATCHED_SHARE = 0.5
#: ...and those whose matches do not mostly lie on one plane: within 1 px of the homography
#: (RANSAC's threshold, the precision the matches are judged at) for at least this share.
MIN_PLANE_SUPPORT = 0.6
#: Matches a region's homography is fitted from at most (a seeded random subset): a plane
#: has 8 parameters; thousands fix it, millions only cost RANSAC's time.
MAX_FIT_MATCHES = 5000
#: A pixel is filled only inside the plane's matches, not beyond them: where at least this
#: share of the region's pixels within :data:`HOLE_WINDOW` px of it hold a match on the plane.
#: Without it, a plain face that did not match took the plane of the floor it touched (a
#: generated forward pair: 0.849 -> 0.809 at 1 px); at half, Plastic's rectified pair gained
#: half the coverage (+0.018 against +0.035 at 1 px) and less precision (0.816 against 0.820).
MIN_HOLE_SUPPORT = 0.25
#: ...over a window three matching windows (:data:`.sgm.BLOCK`) across.
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


class PlaneFill(NamedTuple):
    """What :func:`fill_planes` added."""

    uv1: np.ndarray  #: (N, 2) pixels of image 1 that had no match (COLMAP positions)
    uv2: np.ndarray  #: (N, 2) their partners on the region's plane, on their epipolar lines
    xyz: np.ndarray  #: (N, 3) their points, camera 1's frame
    regions: int  #: regions filled


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
    """The region label of each match's pixel in image 1 (N,) and the (H, W) mask of matched pixels."""
    h, w = labels.shape
    lab = np.empty(uv1.shape[0], np.int32)
    matched = np.zeros((h, w), np.bool_)
    for i in range(uv1.shape[0]):
        x = int(uv1[i, 0])
        y = int(uv1[i, 1])
        lab[i] = labels[y, x]
        matched[y, x] = True
    return lab, matched


@njit(cache=True)
def _nearest_depth(uv2, X, R, t, w2, h2):
    """Per pixel of image 2 (h2, w2), the smallest camera-2 depth (``R X + t``) of the matches landing in it."""
    zbuf = np.full((h2, w2), np.inf, np.float32)
    for i in range(uv2.shape[0]):
        x = int(uv2[i, 0])
        y = int(uv2[i, 1])
        if 0 <= x < w2 and 0 <= y < h2:
            z = R[2, 0] * X[i, 0] + R[2, 1] * X[i, 1] + R[2, 2] * X[i, 2] + t[2]
            if z < zbuf[y, x]:
                zbuf[y, x] = z
    return zbuf


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


def fill_planes(gray1: np.ndarray, size2: tuple[int, int], tv, uv1: np.ndarray, uv2: np.ndarray, X: np.ndarray,
                *, seed: int = 0) -> PlaneFill:
    """Partners for the unmatched pixels of image 1's large plain regions whose matches lie on one plane.

    Args:
        gray1: (H, W) uint8 image 1 (working size).
        size2: (w, h) of image 2.
        tv: the pair's geometry (:class:`.geometry.two_view.TwoView`: ``K1``, ``K2``, ``R``, ``t``, ``F``).
        uv1, uv2: (N, 2) the matches, COLMAP positions, at most one per pixel of image 1.
        X: (N, 3) their points (camera 1's frame), for what they hide in view 2.
    Returns the added matches (:class:`PlaneFill`); pixels already matched are never touched.
    """
    from ..geometry.triangulate import triangulate

    h, w = gray1.shape
    labels, stats = plain_regions(gray1)
    areas = stats[:, cv2.CC_STAT_AREA]
    big = np.flatnonzero(areas >= MIN_REGION_SHARE * h * w)
    empty = PlaneFill(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 3)), 0)
    if len(big) == 0 or len(uv1) == 0:
        return empty
    lab, matched = _region_of_matches(np.ascontiguousarray(uv1), labels)
    rng = np.random.default_rng(seed)
    add1, add2 = [], []
    m = HOLE_WINDOW // 2
    for k in big:
        idx = np.flatnonzero(lab == k)
        if len(idx) < MIN_MATCHED_SHARE * areas[k] or len(idx) < 4:
            continue
        fit = idx if len(idx) <= MAX_FIT_MATCHES else rng.choice(idx, MAX_FIT_MATCHES, replace=False)
        cv2.setRNGSeed(seed)
        H, _ = cv2.findHomography(uv1[fit], uv2[fit], cv2.RANSAC, 1.0)
        if H is None:
            continue
        pred = cv2.perspectiveTransform(uv1[idx].reshape(-1, 1, 2), H).reshape(-1, 2)
        on_plane = np.linalg.norm(pred - uv2[idx], axis=1) <= 1.0
        if np.mean(on_plane) < MIN_PLANE_SUPPORT:
            continue
        # holes of the plane's matches, not a surface beyond them (MIN_HOLE_SUPPORT), over the
        # region's bounding box and the window's reach around it
        x0, y0, bw, bh = stats[k, :4]
        x0, y0, x1, y1 = max(x0 - m, 0), max(y0 - m, 0), min(x0 + bw + m, w), min(y0 + bh + m, h)
        region = (labels[y0:y1, x0:x1] == k).astype(np.float32)
        on = np.zeros_like(region)
        inl = uv1[idx[on_plane]].astype(np.int64)
        on[inl[:, 1] - y0, inl[:, 0] - x0] = 1.0
        win = (HOLE_WINDOW, HOLE_WINDOW)
        dense = cv2.boxFilter(on, -1, win, normalize=False) >= MIN_HOLE_SUPPORT * cv2.boxFilter(region, -1, win, normalize=False)
        ys, xs = np.nonzero((region > 0) & ~matched[y0:y1, x0:x1] & dense)
        if len(ys) == 0:
            continue
        p1 = np.column_stack([xs + x0 + 0.5, ys + y0 + 0.5])
        p2 = _on_lines(tv.F, p1, cv2.perspectiveTransform(p1.reshape(-1, 1, 2), H).reshape(-1, 2))
        inside = (p2[:, 0] >= 0) & (p2[:, 0] < size2[0]) & (p2[:, 1] >= 0) & (p2[:, 1] < size2[1])
        add1.append(p1[inside])
        add2.append(p2[inside])
    if not add1 or sum(map(len, add1)) < MIN_FILL_SHARE * len(uv1):
        return empty
    a1, a2 = np.concatenate(add1), np.concatenate(add2)
    # hidden in view 2: a nearer surface's match lands where the fill would
    zbuf = _nearest_depth(np.ascontiguousarray(uv2), np.ascontiguousarray(X), np.ascontiguousarray(tv.R, np.float64),
                          np.asarray(tv.t, np.float64), *size2)
    Xa, va, _ = triangulate(tv.K1, tv.K2, tv.R, tv.t, a1, a2)
    za = Xa @ tv.R[2] + tv.t[2]
    keep = va & ~_hidden(np.ascontiguousarray(a2), np.ascontiguousarray(za), zbuf, HIDDEN_DEPTH_SHARE)
    return PlaneFill(a1[keep], a2[keep], Xa[keep], len(add1))
