"""Search bands (matching/band.py): depth ranges to line-2 sample ranges, in one pass and from a coarse level."""

import numpy as np

from sefm_recon.geometry.epipolar import line_alphas
from sefm_recon.geometry.two_view import TwoView
from sefm_recon.matching.band import coarse_search_band, depth_grids, invert_band, search_band, widen
from sefm_recon.matching.sefm import CoarseLevel

from .conftest import LINE_K as K
from .conftest import LINE_SIZE as SIZE
from .conftest import grid_bounds, tilted_lines


def _band_reference(a1, off1, a2, off2, dmin, dmax, B, slack):
    lo = np.empty(len(a1), np.int64)
    hi = np.empty(len(a1), np.int64)
    for l in range(len(off1) - 1):
        s1, e1, s2, e2 = off1[l], off1[l + 1], off2[l], off2[l + 1]
        x2 = a2[s2:e2]
        for i in range(s1, e1):
            a_hi = np.arctan2(dmin[i] * np.sin(a1[i]), dmin[i] * np.cos(a1[i]) - B)
            a_lo = np.arctan2(dmax[i] * np.sin(a1[i]), dmax[i] * np.cos(a1[i]) - B) if np.isfinite(dmax[i]) else a1[i]
            lo[i] = np.clip(np.searchsorted(x2, a_lo, "left") - slack, 0, e2 - s2 - 1)
            hi[i] = np.clip(np.searchsorted(x2, a_hi, "right") - 1 + slack, -1, e2 - s2 - 1)
    return lo, hi


def test_depth_band_and_its_inverse_match_references():
    R, t, lp = tilted_lines()
    tv = TwoView(K, K, R, t)
    a1, a2 = line_alphas(lp, K, np.eye(3), 1), line_alphas(lp, K, R.T, 2)
    rng = np.random.default_rng(0)
    dmin = rng.uniform(2, 4, len(a1))
    dmax = np.where(rng.random(len(a1)) < 0.2, np.inf, dmin * rng.uniform(1.0, 3.0, len(a1)))
    lo, hi = search_band(lp, tv, (dmin, dmax), 3, (a1, a2))
    rlo, rhi = _band_reference(a1, lp.offset1, a2, lp.offset2, dmin, dmax, np.linalg.norm(t), 3)
    np.testing.assert_array_equal(lo, rlo)
    np.testing.assert_array_equal(hi, rhi)
    # The inverse band: line-2 sample k may match line-1 sample i iff i's
    # (monotone-widened) band holds k.
    first, last = invert_band(lo, hi, lp.offset1, lp.offset2)
    for l in (0, len(lp) // 2, len(lp) - 1):
        s1, e1, s2, e2 = lp.offset1[l], lp.offset1[l + 1], lp.offset2[l], lp.offset2[l + 1]
        hm = np.maximum.accumulate(hi[s1:e1])
        lm = np.minimum.accumulate(lo[s1:e1][::-1])[::-1]
        for k in range(e2 - s2):
            ok = np.flatnonzero((lm <= k) & (hm >= k))
            if len(ok):
                assert first[s2 + k] == ok[0] and last[s2 + k] == ok[-1]


def _coarse_bounds(lp, coarse, radius, depths):
    """Reference ranges of :func:`coarse_search_band`: the coarse matches' widened grids, read under each sample."""
    dm = coarse.matches
    grids = widen(depth_grids(dm.uv1, np.linalg.norm(dm.xyz, axis=1), coarse.shape), radius)
    return grid_bounds(lp, *grids, coarse.scale, depths)


def test_coarse_band_in_one_pass_equals_bounds_then_band():
    R, t, lp = tilted_lines()
    tv = TwoView(K, K, R, t)
    alphas = line_alphas(lp, K, np.eye(3), 1), line_alphas(lp, K, R.T, 2)
    rng = np.random.default_rng(1)

    class Coarse:  # coarse matches on a third of the reduced image, at 2-6 m
        uv1 = rng.uniform(0, (SIZE[0] // 2, SIZE[1] // 2), (3000, 2))
        xyz = rng.normal(size=(3000, 3)) * 0.1 + [0.0, 0.0, 4.0]

    level = CoarseLevel(Coarse, (0.5, 0.5), (SIZE[1] // 2, SIZE[0] // 2))
    want = search_band(lp, tv, _coarse_bounds(lp, level, 1, (1.0, np.inf)), 3, alphas)
    got = coarse_search_band(lp, tv, level, 1, (1.0, np.inf), 3, alphas)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    assert (want[1] - want[0] < 40).mean() > 0.2  # some bands narrowed by the coarse depths


def test_coarse_bounds_follow_the_coarse_depths_and_fall_back_elsewhere():
    R, t, lp = tilted_lines()

    class Coarse:  # the two fields the coarse band reads
        uv1 = np.array([[100.25, 100.25], [101.25, 100.25]])
        xyz = np.array([[0.0, 0.0, 3.0], [0.0, 0.0, 5.0]])

    shape = (SIZE[1] // 2, SIZE[0] // 2)
    level = CoarseLevel(Coarse, (0.5, 0.5), shape)
    dmin, dmax = _coarse_bounds(lp, level, 1, (1.0, np.inf))
    pts = lp.all_points1() * 0.5
    near = (np.abs(np.floor(pts[:, 0]) - 100.5) <= 1.5) & (np.abs(np.floor(pts[:, 1]) - 100) <= 1)
    assert near.any() and (~near).any()
    # within a coarse pixel of both coarse matches: their range; far away: the global one
    both = (np.floor(pts[:, 0]) >= 100) & (np.floor(pts[:, 0]) <= 101) & (np.abs(np.floor(pts[:, 1]) - 100) <= 1)
    np.testing.assert_allclose(dmin[both], 3.0)
    np.testing.assert_allclose(dmax[both], 5.0)
    assert np.all(dmin[~near] == 1.0) and np.all(np.isinf(dmax[~near]))
    # and the band search reads exactly these ranges
    tv = TwoView(K, K, R, t)
    alphas = line_alphas(lp, K, np.eye(3), 1), line_alphas(lp, K, R.T, 2)
    got = coarse_search_band(lp, tv, level, 1, (1.0, np.inf), 3, alphas)
    want = search_band(lp, tv, (dmin, dmax), 3, alphas)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


def test_depth_grids_add_points_in_place_as_if_all_at_once():
    rng = np.random.default_rng(2)
    uv = rng.uniform(-1, 11, size=(300, 2))  # some outside the 8x10 grid
    dist = rng.uniform(1, 5, size=300)
    gmin, gmax = depth_grids(uv, dist, (8, 10))
    grids = depth_grids(uv, dist, (8, 10), np.arange(300) < 100)
    depth_grids(uv[100:], dist[100:], (8, 10), grids=grids)
    np.testing.assert_array_equal(grids[0], gmin)
    np.testing.assert_array_equal(grids[1], gmax)
    r, c = 3, 4
    inside = (np.floor(uv[:, 1]) == r) & (np.floor(uv[:, 0]) == c)
    assert inside.any()
    assert gmin[r, c] == np.float32(dist[inside].min()) and gmax[r, c] == np.float32(dist[inside].max())
    empty = np.isinf(gmin)
    assert np.all(np.isinf(gmax[empty])) and np.all(gmax[empty] < 0)
