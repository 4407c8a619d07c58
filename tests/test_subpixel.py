"""Sub-pixel refinement (matching/subpixel.py): cut, stretched and sheared windows, and the shear between lines."""

import numpy as np
import pytest

from sefm_recon.matching.subpixel import (Channels, SubpixelOptions, _local_slope, line_shear, next_line,
                                          refine_subpixel)
from sefm_recon.matching.zncc import zncc3, zncc3_sheared


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


def test_next_line_skips_missing_half_planes():
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
