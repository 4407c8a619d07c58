"""Propagation across lines (matching/propagate.py): one pass against its steps one after another."""

import cv2
import numpy as np

from sefm_recon.geometry.epipolar import line_alphas, sample_line_channels
from sefm_recon.geometry.two_view import TwoView
from sefm_recon.matching.band import search_band, widen
from sefm_recon.matching.fill import fill_from_band
from sefm_recon.matching.propagate import PropagateOptions, propagate_candidates

from .conftest import LINE_K as K
from .conftest import LINE_SIZE as SIZE
from .conftest import grid_bounds, tilted_lines


def _propagation_scene(seed, ratio):
    """Line samples of a random blurred image in both views, and distance grids known on a third of the pixels.

    Returns ``R, t, lp, tv, alphas, I1, I2, gmin, gmax, rng``; ``gmax = ratio * gmin``.
    """
    R, t, lp = tilted_lines()
    tv = TwoView(K, K, R, t)
    alphas = line_alphas(lp, K, np.eye(3), 1), line_alphas(lp, K, R.T, 2)
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (SIZE[1], SIZE[0])).astype(np.float32), (0, 0), 2.0)
    I1 = sample_line_channels(img, lp, K, np.eye(3), 1, neighbours=1)
    I2 = sample_line_channels(img, lp, K, R.T, 2, neighbours=1)
    near = np.where(rng.random((SIZE[1], SIZE[0])) < 0.3, rng.uniform(2, 6, (SIZE[1], SIZE[0])), np.inf)
    gmin = near.astype(np.float32)
    gmax = np.where(np.isfinite(near), ratio * near, -np.inf).astype(np.float32)
    return R, t, lp, tv, alphas, I1, I2, gmin, gmax, rng


def _propagate_pass(I1, off1, I2, off2, j, *args):
    """:func:`propagate_candidates` over every unmatched sample: the filled copy of ``j`` and its mask."""
    out = j.copy()
    cand = np.flatnonzero(np.isnan(j))
    hit = propagate_candidates(I1, off1, I2, off2, out, cand, np.searchsorted(cand, off1), *args)
    filled = np.zeros(len(j), bool)
    filled[cand[hit]] = True
    return out, filled


def test_propagation_pass_equals_bounds_then_band_then_fill():
    """The fused pass gives what its three steps give one after another."""
    # depths known on a third of the pixels, every sample unmatched but a few
    R, t, lp, tv, alphas, I1, I2, gmin, gmax, rng = _propagation_scene(5, 1.02)
    j = np.where(rng.random(len(I1)) < 0.1, 5.0, np.nan)
    wmin, wmax = widen((gmin, gmax), 1)
    start1, step1, _ = lp.side(1)
    everywhere = np.ones((SIZE[1], SIZE[0]), np.uint8)
    got, filled = _propagate_pass(I1, lp.offset1, I2, lp.offset2, j, start1, step1, *alphas, wmin, wmax,
                                  float(np.linalg.norm(t)), everywhere, PropagateOptions(1, 6, 3, 0.5, 0))
    depths = grid_bounds(lp, wmin, wmax, (1.0, 1.0), (0.0, np.inf))
    lo, hi = search_band(lp, tv, depths, 1, alphas)
    lo[~np.isfinite(depths[1])], hi[~np.isfinite(depths[1])] = 0, -1  # no match nearby: no band
    want, wfilled = fill_from_band(I1, lp.offset1, I2, lp.offset2, j, lo, hi, 6, 3, 0.5)
    assert wfilled.sum() > 1000
    np.testing.assert_array_equal(filled, wfilled)
    np.testing.assert_array_equal(got, want)
    # only samples on active pixels are tried; they get the same partners
    active = (rng.random((SIZE[1], SIZE[0])) < 0.5).astype(np.uint8)
    part, pfilled = _propagate_pass(I1, lp.offset1, I2, lp.offset2, j, start1, step1, *alphas, wmin, wmax,
                                    float(np.linalg.norm(t)), active, PropagateOptions(1, 6, 3, 0.5, 0))
    px = np.floor(lp.all_points1()).astype(int)
    on = active[np.clip(px[:, 1], 0, SIZE[1] - 1), np.clip(px[:, 0], 0, SIZE[0] - 1)] == 1
    np.testing.assert_array_equal(pfilled, filled & on)
    np.testing.assert_array_equal(part[pfilled], got[pfilled])
    # the pass widens the raw grids itself, for the samples it tries: the same partners
    raw, rfilled = _propagate_pass(I1, lp.offset1, I2, lp.offset2, j, start1, step1, *alphas, gmin, gmax,
                                   float(np.linalg.norm(t)), everywhere,
                                   PropagateOptions(1, 6, 3, 0.5, 0, np.inf, -1, 0.0, 1))
    np.testing.assert_array_equal(rfilled, filled)
    np.testing.assert_array_equal(raw, got)


def test_propagation_next_to_a_depth_edge_searches_each_surface_in_turn():
    # the neighbours of a third of the pixels hold two surfaces, three times apart in distance
    R, t, lp, tv, alphas, I1, I2, gmin, gmax, _ = _propagation_scene(6, 3.0)
    j = np.full(len(I1), np.nan)
    start1, step1, _ = lp.side(1)
    everywhere = np.ones((SIZE[1], SIZE[0]), np.uint8)
    args = (I1, lp.offset1, I2, lp.offset2, j, start1, step1, *alphas, gmin, gmax, float(np.linalg.norm(t)), everywhere)
    split = lambda *slack_margin: PropagateOptions(1, 6, 3, 0.5, 0, np.inf, *slack_margin)  # noqa: E731
    both = grid_bounds(lp, gmin, gmax, (1.0, 1.0), (0.0, np.inf))
    lo, hi = search_band(lp, tv, both, 1, alphas)
    wide = np.isfinite(both[1]) & (hi - lo + 1 > 6)
    assert wide.sum() > 0.5 * np.isfinite(both[1]).sum()
    plain, off = _propagate_pass(*args, split(-1))
    assert not off[wide].any()  # too wide: left alone
    got, on = _propagate_pass(*args, split(1, 0.0))
    np.testing.assert_array_equal(on[~wide], off[~wide])  # narrow bands: as before
    np.testing.assert_array_equal(got[~wide], plain[~wide])
    on &= wide
    assert on.sum() > 1000
    # each partner lies in the band of one end's distance (1 sample wider, half a sample of parabola)
    for which, g in (("near", gmin), ("far", gmax)):
        d = grid_bounds(lp, g, g, (1.0, 1.0), (0.0, np.inf))
        lo, hi = search_band(lp, tv, (d[0], d[0]), 1, alphas)
        inside = on & (got >= lo - 0.5) & (got <= hi + 0.5)
        if which == "near":
            in_near = inside
        else:
            assert np.all((in_near | inside)[on])
            assert in_near.sum() > 100 and inside.sum() > 100
    # a margin between the two surfaces' correlations keeps only the clearer samples
    _, strict = _propagate_pass(*args, split(1, 0.2))
    strict &= wide
    assert 0 < strict.sum() < on.sum() and not (strict & ~on).any()
