"""SeFM on a pair of working images: line pairs -> rough -> dense -> validity.

Array in, array out: images and the two-view geometry come in, matched pixel
positions (working frame) come out.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..config import Config
from ..errors import InputError
from ..geometry.epipolar import LinePairs, line_pairs, neighbour_positions, ray_angles, sample_points
from ..geometry.triangulate import triangulate
from ..geometry.two_view import TwoView
from . import kernels
from .validity import depth_continuity, neighbour_consistency

logger = logging.getLogger(__name__)


@dataclass
class DenseMatches:
    """Matches in the working frame, in line order."""

    uv1: np.ndarray  #: (N, 2)
    uv2: np.ndarray  #: (N, 2)
    score: np.ndarray  #: (N,) confidence in (0, 1]
    line: np.ndarray  #: (N,) index of the epipolar line pair
    xyz: np.ndarray  #: (N, 3) triangulated points, camera-1 frame
    counts: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)


def depth_range(tv: TwoView, margin: float = 2.0) -> tuple[float, float]:
    """Range of distances from camera 1 to search, from the SIFT inliers.

    The 1st-99th percentile of the inliers' distances, widened by ``margin``
    (divided at the near end, multiplied at the far end). Without enough
    inliers, everything from a fifth of the baseline to infinity.
    """
    baseline = float(np.linalg.norm(tv.t))
    if len(tv.kp1) >= 8:
        X, valid, _ = triangulate(tv.K1, tv.K2, tv.R, tv.t, tv.kp1, tv.kp2)
        dist = np.linalg.norm(X[valid], axis=1)
        if len(dist) >= 8:
            lo, hi = np.percentile(dist, [1, 99])
            return float(lo / margin), float(hi * margin)
    return 0.2 * baseline, float("inf")


def sample_alphas(lp: LinePairs, tv: TwoView) -> tuple[np.ndarray, np.ndarray]:
    """Angle from the baseline of every sample's ray, flat, for image 1 and image 2."""
    _, a1 = ray_angles(tv.K1, np.eye(3), lp.basis, lp.all_points1())
    _, a2 = ray_angles(tv.K2, tv.R.T, lp.basis, lp.all_points2())
    return a1, a2


def sample_channels(image: np.ndarray, lp: LinePairs, K: np.ndarray, Rc: np.ndarray, which: int,
                    alpha: np.ndarray, neighbours: int, step: float) -> np.ndarray:
    """(N, C * (2 * neighbours + 1)) samples of each line and its aligned neighbour lines."""
    out = []
    for k in range(-neighbours, neighbours + 1):
        if k == 0:
            pts = lp.all_points1() if which == 1 else lp.all_points2()
        else:
            pts = neighbour_positions(lp, K, Rc, which, alpha, k * step)
        out.append(sample_points(image, pts))
    return np.ascontiguousarray(np.concatenate(out, axis=1))


