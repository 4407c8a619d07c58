"""The per-line numba kernels against plain numpy references, and the coarse-to-fine band."""

import cv2
import numpy as np
import pytest

from sefm_recon.geometry import kernels as gk
from sefm_recon.geometry.epipolar import line_alphas, line_pairs, ray_angles, sample_line_channels
from sefm_recon.matching.band import depth_grids, invert_band, search_band, widen
from sefm_recon.matching.fill import bridge_gaps, fill_from_band, fill_gaps
from sefm_recon.matching.propagate import PropagateOptions, propagate_candidates
from sefm_recon.matching.sefm import CoarseLevel
from sefm_recon.matching.subpixel import Channels, SubpixelOptions, _local_slope, line_shear, refine_subpixel
from sefm_recon.matching.zncc import zncc, zncc3, zncc3_sheared, zncc_search
from sefm_recon.geometry.two_view import TwoView

from .conftest import rot_y

K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
SIZE = (640, 480)


def _lp():
    R = rot_y(-0.15)
    t = -R @ np.array([1.0, 0.1, 0.2])
    return R, t, line_pairs(K, K, R, t, SIZE, SIZE)


def test_line_alphas_match_ray_angles():
    R, t, lp = _lp()
    for which, Rc, pts in ((1, np.eye(3), lp.all_points1()), (2, R.T, lp.all_points2())):
        _, ref = ray_angles(K, Rc, lp.basis, pts)
        np.testing.assert_allclose(line_alphas(lp, K, Rc, which), ref, atol=1e-12)


def test_neighbour_channels_sample_the_neighbour_lines_at_the_same_ray_angle():
    R, t, lp = _lp()
    # A linear image: sampled value = a known function of the position, so the
    # samples tell where the kernel looked.
    yy, xx = np.mgrid[0:SIZE[1], 0:SIZE[0]].astype(np.float32)
    img = np.stack([xx + 0.5, yy + 0.5], axis=2)  # value = COLMAP position of the pixel centre
    I = sample_line_channels(img, lp, K, np.eye(3), 1, neighbours=1, neighbour_step=1.0)
    assert I.shape == (lp.offset1[-1], 6)
    centre = lp.all_points1()
    inside = (centre[:, 0] > 3) & (centre[:, 0] < SIZE[0] - 3) & (centre[:, 1] > 3) & (centre[:, 1] < SIZE[1] - 3)
    np.testing.assert_allclose(I[inside, 2:4], centre[inside], atol=1e-3)
    phi_c, a_c = ray_angles(K, np.eye(3), lp.basis, centre[inside])
    for o, cols in ((-1, slice(0, 2)), (1, slice(4, 6))):
        phi, a = ray_angles(K, np.eye(3), lp.basis, I[inside, cols].astype(np.float64))
        d = (phi - phi_c - o * lp.phi_step + np.pi) % (2 * np.pi) - np.pi
        assert np.abs(d).max() < 1e-3 * lp.phi_step + 1e-6  # the neighbour half-plane...
        np.testing.assert_allclose(a, a_c, atol=1e-5)  # ...at the same angle from the baseline
        # ...about one line step away
        step = np.linalg.norm(I[inside, cols] - centre[inside], axis=1)
        assert 0.2 < np.median(step) < 1.5


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
    R, t, lp = _lp()
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


def _grid_bounds(lp, gmin, gmax, scale, depths):
    """Reference: each line-1 sample's distance range from the grid cell under it, else ``depths`` (numpy)."""
    pts = lp.all_points1()
    H, W = gmin.shape
    c = np.clip(np.floor(pts[:, 0] * scale[0]).astype(int), 0, W - 1)
    r = np.clip(np.floor(pts[:, 1] * scale[1]).astype(int), 0, H - 1)
    known = np.isfinite(gmin[r, c])
    return (np.where(known, gmin[r, c], depths[0]).astype(np.float64),
            np.where(known, gmax[r, c], depths[1]).astype(np.float64))


def _coarse_bounds(lp, coarse, radius, depths):
    """Reference ranges of :func:`coarse_search_band`: the coarse matches' widened grids, read under each sample."""
    dm = coarse.matches
    grids = widen(depth_grids(dm.uv1, np.linalg.norm(dm.xyz, axis=1), coarse.shape), radius)
    return _grid_bounds(lp, *grids, coarse.scale, depths)


