"""SeFM on a pair of working images: line pairs -> rough -> dense -> validity.

Array in, array out: images and the two-view geometry come in, matched pixel
positions (working frame) come out. :func:`match_pair` runs the stages, each in
its own module: the search band (:mod:`.band`), rough and dense matching per
line pair (:mod:`.rough`, :mod:`.dense`), gap filling (:mod:`.fill`), sub-pixel
refinement (:mod:`.subpixel`), validity (:mod:`.validity`) and propagation
across lines (:mod:`.propagate`), on a coarser pyramid level first where the
images are large (:func:`coarse_level`).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from typing import NamedTuple

import cv2
import numpy as np

from ..config import Config
from ..errors import InputError
from ..geometry.epipolar import line_pairs, sample_line_channels
from ..geometry.triangulate import triangulate
from ..geometry.two_view import TwoView
from .band import coarse_search_band, sample_alphas, search_band
from .dense import line_options, match_direction, reverse_check
from .fill import bridge_gaps, fill_from_band, fill_gaps
from .points import at_distance
from .propagate import propagate
from .subpixel import refine
from .validity import validated_points

logger = logging.getLogger(__name__)


@dataclass
class DenseMatches:
    """Matches in the working frame, in line order."""

    uv1: np.ndarray  #: (N, 2)
    uv2: np.ndarray  #: (N, 2)
    score: np.ndarray  #: (N,) confidence in (0, 1]
    line: np.ndarray  #: (N,) index of the epipolar line pair (-1: filled from a plane, :mod:`.planes`)
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


def _reduce(image: np.ndarray, factor: int) -> tuple[np.ndarray, float, float]:
    """Image reduced ``factor`` times (area average) and the x, y scale factors (COLMAP pixels scale by them)."""
    h, w = image.shape[:2]
    small = cv2.resize(image, (-(-w // factor), -(-h // factor)), interpolation=cv2.INTER_AREA)
    return small, small.shape[1] / w, small.shape[0] / h


class CoarseLevel(NamedTuple):
    """A coarser level's matches, and how image 1 was scaled for it."""

    matches: DenseMatches
    scale: tuple[float, float]  #: (sx, sy): coarse COLMAP pixels per full-size pixel
    shape: tuple[int, int]  #: (height, width) of the coarse image 1


def coarse_level(img1: np.ndarray, img2: np.ndarray, tv: TwoView, cfg: Config) -> CoarseLevel | None:
    """Match the pair reduced ``pyramid.factor`` times (itself coarse to fine when still large).

    Returns None when the images are small enough to match directly
    (``pyramid.min_size``). A factor of 4 rather than 2: as accurate, without the
    middle level's time.
    """
    p = cfg.pyramid
    longest = max(img1.shape[:2] + img2.shape[:2])
    if p.min_size <= 0 or longest <= p.min_size or longest < 512:
        return None
    c1, sx1, sy1 = _reduce(img1, p.factor)
    c2, sx2, sy2 = _reduce(img2, p.factor)
    S1 = np.diag([sx1, sy1, 1.0])
    S2 = np.diag([sx2, sy2, 1.0])
    tvc = dataclasses.replace(tv, K1=S1 @ tv.K1, K2=S2 @ tv.K2, kp1=tv.kp1 * [sx1, sy1], kp2=tv.kp2 * [sx2, sy2])
    # The key-point threshold is the photo's (see jump_threshold), not the reduced image's:
    # the coarse level then finds low-contrast surfaces the fine level needs.
    ccfg = dataclasses.replace(cfg, rough=dataclasses.replace(cfg.rough, jump_threshold=jump_threshold(cfg, longest),
                                                              jump_reference_size=0))
    if not p.coarse_subpixel:  # the coarse level only bounds the search: whole samples do
        ccfg = dataclasses.replace(ccfg, dense=dataclasses.replace(cfg.dense, subpixel=False, fill_max_gap=0,
                                                                   propagate_passes=0))
    if not p.coarse_both_directions:  # the same bands, the coarse level in 60 % of the time
        ccfg = dataclasses.replace(ccfg, dense=dataclasses.replace(ccfg.dense, both_directions=False))
    try:
        dm = match_pair(c1, c2, tvc, ccfg)
    except InputError:
        return None
    return CoarseLevel(dm, (sx1, sy1), c1.shape[:2])


def _per_sample_step(value: float, cfg: Config, longest: int) -> float:
    """An intensity step per sample that holds at ``rough.jump_reference_size``, for a photo ``longest`` px long.

    A photo of the same object at twice the resolution has half the
    intensity step per sample (an edge spreads over twice the samples), so
    above the reference size the value shrinks in proportion.
    """
    r = cfg.rough
    if r.jump_reference_size > 0 and longest > r.jump_reference_size:
        return value * r.jump_reference_size / longest
    return value


