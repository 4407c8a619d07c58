"""Propagation across line pairs: valid matches grow into their unmatched neighbours (an addition to the paper).

Scanline DP decides each line alone and leaves gaps where one line was
ambiguous; the lines beside it often matched there. Every unmatched sample
takes the distance range of the valid matches around it (:mod:`.band`'s
depth grids) and searches the line-2 band of that range by window ZNCC
(:mod:`.zncc`), pass after pass from the new matches.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np
from numba import njit, prange

from ..config import Config
from ..geometry.epipolar import LinePairs
from ..geometry.two_view import TwoView
from .band import depth_grids, sample_band, widen
from .points import points_of_samples
from .validity import ValidatedPoints
from .zncc import zncc_search


class PropagateOptions(NamedTuple):
    """Settings of :func:`propagate_candidates`."""

    slack: int  #: samples added to each side of a band
    max_width: int  #: a band at most this many samples wide is searched whole
    half: int  #: ZNCC window half length, samples
    min_zncc: float  #: correlation a match needs
    shift: int = 0  #: samples a window may move to either side next to a depth edge (:func:`.zncc.zncc_search`)
    max_step: float = np.inf  #: ...but not across an intensity step over this (grey levels between samples)
    split_slack: int = -1  #: >= 0: a band too wide is searched at its two end distances, this many samples wider
    split_margin: float = 0.0  #: ...where the better end's ZNCC must beat the other's by this
    radius: int = 0  #: pixels around a sample whose distance ranges bound its band


class PropagationState(NamedTuple):
    """What a propagation round leaves the next (:func:`propagate`)."""

    gmin: np.ndarray  #: (H, W) float32 widened smallest distance of the valid matches near each pixel
    gmax: np.ndarray  #: (H, W) float32 the largest
    active: np.ndarray  #: (H, W) uint8 pixels whose range changed in the last pass


@njit(parallel=True, cache=True)
def propagate_candidates(I1, off1, I2, off2, j, cand, cand_off, start1, step1, a1, a2, gmin, gmax, baseline, active,
                         opts):
    """One propagation pass: match unmatched samples inside the depth range of the matches around them.

    The samples tried are listed: ``cand`` (M,) flat sample indices,
    increasing, and ``cand_off`` (L + 1,) the range of each line's in it
    (``np.searchsorted(cand, off1)``); the list spares a scan of every
    sample in each pass. Sample ``k`` of line ``l`` (at ``start1[l] + k
    step1[l]``, COLMAP pixels of image 1) reads the distance range
    ``gmin``/``gmax`` (H, W) of the pixels within ``opts.radius`` of its pixel
    (inf where none; reading it here costs less than widening the grids
    for the few samples tried); its line-2 band
    (:func:`.band.sample_band` of the ray angles ``a1``
    (N1,), ``a2`` (N2,) and the ``baseline``, ``opts.slack`` samples wider)
    at most ``opts.max_width`` samples wide is searched by ZNCC as in
    :func:`.fill.fill_from_band`. Only samples on pixels where ``active`` (H, W)
    is set are tried (the pixels whose range changed since the last pass).
    With ``opts.split_slack`` >= 0, a band too wide is a depth edge (the
    neighbours hold two surfaces): the bands of its two end distances,
    ``split_slack`` samples wider, are searched instead, and the better one's
    ZNCC must beat the other's by ``opts.split_margin``.
    The partners found are written into ``j`` in place (each sample reads
    only its own, so this is the same as filling a copy). Returns the mask
    (M,) of the filled candidates.
    """
    slack, max_width, half, min_zncc = opts.slack, opts.max_width, opts.half, opts.min_zncc
    shift, max_step, split_slack, split_margin, radius = (opts.shift, opts.max_step, opts.split_slack,
                                                          opts.split_margin, opts.radius)
    L = off1.shape[0] - 1
    H, W = gmin.shape
    hit = np.zeros(cand.shape[0], np.bool_)
    for ll in prange(L):
        l = np.int64(ll)
        if cand_off[l] == cand_off[l + 1]:
            continue
        s1 = off1[l]
        s2 = off2[l]
        e2 = off2[l + 1]
        a = I1[s1:off1[l + 1]]
        b = I2[s2:e2]
        ga = s2
        gb = s2
        for q in range(cand_off[l], cand_off[l + 1]):
            i = cand[q]
            k = i - s1
            c = min(max(int(np.floor(start1[l, 0] + k * step1[l, 0])), 0), W - 1)
            r = min(max(int(np.floor(start1[l, 1] + k * step1[l, 1])), 0), H - 1)
            if not active[r, c]:
                continue
            dmin = np.inf
            dmax = -np.inf
            for rr in range(max(r - radius, 0), min(r + radius + 1, H)):
                for cc in range(max(c - radius, 0), min(c + radius + 1, W)):
                    dmin = min(dmin, gmin[rr, cc])
                    dmax = max(dmax, gmax[rr, cc])
            if not np.isfinite(dmax):
                continue
            lo, hi, ga, gb = sample_band(a1[i], a2, s2, e2, dmin, dmax, baseline, slack, ga, gb)
            if hi < lo:
                continue
            if hi - lo + 1 <= max_width:
                best, pos = zncc_search(a, k, b, float(lo), hi - lo + 1, half, min_zncc, shift, max_step)
            elif split_slack >= 0:
                # Next to a depth edge the neighbours hold two surfaces: try each one's distance.
                best = -2.0
                other = -2.0
                pos = 0.0
                for dist in (dmin, dmax):
                    lo2, hi2, _, _ = sample_band(a1[i], a2, s2, e2, dist, dist, baseline, split_slack, ga, gb)
                    if hi2 < lo2:
                        continue
                    z, p = zncc_search(a, k, b, float(lo2), hi2 - lo2 + 1, half, min_zncc, shift, max_step)
                    if z > best:
                        other = best
                        best = z
                        pos = p
                    else:
                        other = max(other, z)
                if best - other < split_margin:
                    continue
            else:
                continue
            if best >= min_zncc:
                j[i] = pos
                hit[q] = True
    return hit


def propagate(lp: LinePairs, tv: TwoView, I1: np.ndarray, I2: np.ndarray, j: np.ndarray, pts: ValidatedPoints,
              alphas: tuple[np.ndarray, np.ndarray], shape: tuple[int, int], cfg: Config, max_step: float = np.inf,
              shift: int | None = None, state: PropagationState | None = None
              ) -> tuple[np.ndarray, np.ndarray, PropagationState]:
    """Grow the valid matches into their unmatched neighbours (2-D, across line pairs).

    ``j`` (N1,) are the partners on line 2 (NaN: none), ``pts`` their points
    and validity (:func:`.validity.validated_points`), ``I1``, ``I2`` the line
    samples, ``alphas`` their ray angles, ``shape`` (height, width) of image 1.

    Every sample without a valid match gets the depth range of the matches
    within ``dense.propagate_radius`` pixels of it; where that range is at
    most ``dense.propagate_width`` samples of line 2 wide, the partner is its
    best ZNCC at ``dense.propagate_min_zncc`` or more (as the coarse-band
    fill; where the centred window fails, windows moved
    ``shift`` samples (default ``dense.propagate_window_shift``, see
    :func:`.sefm.window_shift`) to either side are tried, for
    samples next to a depth edge, but not across an intensity step over
    ``max_step``: :func:`.sefm.shift_max_step`). Where the range is wider (the
    neighbours lie on two surfaces), its two ends are searched in turn
    (``dense.propagate_split_*``). Scanline DP leaves gaps where one line
    alone was ambiguous; the lines beside it often matched there. Each of
    the ``dense.propagate_passes`` passes grows from the valid matches and
    the previous passes' new ones; the caller validates the result.

    The validation drops some matches, often wrong ones next to a depth edge
    that the first validation kept (their neighbours were missing then);
    their depths widened their neighbours' ranges past ``propagate_width``.
    So the caller runs ``dense.propagate_rounds`` rounds, each after a
    validation, passing the ``state`` a round returns to the next: that round
    tries only the samples whose range changed and those the validation
    dropped (a sample that failed with the same range fails again).
    Returns the new ``j`` (invalid matches dropped, new ones added), the
    mask of new ones and the state.
    """
    d = cfg.dense
    shift = d.propagate_window_shift if shift is None else shift
    keep = pts.keep
    grids = depth_grids(pts.uv1, pts.dist, shape, keep)
    valid = np.zeros(len(j), bool)
    valid[pts.idx[keep]] = True
    jv = np.where(valid, j, np.nan)  # one pass; a NaN fill and a scatter cost 5x more here
    new = np.zeros(len(j), bool)
    start1, step1, _ = lp.side(1)
    baseline = float(np.linalg.norm(tv.t))
    kernel = np.ones((2 * d.propagate_radius + 1,) * 2, np.uint8)
    # One sample of slack: the neighbours' depths are fine-level ones.
    opts = PropagateOptions(1, d.propagate_width, d.fill_half_window, d.propagate_min_zncc, shift, max_step,
                            d.propagate_split_slack, d.propagate_split_margin, d.propagate_radius)
    if state is None:
        active = np.ones(shape, np.uint8)
    else:
        old_min, old_max, active = state
        gmin, gmax = widen(grids, d.propagate_radius)
        active = active | (gmin != old_min) | (gmax != old_max)
        # A match the validation dropped may be kept among its new neighbours.
        active |= cv2.dilate(_pixel_mask(pts.uv1, ~keep, shape), kernel).astype(bool)
        active = active.astype(np.uint8)
        del old_min, old_max
    # The unmatched samples, listed once: each pass tries only these (in place in jv).
    cand = np.flatnonzero(np.isnan(jv))
    for _ in range(d.propagate_passes):
        if not active.any():
            break
        hit = propagate_candidates(I1, lp.offset1, I2, lp.offset2, jv, cand, np.searchsorted(cand, lp.offset1),
                                   start1, step1, *alphas, *grids, baseline, active, opts)
        if not hit.any():
            active = np.zeros(shape, np.uint8)
            break
        fi = cand[hit]
        cand = cand[~hit]
        new[fi] = True
        # The new matches' points seed the next pass.
        fuv1, fdist, fvalid = points_of_samples(fi, jv, lp, tv)
        depth_grids(fuv1, fdist, shape, fvalid, grids)
        # Only pixels whose widened range just changed can match in the next
        # pass: a sample that failed with the same range fails again.
        active = cv2.dilate(_pixel_mask(fuv1, fvalid, shape), kernel)
    return jv, new, PropagationState(*widen(grids, d.propagate_radius), active)


def _pixel_mask(uv: np.ndarray, mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(height, width) uint8, 1 at the pixels ``floor(uv)`` of the masked points."""
    out = np.zeros(shape, np.uint8)
    ij = np.floor(uv[mask]).astype(np.int64)
    ok = (ij[:, 0] >= 0) & (ij[:, 0] < shape[1]) & (ij[:, 1] >= 0) & (ij[:, 1] < shape[0])
    out[ij[ok, 1], ij[ok, 0]] = 1
    return out