def test_coarse_band_in_one_pass_equals_bounds_then_band():
    from sefm_recon.matching.band import coarse_search_band

    R, t, lp = _lp()
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
    from sefm_recon.matching.band import coarse_search_band

    R, t, lp = _lp()

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


def test_two_d_check_drops_a_point_the_majority_disagrees_with():
    from sefm_recon.matching.validity import NeighbourCheck, grid_median_check, neighbour_consistency, neighbour_median

    rows, cols = np.mgrid[0:5, 0:5]
    uv = np.stack([cols.ravel(), rows.ravel()], 1) + 0.5  # pixel centres
    value = np.ones(25)
    value[12] = 5.0  # the centre disagrees with all 24 neighbours
    value[0] = 1.5  # a corner within tol of its neighbours
    mask = np.ones(25, bool)
    keep, median = neighbour_median(uv, value, (5, 5), 2, 1.0, 6, False, mask)
    np.testing.assert_array_equal(keep, neighbour_consistency(uv, value, (5, 5), 2, 1.0, 6, False, mask))
    assert not keep[12] and keep[0] and keep[1:12].all()
    assert median[0] == 1.0  # the neighbours' median, the point itself left out
    assert median[12] == 5.0  # a dropped point keeps its own value
    _, support, _ = grid_median_check(uv, value, mask, 5, 5, NeighbourCheck(2, 1.0, 6))
    assert support[12] == 24 and support[0] == 8
    # a point outside the mask neither takes part nor is kept
    mask[12] = False
    keep, median = neighbour_median(uv, value, (5, 5), 2, 1.0, 6, False, mask)
    np.testing.assert_array_equal(keep, neighbour_consistency(uv, value, (5, 5), 2, 1.0, 6, False, mask))
    assert not keep[12] and keep[:12].all() and keep[13:].all() and median[12] == 5.0
    _, support, _ = grid_median_check(uv, value, mask, 5, 5, NeighbourCheck(2, 1.0, 6))
    assert support[0] == 7 and support[6] == 14  # the masked centre no longer counts


def test_two_d_check_with_an_even_count_keeps_what_lies_near_either_middle_value():
    from sefm_recon.matching.validity import neighbour_consistency, neighbour_median

    # Point 0 at (0, 0) has 8 neighbours in its 5x5 window: four at 1 and four at 3.
    uv = np.array([[0, 0], [1, 0], [2, 0], [0, 1], [1, 1], [2, 1], [0, 2], [1, 2], [2, 2]], float) + 0.5
    value = np.array([0.0, 1, 1, 1, 1, 3, 3, 3, 3])
    for x, kept in ((0.0, False), (0.5, True), (3.4, True), (4.5, False)):
        value[0] = x
        keep, median = neighbour_median(uv, value, (3, 3), 2, 0.5, 6, False)
        assert keep[0] == kept == neighbour_consistency(uv, value, (3, 3), 2, 0.5, 6, False)[0], x
        assert median[0] == (2.0 if kept else x)  # the mean of the middle two, where kept


def test_neighbour_median_is_within_a_bin_of_the_exact_median():
    from sefm_recon.matching.validity import neighbour_consistency, neighbour_median

    rng = np.random.default_rng(3)
    h, w, r, tol, bins = 12, 15, 2, 0.6, 16
    uv = rng.uniform(0, [w, h], (150, 2))
    value = rng.normal(size=150).round(1)  # ties included
    mask = rng.uniform(size=150) < 0.9
    keep, median = neighbour_median(uv, value, (h, w), r, tol, 3, True, mask, bins)
    # the same keep mask as the check alone
    np.testing.assert_array_equal(keep, neighbour_consistency(uv, value, (h, w), r, tol, 3, True, mask))
    grid = np.full((h, w), np.nan)
    for k in np.flatnonzero(mask):  # the first point of a cell wins
        i, j = np.floor(uv[k, ::-1]).astype(int)
        if np.isnan(grid[i, j]):
            grid[i, j] = value[k]
    for k in range(150):
        i, j = np.floor(uv[k, ::-1]).astype(int)
        win = grid[max(i - r, 0):i + r + 1, max(j - r, 0):j + r + 1].copy()
        win[i - max(i - r, 0), j - max(j - r, 0)] = np.nan  # the point's own cell is left out
        v = win[np.isfinite(win)]
        if keep[k] and len(v) >= 3:
            assert abs(median[k] - np.median(v)) <= 2 * tol / bins + 1e-6, k
        else:
            assert median[k] == value[k]
    assert keep.sum() > 50 and (~keep & mask).sum() > 5  # both cases seen