def jump_threshold(cfg: Config, longest: int) -> float:
    """The key-point threshold on ``da_i`` for images whose longer side is ``longest`` pixels.

    Scaled with the size (:func:`_per_sample_step`), so the key points stay
    the same features of the scene.
    """
    return _per_sample_step(cfg.rough.jump_threshold, cfg, longest)


def shift_max_step(cfg: Config, longest: int) -> float:
    """The intensity step (grey levels between neighbouring samples) a propagation window is not moved across.

    ``dense.propagate_shift_max_step`` (inf when 0), scaled with the size as
    the key-point threshold (:func:`_per_sample_step`).
    """
    step = cfg.dense.propagate_shift_max_step
    return float(_per_sample_step(step, cfg, longest)) if step > 0 else np.inf


def window_shift(cfg: Config, longest: int) -> int:
    """How far a propagation window is moved next to a depth edge, in samples, for a photo ``longest`` px long.

    ``dense.propagate_window_shift`` up to twice ``rough.jump_reference_size``
    (2000 px), growing with the square root of the size above it (6 at
    4000 px). An edge spreads over more samples on a larger photo, so the
    window must move farther to clear it, but the farther it moves the less
    it says about the sample itself: each step gains a little coverage for less
    precision (docs/algorithm.md).
    """
    shift = cfg.dense.propagate_window_shift
    ref = 2 * cfg.rough.jump_reference_size
    if ref > 0 and longest > ref:
        return int(round(shift * np.sqrt(longest / ref)))
    return shift


def _prepare(image: np.ndarray, sigma: float, color: bool) -> np.ndarray:
    """The image as float32 (grey unless ``color``), blurred by ``sigma`` px."""
    if image.ndim == 3 and not color:
        # Converted in blocks of rows: a float copy of all three channels is 3x the result.
        img = np.empty(image.shape[:2], np.float32)
        for r in range(0, image.shape[0], 256):
            img[r:r + 256] = cv2.cvtColor(image[r:r + 256].astype(np.float32), cv2.COLOR_RGB2GRAY)
    else:
        img = image.astype(np.float32)
    if sigma > 0:
        cv2.GaussianBlur(img, (0, 0), sigma, dst=img)
    return img


