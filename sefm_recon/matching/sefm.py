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
from ..geometry.epipolar import LinePairs, alpha_of_samples, line_pairs, sample_lines
from ..geometry.triangulate import triangulate
from ..geometry.two_view import TwoView
from . import kernels
from .validity import depth_continuity

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


def search_band(lp: LinePairs, tv: TwoView, depths: tuple[float, float], slack: int) -> tuple[np.ndarray, np.ndarray]:
    """For each line-1 sample, the line-2 sample range holding points at the given depths.

    A point at distance ``d`` along the ray of angle ``alpha1`` is seen from
    camera 2 under ``alpha2 = atan2(d sin alpha1, d cos alpha1 - B)``; ``alpha2``
    falls from pi (d = 0) to alpha1 (d = inf).
    """
    a1 = alpha_of_samples(lp, tv.K1, np.eye(3), 1)
    a2 = alpha_of_samples(lp, tv.K2, tv.R.T, 2)
    B = float(np.linalg.norm(tv.t))
    dmin, dmax = depths
    a2_hi = np.arctan2(dmin * np.sin(a1), dmin * np.cos(a1) - B)
    if np.isfinite(dmax):
        a2_lo = np.arctan2(dmax * np.sin(a1), dmax * np.cos(a1) - B)
    else:
        a2_lo = a1.copy()
    off1, off2 = lp.offset1, lp.offset2
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
    del off1
    return lo, hi


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
    f1 = _prepare(img1, cfg.lines.blur_sigma, cfg.lines.color)
    f2 = _prepare(img2, cfg.lines.blur_sigma, cfg.lines.color)
    I1 = sample_lines(f1, lp.start1, lp.step1, lp.count1)
    I2 = sample_lines(f2, lp.start2, lp.step2, lp.count2)
    depths = depth_range(tv, cfg.geometry.depth_margin)
    lo, hi = search_band(lp, tv, depths, cfg.rough.band_slack)
    timings["line_pairs"] = time.perf_counter() - t0
    logger.info("search depths %.3g .. %.3g (baseline %.3g)", depths[0], depths[1], np.linalg.norm(tv.t))

    t0 = time.perf_counter()
    off1, off2 = lp.offset1, lp.offset2
    j = np.full(len(I1), np.nan)
    cost = np.full(len(I1), np.nan, np.float32)
    anchor = np.zeros(len(I1), bool)
    stats = np.zeros((len(lp), 5), np.int64)
    chunks = np.array_split(np.arange(len(lp)), max(1, min(50, len(lp) // 64)))
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(lp), desc="matching line pairs", unit="line", leave=False)
    for chunk in chunks:
        if len(chunk) == 0:
            continue
        a, b = chunk[0], chunk[-1] + 1
        s1, e1, s2, e2 = off1[a], off1[b], off2[a], off2[b]
        rj, rc, ra, rs = kernels.match_lines(
            I1[s1:e1], off1[a:b + 1] - s1, I2[s2:e2], off2[a:b + 1] - s2, lo[s1:e1], hi[s1:e1],
            cfg.rough.jump_threshold, cfg.rough.descriptor_radius, cfg.rough.descriptor_coefficients,
            cfg.rough.max_descriptor_distance, cfg.validity.sv_max_unmatched, cfg.validity.sv_strength,
            cfg.dense.occlusion_penalty, cfg.dense.band_fraction, cfg.dense.band_min, cfg.dense.band_max,
            cfg.dense.occlusion_run,
        )
        j[s1:e1], cost[s1:e1], anchor[s1:e1], stats[a:b] = rj, rc, ra, rs
        if bar is not None:
            bar.update(len(chunk))
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
    score = 1.0 / (1.0 + cost[idx] / 8.0)
    timings["validity"] = time.perf_counter() - t0
    counts = {
        "line_pairs": int(len(lp)),
        "samples": int(len(I1)),
        "keypoints": int(stats[:, 0].sum()),
        "rough_matches": int(stats[:, 2].sum()),
        "segments": int(stats[:, 4].sum()),
        "valid_segments": int(stats[:, 3].sum()),
        "dense_matches": int(dense.sum()),
        "valid_matches": int(keep.sum()),
    }
    logger.info(
        "SeFM: %d line pairs, %d rough matches, %d/%d valid segments, %d dense, %d valid",
        counts["line_pairs"], counts["rough_matches"], counts["valid_segments"], counts["segments"],
        counts["dense_matches"], counts["valid_matches"],
    )
    return DenseMatches(uv1[keep], uv2[keep], score[keep].astype(np.float32), line[keep], X[keep], counts, timings)