def test_points_at_distance_lie_on_the_ray_and_project_to_the_epipolar_line():
    from sefm_recon.geometry.triangulate import project

    K1 = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    K2 = np.array([[520.0, 0, 300], [0, 520, 250], [0, 0, 1]])
    a = 0.1
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    t = np.array([-1.0, 0.05, 0.1])
    rng = np.random.default_rng(0)
    uv1 = rng.uniform([0, 0], [640, 480], (50, 2))
    dist = rng.uniform(2, 10, 50)
    X, uv2 = gk.points_at_distance(np.linalg.inv(K1), K2, R, t, uv1, dist)
    np.testing.assert_allclose(np.linalg.norm(X, axis=1), dist)
    np.testing.assert_allclose(project(K1, np.eye(3), np.zeros(3), X), uv1, atol=1e-9)
    np.testing.assert_allclose(project(K2, R, t, X), uv2, atol=1e-9)


@pytest.mark.parametrize("jpos", [20.0, 20.3, 35.75])
def test_three_zncc_in_one_pass_equal_three_single_ones(jpos):
    rng = np.random.default_rng(1)
    a = rng.normal(size=(60, 3)).astype(np.float32)
    b = rng.normal(size=(60, 3)).astype(np.float32)
    got = zncc3(a, 25, b, jpos, 5)
    want = [zncc(a, 25, b, jpos + d, 5) for d in (-1.0, 0.0, 1.0)]
    np.testing.assert_allclose(got, want, atol=1e-9)


def _zncc_ref(a, i, b, jpos, s_lo, s_hi):
    """ZNCC over window offsets s_lo..s_hi, b linearly interpolated at jpos + s (numpy reference)."""
    s = np.arange(s_lo, s_hi + 1)
    x = a[i + s].ravel().astype(float)
    j0 = int(np.floor(jpos))
    f = jpos - j0
    y = ((1 - f) * b[j0 + s] + f * b[np.minimum(j0 + s + 1, len(b) - 1)]).ravel().astype(float)
    x -= x.mean()
    y -= y.mean()
    return float(x @ y / np.sqrt((x @ x) * (y @ y)))


@pytest.mark.parametrize("i, jpos, s_lo, s_hi", [
    (2, 20.3, -2, 5),    # window cut at the start of line 1
    (25, 1.4, 0, 5),     # at the start of line 2 (jpos - 1 + s >= 0)
    (25, 55.6, -5, 2),   # at the end of line 2 (jpos + 1 + s < 59)
])
def test_zncc_near_line_ends_uses_the_cut_window(i, jpos, s_lo, s_hi):
    rng = np.random.default_rng(3)
    a = rng.normal(size=(60, 3)).astype(np.float32)
    b = rng.normal(size=(60, 3)).astype(np.float32)
    got = zncc3(a, i, b, jpos, 5)
    want = [_zncc_ref(a, i, b, jpos + d, s_lo, s_hi) for d in (-1.0, 0.0, 1.0)]
    np.testing.assert_allclose(got, want, atol=1e-6)


def test_zncc_window_too_short_near_a_line_end_is_rejected():
    rng = np.random.default_rng(4)
    a = rng.normal(size=(60, 2)).astype(np.float32)
    b = rng.normal(size=(60, 2)).astype(np.float32)
    # fewer than half + 1 = 6 samples fit: i = 59 leaves offsets -5..0, but line 2 ends at jpos + 0
    assert zncc3(a, 59, b, 59.0, 5)[1] == -2.0
    assert zncc(a, 59, b, 59.0, 5) == -2.0  # single ZNCC (search, fill) needs the whole window
    assert zncc(a, 0, b, 30.0, 5) == -2.0
    assert zncc(a, 30, b, 30.0, 5) > -2.0