def search_band(lp: LinePairs, tv: TwoView, depths: tuple[float, float], slack: int,
                alphas: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """For each line-1 sample, the line-2 sample range holding points at the given depths.

    A point at distance ``d`` along the ray of angle ``alpha1`` is seen from
    camera 2 under ``alpha2 = atan2(d sin alpha1, d cos alpha1 - B)``; ``alpha2``
    falls from pi (d = 0) to alpha1 (d = inf).
    """
    a1, a2 = alphas if alphas is not None else sample_alphas(lp, tv)
    B = float(np.linalg.norm(tv.t))
    dmin, dmax = depths
    a2_hi = np.arctan2(dmin * np.sin(a1), dmin * np.cos(a1) - B)
    if np.isfinite(dmax):
        a2_lo = np.arctan2(dmax * np.sin(a1), dmax * np.cos(a1) - B)
    else:
        a2_lo = a1.copy()
    off2 = lp.offset2
    line1 = np.repeat(np.arange(len(lp)), lp.count1)
    line2 = np.repeat(np.arange(len(lp)), lp.count2)
    # alpha is in [0, pi] and increases along each line: offsetting by 8 per line
    # makes one sorted key over all lines, so one searchsorted does every line.
    key2 = line2 * 8.0 + a2
    lo = np.searchsorted(key2, line1 * 8.0 + a2_lo, side="left") - off2[line1] - slack
    hi = np.searchsorted(key2, line1 * 8.0 + a2_hi, side="right") - 1 - off2[line1] + slack
    n2 = lp.count2[line1]
    lo = np.clip(lo, 0, n2 - 1).astype(np.int64)
    hi = np.clip(hi, -1, n2 - 1).astype(np.int64)
    return lo, hi


def invert_band(lo: np.ndarray, hi: np.ndarray, off1: np.ndarray, off2: np.ndarray):
    """Band of line-1 positions for every line-2 sample, from the line-2 band of every line-1 sample."""
    L = len(off1) - 1
    count1, count2 = np.diff(off1), np.diff(off2)
    line1 = np.repeat(np.arange(L), count1)
    line2 = np.repeat(np.arange(L), count2)
    big = 1 << 24
    # Monotone envelopes (only ever widen the band): hi as a running max, lo as a
    # running min from the end of each line.
    hi_m = hi.astype(np.int64).copy()
    lo_m = lo.astype(np.int64).copy()
    for l in range(L):  # L ~ 1e3 lines: vectorised per line, cheap
        a, b = off1[l], off1[l + 1]
        hi_m[a:b] = np.maximum.accumulate(hi_m[a:b])
        lo_m[a:b] = np.minimum.accumulate(lo_m[a:b][::-1])[::-1]
    k2 = np.arange(len(line2)) - off2[line2]
    first = np.searchsorted(line1 * big + hi_m, line2 * big + k2, side="left") - off1[line2]
    last = np.searchsorted(line1 * big + lo_m, line2 * big + k2, side="right") - 1 - off1[line2]
    n1 = count1[line2]
    return np.clip(first, 0, n1 - 1).astype(np.int64), np.clip(last, -1, n1 - 1).astype(np.int64)


def consistent(j12: np.ndarray, i21: np.ndarray, off1, off2, count2, tol: float) -> np.ndarray:
    """Left-right check: keep j12[i] only where matching back from round(j12[i]) returns to i."""
    L = len(off1) - 1
    line1 = np.repeat(np.arange(L), np.diff(off1))
    k1 = np.arange(len(j12)) - off1[line1]
    out = np.full_like(j12, np.nan)
    ok = np.isfinite(j12)
    jr = np.clip(np.rint(np.where(ok, j12, 0)).astype(np.int64), 0, count2[line1] - 1)
    back = i21[off2[line1] + jr]
    ok &= np.isfinite(back) & (np.abs(back - k1) <= tol)
    out[ok] = j12[ok]
    return out


def _match_direction(Ia, offa, Ib, offb, lo, hi, cfg: Config, bar=None):
    """Run the line kernel over all line pairs, in chunks (for the progress bar)."""
    n = len(offa) - 1
    j = np.full(len(Ia), np.nan)
    cost = np.full(len(Ia), np.nan, np.float32)
    anchor = np.zeros(len(Ia), bool)
    stats = np.zeros((n, 5), np.int64)
    chunks = np.array_split(np.arange(n), max(1, min(50, n // 64)))
    for chunk in chunks:
        if len(chunk) == 0:
            continue
        a, b = chunk[0], chunk[-1] + 1
        s1, e1, s2, e2 = offa[a], offa[b], offb[a], offb[b]
        rj, rc, ra, rs = kernels.match_lines(
            Ia[s1:e1], offa[a:b + 1] - s1, Ib[s2:e2], offb[a:b + 1] - s2, lo[s1:e1], hi[s1:e1],
            cfg.rough.jump_threshold, cfg.rough.descriptor_radius, cfg.rough.descriptor_coefficients,
            cfg.rough.max_descriptor_distance, cfg.validity.sv_max_unmatched, cfg.validity.sv_strength,
            cfg.dense.occlusion_penalty, cfg.dense.band_fraction, cfg.dense.band_min, cfg.dense.band_max,
            cfg.dense.occlusion_run, cfg.dense.open_ends,
        )
        j[s1:e1], cost[s1:e1], anchor[s1:e1], stats[a:b] = rj, rc, ra, rs
        if bar is not None:
            bar.update(len(chunk))
    return j, cost, anchor, stats


def _prepare(image: np.ndarray, sigma: float, color: bool) -> np.ndarray:
    img = image.astype(np.float32)
    if img.ndim == 3 and not color:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    if sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), sigma)
    return img


def match_pair(img1: np.ndarray, img2: np.ndarray, tv: TwoView, cfg: Config, progress: bool = False) -> DenseMatches:
    """Dense SeFM matches between two working images.

    Args:
        img1, img2: (H, W, 3) uint8 RGB, undistorted, matching ``tv.K1``/``tv.K2``.
        tv: relative geometry.
    """
    timings = {}
    t0 = time.perf_counter()
    size1 = (img1.shape[1], img1.shape[0])
    size2 = (img2.shape[1], img2.shape[0])
    lp = line_pairs(tv.K1, tv.K2, tv.R, tv.t, size1, size2, cfg.lines.line_spacing,
                    cfg.lines.sample_spacing, cfg.lines.max_lines)
    if len(lp) == 0:
        raise InputError("no epipolar line crosses both images: with this geometry the views do not overlap")
    f1 = _prepare(img1, cfg.lines.blur_sigma, cfg.lines.color)
    f2 = _prepare(img2, cfg.lines.blur_sigma, cfg.lines.color)
    alphas = sample_alphas(lp, tv)
    nb, nstep = cfg.lines.neighbours, cfg.lines.neighbour_step
    I1 = sample_channels(f1, lp, tv.K1, np.eye(3), 1, alphas[0], nb, nstep)
    I2 = sample_channels(f2, lp, tv.K2, tv.R.T, 2, alphas[1], nb, nstep)
    depths = depth_range(tv, cfg.geometry.depth_margin)
    lo, hi = search_band(lp, tv, depths, cfg.rough.band_slack, alphas)
    timings["line_pairs"] = time.perf_counter() - t0
    logger.info("search depths %.3g .. %.3g (baseline %.3g)", depths[0], depths[1], np.linalg.norm(tv.t))

    t0 = time.perf_counter()
    off1, off2 = lp.offset1, lp.offset2
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(lp) * (2 if cfg.dense.both_directions else 1), desc="matching line pairs",
                   unit="line", leave=False)
    j, cost, anchor, stats = _match_direction(I1, off1, I2, off2, lo, hi, cfg, bar)
    n_dense = int(np.isfinite(j).sum())
    if cfg.dense.both_directions:
        lo21, hi21 = invert_band(lo, hi, off1, off2)
        i21, _, _, _ = _match_direction(I2, off2, I1, off1, lo21, hi21, cfg, bar)
        j = consistent(j, i21, off1, off2, lp.count2, cfg.dense.consistency_px)
    if cfg.dense.fill_max_gap > 0:
        j, filled = kernels.fill_gaps(I1, off1, I2, off2, j, cfg.dense.fill_max_gap, cfg.dense.fill_radius,
                                      cfg.dense.fill_half_window, cfg.dense.fill_min_zncc)
        cost[filled] = 0.0
    if cfg.dense.subpixel:
        for _ in range(cfg.dense.subpixel_iterations):
            j = kernels.refine_subpixel(I1, off1, I2, off2, j, cfg.dense.subpixel_half_window, 1.0)
    if bar is not None:
        bar.close()
    timings["matching"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    line1 = np.repeat(np.arange(len(lp)), lp.count1)
    k1 = np.arange(len(I1)) - off1[line1]
    dense = np.isfinite(j)
    ok = dense & (cost <= cfg.validity.max_cost)
    idx = np.flatnonzero(ok)
    line = line1[idx]
    uv1 = lp.points1(line, k1[idx].astype(np.float64))
    uv2 = lp.points2(line, j[idx])
    X, valid, angle = triangulate(tv.K1, tv.K2, tv.R, tv.t, uv1, uv2)
    valid &= angle >= np.radians(cfg.validity.min_tri_angle_deg)
    dist = np.linalg.norm(X, axis=1)
    keep = np.zeros(len(idx), bool)
    vi = np.flatnonzero(valid)
    keep[vi] = depth_continuity(dist[vi], line[vi], cfg.validity.sp_depth_jump, cfg.validity.sp_min_run)
    if cfg.validity.neighbour_tol_px > 0:
        ki = np.flatnonzero(keep)
        # One pixel of disparity is about 1 / (f * B) in inverse depth.
        scale = float(tv.K1[0, 0] * np.linalg.norm(tv.t))
        keep[ki] = neighbour_consistency(uv1[ki], scale / dist[ki], img1.shape[:2], cfg.validity.neighbour_radius,
                                         cfg.validity.neighbour_tol_px, cfg.validity.neighbour_support,
                                         cfg.validity.drop_isolated)
    score = 1.0 / (1.0 + cost[idx] / 8.0)
    timings["validity"] = time.perf_counter() - t0
    counts = {
        "line_pairs": int(len(lp)),
        "samples": int(len(I1)),
        "keypoints": int(stats[:, 0].sum()),
        "rough_matches": int(stats[:, 2].sum()),
        "segments": int(stats[:, 4].sum()),
        "valid_segments": int(stats[:, 3].sum()),
        "dense_matches": n_dense,
        "consistent_matches": int(dense.sum()),
        "valid_matches": int(keep.sum()),
    }
    logger.info(
        "SeFM: %d line pairs, %d rough matches, %d/%d valid segments, %d dense, %d valid",
        counts["line_pairs"], counts["rough_matches"], counts["valid_segments"], counts["segments"],
        counts["dense_matches"], counts["valid_matches"],
    )
    return DenseMatches(uv1[keep], uv2[keep], score[keep].astype(np.float32), line[keep], X[keep], counts, timings)
