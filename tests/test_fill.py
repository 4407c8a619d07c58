"""Gap filling (matching/fill.py): correlation fills and bridges, and the depth edges they leave alone."""

import numpy as np

from sefm_recon.matching.fill import bridge_gaps, fill_from_band, fill_gaps


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