def test_refine_subpixel_refines_and_scores_samples_at_the_line_ends():
    # line 2 is line 1 shifted by 3.4 samples of a smooth signal
    n = 80
    x = np.arange(n + 10, dtype=float)
    sig = lambda t: np.stack([np.sin(0.35 * t) + 0.5 * np.sin(0.11 * t + 1), np.cos(0.23 * t)], 1)
    a = sig(x[:n]).astype(np.float32)
    b = sig(x[:n + 6] - 3.4).astype(np.float32)  # b[k] = a at k - 3.4: a[i] sits at j = i + 3.4
    off1 = np.array([0, n], np.int64)
    off2 = np.array([0, n + 6], np.int64)
    j = np.arange(n, dtype=float) + 3.0  # the DP's whole-sample answer
    out, z = refine_subpixel(a, off1, b, off2, j, SubpixelOptions(7, 1.0), Channels())
    for i in (0, 1, n - 2):  # the full 15-sample window does not fit at any of these
        assert z[i] > 0.95
        assert abs(out[i] - (i + 3.4)) < 0.15  # from 0.4 off (the parabola is not exact)
    assert abs(out[40] - 43.4) < 0.05

    # Channels c0:c1 of wider arrays (a view in the kernel) give what a copy of them gives.
    rng = np.random.default_rng(0)
    wide_a = np.concatenate([rng.normal(size=(n, 1)), a, rng.normal(size=(n, 3))], 1).astype(np.float32)
    wide_b = np.concatenate([rng.normal(size=(n + 6, 1)), b, rng.normal(size=(n + 6, 3))], 1).astype(np.float32)
    got = refine_subpixel(wide_a, off1, wide_b, off2, j, SubpixelOptions(7, 1.0, 6, 0.1), Channels(1, 3))
    want = refine_subpixel(a, off1, b, off2, j, SubpixelOptions(7, 1.0, 6, 0.1), Channels())
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    every = refine_subpixel(wide_a, off1, wide_b, off2, j, SubpixelOptions(7, 1.0), Channels())
    assert not np.array_equal(every[1], want[1])


def test_local_slope_of_the_partners():
    j = np.array([10.0, 11.5, np.nan, 14.5, 16.0, 17.5, np.nan, np.nan])
    assert _local_slope(j, 3, 8, 2) == pytest.approx(1.5)  # j[1], j[5]: (17.5 - 11.5) / 4
    assert _local_slope(j, 5, 8, 2) == pytest.approx(1.5)  # nothing at 7: the nearest, j[5] itself
    assert _local_slope(np.full(5, np.nan), 2, 5, 2) == 1.0
    assert _local_slope(np.array([0.0, 5.0, 10.0]), 1, 3, 1) == 2.0  # clipped
    assert _local_slope(np.array([5.0, 5.0, 5.0]), 1, 3, 1) == 0.5