def match_pair(img1: np.ndarray, img2: np.ndarray, tv: TwoView, cfg: Config, progress: bool = False) -> DenseMatches:
    """Dense SeFM matches between two working images.

    Args:
        img1, img2: (H, W, 3) uint8 RGB, undistorted, matching ``tv.K1``/``tv.K2``.
        tv: relative geometry.
    """
    timings = {}
    t0 = time.perf_counter()
    coarse = coarse_level(img1, img2, tv, cfg)
    if coarse is not None:
        timings["coarse"] = time.perf_counter() - t0
        logger.info("coarse level %dx%d: %d matches in %.2f s", coarse.shape[1], coarse.shape[0],
                    len(coarse.matches.uv1), timings["coarse"])
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
    I1 = sample_line_channels(f1, lp, tv.K1, np.eye(3), 1, nb, nstep)
    I2 = sample_line_channels(f2, lp, tv.K2, tv.R.T, 2, nb, nstep)
    del f1, f2
    depths = depth_range(tv, cfg.geometry.depth_margin)
    logger.info("search depths %.3g .. %.3g (baseline %.3g)", depths[0], depths[1], np.linalg.norm(tv.t))
    if coarse is not None:
        lo, hi = coarse_search_band(lp, tv, coarse, cfg.pyramid.radius, depths, cfg.rough.band_slack, alphas)
    else:
        lo, hi = search_band(lp, tv, depths, cfg.rough.band_slack, alphas)
    # Big temporaries are dropped as soon as they are used up, so later stages
    # reuse their memory instead of paying page faults on fresh memory.
    del depths
    timings["line_pairs"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    off1, off2 = lp.offset1, lp.offset2
    # On large images a ZNCC test does most of the reverse pass's work at half
    # the cost.
    d = cfg.dense
    both = d.both_directions and (d.reverse_max_size <= 0 or max(size1 + size2) <= d.reverse_max_size)
    min_zncc = d.min_zncc if both or not d.both_directions else d.single_min_zncc
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(lp) * (2 if both else 1), desc="matching line pairs",
                   unit="line", leave=False)
    opts = line_options(cfg, jump_threshold(cfg, max(size1 + size2)))
    forward = match_direction(I1, off1, I2, off2, lo, hi, opts, bar)
    j, cost, stats = forward.j, forward.cost, forward.stats
    del forward
    n_dense = int(np.isfinite(j).sum())
    if both:
        j = reverse_check(j, I1, off1, I2, off2, lo, hi, lp.count2, opts, cfg.dense.consistency_px, bar)
    max_scale = d.fill_max_scale if d.fill_max_scale > 0 else np.inf
    if cfg.dense.fill_max_gap > 0:
        j, filled = fill_gaps(I1, off1, I2, off2, j, cfg.dense.fill_max_gap, cfg.dense.fill_radius,
                              cfg.dense.fill_half_window, cfg.dense.fill_min_zncc, max_scale)
        cost[filled] = 0.0
    if coarse is not None and cfg.pyramid.fill_width > 0:
        # The band fill judges a gap by the matches around it only where they
        # were checked both ways: single-direction DP matches fold at wrong
        # matches too (at 2000 px the test then cost 0.009 coverage at 1 px).
        j, filled = fill_from_band(I1, off1, I2, off2, j, lo, hi, cfg.pyramid.fill_width,
                                   cfg.dense.fill_half_window, cfg.dense.fill_min_zncc,
                                   max_scale if both else np.inf)
        cost[filled] = 0.0
    del lo, hi
    if cfg.dense.subpixel and cfg.dense.subpixel_iterations > 0:
        j, zncc = refine(I1, I2, lp, j, alphas, cfg)
        # A partner whose window does not correlate is most often a wrong one.
        if min_zncc > -1.0:
            j[zncc < min_zncc] = np.nan
        del zncc
    if bar is not None:
        bar.close()
    timings["matching"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    dense = np.isfinite(j)
    smooth = cfg.validity.median_depth
    last = cfg.dense.propagate_passes == 0
    # Before propagation only the depths are needed.
    pts = validated_points(j, cost, lp, tv, img1.shape[:2], cfg, smooth and last, pairs=last)
    timings["validity"] = time.perf_counter() - t0

    n_propagated = 0
    if cfg.dense.propagate_passes > 0:
        t0 = time.perf_counter()
        longest = max(size1 + size2)
        max_step, shift = shift_max_step(cfg, longest), window_shift(cfg, longest)
        j, new, state = propagate(lp, tv, I1, I2, j, pts, alphas, img1.shape[:2], cfg, max_step, shift)
        cost[new] = 0.0
        for _ in range(cfg.dense.propagate_rounds - 1):
            # The validation drops matches (often wrong ones next to a depth
            # edge) whose depths widened their neighbours' ranges past what
            # propagation searches: grow again from the valid ones. The last
            # validation's arrays go first, so this one reuses their memory.
            del pts
            pts = validated_points(j, cost, lp, tv, img1.shape[:2], cfg, pairs=False)
            j, again, state = propagate(lp, tv, I1, I2, j, pts, alphas, img1.shape[:2], cfg, max_step, shift,
                                        state=state)
            cost[again] = 0.0
            new |= again
        del state
        if d.bridge_max_gap > 0:
            # Holes the correlation could not fill inside a surface: the
            # final validation judges the interpolated partners by their
            # neighbours on the lines beside them.
            j, bridged = bridge_gaps(j, lp.offset1, d.bridge_max_gap, 0.5, 2.0, d.bridge_slope_tol)
            cost[bridged] = 0.0
        # The line samples and ray angles are used up: the last validation reuses their memory.
        del pts, I1, I2, alphas
        n_propagated = int((new & np.isfinite(j)).sum())  # a later round's validation may drop some
        pts = validated_points(j, cost, lp, tv, img1.shape[:2], cfg, smooth)
        timings["propagate"] = time.perf_counter() - t0
    # Index arrays gather rows several times faster than boolean masks.
    ki = np.flatnonzero(pts.keep)
    score = (1.0 / (1.0 + cost[pts.idx.take(ki)] / 8.0)).astype(np.float32)
    uv1 = pts.uv1.take(ki, axis=0)
    if pts.median is not None:
        # The partner moves along its epipolar line to the depth of the 2-D median.
        t0 = time.perf_counter()
        X, uv2 = at_distance(uv1, pts.median.take(ki), tv)
        timings["validity"] += time.perf_counter() - t0
    else:
        uv2, X = pts.uv2.take(ki, axis=0), pts.X.take(ki, axis=0)
    counts = {
        "line_pairs": int(len(lp)),
        "samples": int(lp.offset1[-1]),
        "keypoints": int(stats[:, 0].sum()),
        "rough_matches": int(stats[:, 2].sum()),
        "segments": int(stats[:, 4].sum()),
        "valid_segments": int(stats[:, 3].sum()),
        "dense_matches": n_dense,
        "consistent_matches": int(dense.sum()),
        "propagated_matches": n_propagated,
        "valid_matches": int(len(ki)),
    }
    logger.info(
        "SeFM: %d line pairs, %d rough matches, %d/%d valid segments, %d dense, %d valid",
        counts["line_pairs"], counts["rough_matches"], counts["valid_segments"], counts["segments"],
        counts["dense_matches"], counts["valid_matches"],
    )
    return DenseMatches(uv1, uv2, score, pts.line.take(ki), X, counts, timings)