def test_stretched_window_finds_the_partner_on_a_slanted_surface():
    # line 2 shows line 1's texture stretched 1.5 times: a[i] sits at j = 1.5 i + 4.3
    rng = np.random.default_rng(6)
    n = 120
    t = np.arange(n, dtype=float)
    noise = rng.normal(size=(n + 4, 2))
    base = (noise[:-4] + 2 * noise[1:-3] + 3 * noise[2:-2] + 2 * noise[3:-1] + noise[4:]) / 9  # texture ~3 samples
    a = base.astype(np.float32)
    tj = np.arange(int(1.5 * n) + 10, dtype=float)
    src = (tj - 4.3) / 1.5
    b = np.stack([np.interp(src, t, base[:, c]) for c in range(2)], 1).astype(np.float32)
    i, jpos = 50, 1.5 * 50 + 4.3
    unstretched = zncc3_sheared(a, i, b, 60.0, 7, 1.0, 0.0, 0, a.shape[1])
    assert unstretched == pytest.approx(zncc3(a, i, b, 60.0, 7), abs=1e-9)
    plain = zncc3(a, i, b, jpos, 7)[1]
    stretched = zncc3_sheared(a, i, b, jpos, 7, 1.5, 0.0, 0, a.shape[1])[1]
    assert stretched > 0.99 and stretched > plain + 0.05
    # refinement from the whole-sample answer, with and without the stretch
    off1 = np.array([0, n], np.int64)
    off2 = np.array([0, len(b)], np.int64)
    truth = 1.5 * t + 4.3
    j = np.where((t > 10) & (t < n - 10), np.rint(truth), np.nan)
    inner = np.isfinite(j)
    got, _ = refine_subpixel(a, off1, b, off2, j, SubpixelOptions(7, 1.0, 6, 0.1), Channels())
    plain, _ = refine_subpixel(a, off1, b, off2, j, SubpixelOptions(7, 1.0, 0, 0.1), Channels())
    err = np.abs(got[inner] - truth[inner])
    assert np.median(err) < 0.05 and err.mean() < 0.2 * np.abs(plain[inner] - truth[inner]).mean()


def _sheared_lines(h, n=140, offset=3.7, seed=8):
    """One line pair of 3 neighbour lines (columns -1, 0, +1): line 2's neighbour o shows line 1's at o h samples on."""
    rng = np.random.default_rng(seed)
    t = np.arange(n + 40, dtype=float)
    noise = rng.normal(size=(n + 44, 3))
    tex = (noise[:-4] + 2 * noise[1:-3] + 3 * noise[2:-2] + 2 * noise[3:-1] + noise[4:]) / 9  # texture ~3 samples
    a = tex[20:20 + n].astype(np.float32)
    # a[i, o] is at j = i + offset + o h on line 2
    tj = np.arange(n, dtype=float)
    b = np.stack([np.interp(tj - offset - o * h + 20, t, tex[:, o + 1]) for o in (-1, 0, 1)], 1).astype(np.float32)
    return a, b, np.arange(n) + offset


def test_sheared_window_finds_the_partner_where_depth_changes_across_lines():
    a, b, truth = _sheared_lines(1.2)
    n = len(a)
    off = np.array([0, n], np.int64)
    t = np.arange(n)
    j = np.where((t > 12) & (t < n - 12), np.rint(truth), np.nan)
    inner = np.isfinite(j)
    shear = np.where(inner, 1.2, 0.0).astype(np.float32)
    got, z = refine_subpixel(a, off, b, off, j, SubpixelOptions(7, 1.0, 6, 0.1, 0.1), Channels(0, -1, -1, 1),
                             shear)
    plain, zp = refine_subpixel(a, off, b, off, j, SubpixelOptions(7, 1.0, 6, 0.1), Channels())
    err = np.abs(got[inner] - truth[inner])
    assert np.median(err) < 0.05 and err.mean() < 0.5 * np.abs(plain[inner] - truth[inner]).mean()
    assert np.median(z[inner]) > 0.95 and np.median(z[inner]) > np.median(zp[inner]) + 0.1  # at the whole-sample j
    # a shear under min_shear takes the unmoved window: the same answer
    small = np.where(inner, 0.05, 0.0).astype(np.float32)
    moved = refine_subpixel(a, off, b, off, j, SubpixelOptions(7, 1.0, 6, 0.1, 0.1), Channels(0, -1, -1, 1), small)
    np.testing.assert_array_equal(moved[0], plain)


def test_line_shear_reads_how_far_matches_move_from_one_line_to_the_next():
    # 5 parallel line pairs whose samples start at different ray angles (line l
    # 2 l samples on in image 1, 3 l in image 2); the ray at line-1 angle index
    # u meets line 2 at angle index u + 0.7 l - 4: 0.7 samples of shear per line
    L, n = 5, 60
    a1 = np.concatenate([0.5 + 0.01 * (np.arange(n) + 2 * l) for l in range(L)])
    a2 = np.concatenate([0.6 + 0.01 * (np.arange(n + 10) + 3 * l) for l in range(L)])
    off1 = np.arange(L + 1, dtype=np.int64) * n
    off2 = np.arange(L + 1, dtype=np.int64) * (n + 10)
    j = np.concatenate([(np.arange(n) + 2 * l) + 0.7 * l - 4 - 3 * l for l in range(L)])
    j[(j < 0) | (j > n + 9)] = np.nan
    nxt = np.array([1, 2, 3, 4, -1], np.int64)
    h = line_shear(j, a1, off1, a2, off2, nxt, 4, 2.0)
    ok = np.isfinite(j)
    np.testing.assert_allclose(h[ok], 0.7, atol=1e-6)
    assert np.all(h[~ok] == 0)
    # shears over max_shear are across a depth edge: left out (0 where nothing is left)
    assert np.all(line_shear(j, a1, off1, a2, off2, nxt, 4, 0.69) == 0)
    # no neighbour half-plane: no shear
    assert np.all(line_shear(j, a1, off1, a2, off2, np.full(L, -1, np.int64), 4, 5.0) == 0)


def test_shifted_window_matches_a_sample_next_to_a_depth_edge():
    # line 1: foreground texture up to sample 49, background from 50; in line 2
    # the foreground moved by 2 samples and the background by 6 (4 occluded)
    rng = np.random.default_rng(7)
    fg = rng.normal(size=(80, 3))
    bg = rng.normal(size=(120, 3))
    a = np.concatenate([fg[:50], bg[50:110]]).astype(np.float32)
    b = np.empty((116, 3), np.float32)
    b[2:52] = fg[:50]  # b[k] = fg[k - 2]
    b[:2] = rng.normal(size=(2, 3))
    b[52:56] = rng.normal(size=(4, 3))  # background seen only in view 2
    b[56:116] = bg[50:110]  # b[k] = bg[k - 6]
    i = 51  # background, one sample from the edge: its partner is 57
    centred, _ = zncc_search(a, i, b, 54.0, 7, 3, 0.98, 0)
    shifted, pos = zncc_search(a, i, b, 54.0, 7, 3, 0.98, 3)
    assert centred < 0.98 < shifted and pos == pytest.approx(57.0, abs=0.5)
    # inside the background, the centred window already does it (and is kept)
    z, pos = zncc_search(a, 80, b, 83.0, 7, 3, 0.98, 3)
    assert z > 0.99 and pos == pytest.approx(86.0, abs=0.5)



def test_shifted_window_does_not_cross_an_intensity_step():
    # line 1: background up to sample 49, a bright foreground from 50; in line 2
    # the foreground moved by -6 samples and the background by -2, so background
    # samples 46-49 are hidden behind the foreground in view 2
    rng = np.random.default_rng(3)
    bg = rng.normal(size=(60, 3))
    fg = rng.normal(size=(120, 3)) + 6.0  # a step of 6 on a texture of 1
    a = np.concatenate([bg[:50], fg[50:110]]).astype(np.float32)
    b = np.concatenate([bg[2:46], fg[50:110]]).astype(np.float32)  # b[k] = bg[k + 2] (k < 44), fg[k + 6]
    i = 49  # occluded in view 2
    # moved 3 samples into the foreground (windows of 5), the window finds the
    # foreground's partner: the hidden sample would take the foreground's depth
    centred, _ = zncc_search(a, i, b, 40.0, 7, 2, 0.98, 0)
    z, pos = zncc_search(a, i, b, 40.0, 7, 2, 0.98, 3)
    assert centred < 0.98 < z and pos == pytest.approx(43.0, abs=0.5)
    # with the step limit it is not moved across the edge, and stays unmatched
    z, _ = zncc_search(a, i, b, 40.0, 7, 2, 0.98, 3, 4.0)
    assert z < 0.98
    # a foreground sample next to the edge still moves its window into the foreground
    z, pos = zncc_search(a, 50, b, 40.0, 7, 2, 0.98, 3, 4.0)
    assert z > 0.98 and pos == pytest.approx(44.0, abs=0.5)


def _shifted_line(seed: int, n: int):
    """One line pair of white noise, line-1 sample i being line-2 sample i + 4: a, off, b, off2."""
    rng = np.random.default_rng(seed)
    b = np.repeat(rng.normal(size=(n + 10, 1)), 3, axis=1).astype(np.float32)
    return b[4:n + 4].copy(), np.array([0, n], np.int64), b, np.array([0, n + 10], np.int64)


def test_gap_filling_leaves_depth_edges_alone():
    n = 120
    a, off, b, off2 = _shifted_line(4, n)
    j = np.full(n, np.nan)
    # a fold: 20 samples between partners 2 apart (a depth edge), then a surface gap
    j[10], j[30] = 14.0, 16.0
    j[60], j[80] = 64.0, 84.0
    fold = np.arange(11, 30)
    _, ffree = fill_gaps(a, off, b, off2, j, 64, 3, 3, 0.9)
    assert ffree[fold].any()  # unlimited, the fold's samples near its ends find partners
    out, filled = fill_gaps(a, off, b, off2, j, 64, 3, 3, 0.9, 3.0)
    assert not filled[fold].any()
    assert filled[61:80].all()
    np.testing.assert_array_equal(np.rint(out[61:80]), np.arange(61, 80) + 4.0)
    # the band fill skips the fold's samples too (when asked), and fills the others
    lo = np.arange(n, dtype=np.int64) + 1
    hi = lo + 8
    _, gfilled = fill_from_band(a, off, b, off2, j, lo, hi, 12, 3, 0.9, 3.0)
    assert not gfilled[fold].any() and gfilled[40:55].all()
    _, ufilled = fill_from_band(a, off, b, off2, j, lo, hi, 12, 3, 0.9)
    assert ufilled[fold].all()


def test_fill_from_band_finds_the_shift_inside_a_narrow_band():
    n = 200
    a, off, b, off2 = _shifted_line(2, n)
    j = np.full(n, np.nan)
    lo = np.arange(n, dtype=np.int64) + 1
    hi = lo + 8
    hi[:20] = lo[:20] + 40  # too wide: left alone
    out, filled = fill_from_band(a, off, b, off2, j, lo, hi, 12, 3, 0.9)
    inner = np.arange(20, n - 10)
    assert filled[inner].all() and not filled[:20].any()
    # the best whole shift, then a parabola (white noise has no smooth peak: within half a sample)
    np.testing.assert_array_equal(np.rint(out[inner]), inner + 4.0)


def _propagation_scene(seed, ratio):
    """Line samples of a random blurred image in both views, and distance grids known on a third of the pixels.

    Returns ``R, t, lp, tv, alphas, I1, I2, gmin, gmax, rng``; ``gmax = ratio * gmin``.
    """
    R, t, lp = _lp()
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
    depths = _grid_bounds(lp, wmin, wmax, (1.0, 1.0), (0.0, np.inf))
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


def test_sample_points_are_those_of_the_line_matches():
    from sefm_recon.matching.points import PairGeometry, line_matches_to_points, sample_points

    R, t, lp = _lp()
    rng = np.random.default_rng(3)
    n = int(lp.offset1[-1])
    j = np.where(rng.random(n) < 0.3, rng.uniform(0, 50, n), np.nan)
    start1, step1, off1 = lp.side(1)
    start2, step2, _ = lp.side(2)
    Kinv = np.linalg.inv(K)
    Rt = np.ascontiguousarray(R.T)
    c2 = -Rt @ np.asarray(t, np.float64)
    geo = PairGeometry(start1, step1, off1, start2, step2, Kinv, Kinv, Rt, c2)
    idx, line, uv1, _, _, dist, valid = line_matches_to_points(j, np.zeros(n), 1.0, geo, 0.0, False)
    pick = np.sort(rng.choice(len(idx), 500, replace=False))
    got = sample_points(idx[pick], line[pick], j, geo, 0.0)
    np.testing.assert_array_equal(got[0], uv1[pick])
    np.testing.assert_array_equal(got[1], dist[pick])
    np.testing.assert_array_equal(got[2], valid[pick])


def test_propagation_next_to_a_depth_edge_searches_each_surface_in_turn():
    # the neighbours of a third of the pixels hold two surfaces, three times apart in distance
    R, t, lp, tv, alphas, I1, I2, gmin, gmax, _ = _propagation_scene(6, 3.0)
    j = np.full(len(I1), np.nan)
    start1, step1, _ = lp.side(1)
    everywhere = np.ones((SIZE[1], SIZE[0]), np.uint8)
    args = (I1, lp.offset1, I2, lp.offset2, j, start1, step1, *alphas, gmin, gmax, float(np.linalg.norm(t)), everywhere)
    split = lambda *slack_margin: PropagateOptions(1, 6, 3, 0.5, 0, np.inf, *slack_margin)  # noqa: E731
    both = _grid_bounds(lp, gmin, gmax, (1.0, 1.0), (0.0, np.inf))
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
        d = _grid_bounds(lp, g, g, (1.0, 1.0), (0.0, np.inf))
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


def test_galloping_search_equals_bisection_from_any_guess():
    from sefm_recon.geometry.kernels import _first_above, _first_at_least, _gallop

    rng = np.random.default_rng(0)
    for _ in range(3000):
        n = int(rng.integers(1, 40))
        a = np.sort(rng.integers(0, 20, n)).astype(float)  # ties included
        s = int(rng.integers(0, n))
        e = int(rng.integers(s, n + 1))
        v = float(rng.integers(-2, 22)) + float(rng.choice([0.0, 0.5]))
        guess = int(rng.integers(-3, n + 4))  # also outside [s, e]
        assert _gallop(a, s, e, v, guess, False) == _first_at_least(a, s, e, v)
        assert _gallop(a, s, e, v, guess, True) == _first_above(a, s, e, v)


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


def test_next_line_skips_missing_half_planes():
    from sefm_recon.matching.subpixel import next_line

    class Lines:  # the two fields next_line reads
        phi_step = 0.01
        phi = np.array([0.00, 0.01, 0.02, 0.04, 0.05])  # the half-plane at 0.03 crosses only one image

        def __len__(self):
            return len(self.phi)

    np.testing.assert_array_equal(next_line(Lines(), 1.0), [1, 2, -1, 4, -1])
    Lines.phi = Lines.phi[::-1].copy()  # lines in the other order
    np.testing.assert_array_equal(next_line(Lines(), 1.0), [-1, 0, -1, 2, 3])
    # all the way round (an epipole inside the image): the last line's next is the first
    Lines.phi_step = 2 * np.pi / 628
    Lines.phi = np.arange(628) * Lines.phi_step
    assert next_line(Lines(), 1.0)[-1] == 0


def test_bridge_gaps_interpolates_short_gaps_inside_a_surface_only():
    k = np.arange(40.0)
    j = 5.0 + 1.2 * k  # a slanted surface
    j[10:12] = np.nan  # a gap of 2: bridged
    j[20:25] = np.nan  # 5: too long
    off = np.array([0, 40], np.int64)
    out, bridged = bridge_gaps(j, off, 4, 0.5, 2.0, 0.5)
    np.testing.assert_array_equal(np.flatnonzero(bridged), [10, 11])
    np.testing.assert_allclose(out[10:12], 5.0 + 1.2 * k[10:12])
    assert np.isnan(out[20:25]).all()
    # a depth step in the gap (the partners jump, or bend past the tolerance on one side): left alone
    step = 5.0 + np.where(k < 11, k, k + 6.0)
    step[10:12] = np.nan
    assert not bridge_gaps(step, off, 4, 0.5, 2.0, 0.5)[1].any()
    bend = 5.0 + np.where(k < 11, k, 11 + 1.9 * (k - 11))
    bend[11:13] = np.nan
    assert not bridge_gaps(bend, off, 4, 0.5, 2.0, 0.5)[1].any()
    assert bridge_gaps(bend, off, 4, 0.5, 2.0, 1.0)[1].sum() == 2
    # nothing matched beyond an end: not judged, not bridged; gaps do not run across lines
    edge = 5.0 + k
    edge[1:3] = np.nan
    edge[0] = 5.0
    assert not bridge_gaps(edge[:4], np.array([0, 4], np.int64), 4, 0.5, 2.0, 0.5)[1].any()
    two = 5.0 + k
    two[18:22] = np.nan
    assert not bridge_gaps(two, np.array([0, 20, 40], np.int64), 4, 0.5, 2.0, 0.5)[1].any()
