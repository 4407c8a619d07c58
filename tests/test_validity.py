"""The 2-D neighbour check and its median (matching/validity.py) against plain numpy references."""

import numpy as np

from sefm_recon.matching.validity import NeighbourCheck, grid_median_check, neighbour_consistency, neighbour_median


def test_two_d_check_drops_a_point_the_majority_disagrees_with():
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
    # Point 0 at (0, 0) has 8 neighbours in its 5x5 window: four at 1 and four at 3.
    uv = np.array([[0, 0], [1, 0], [2, 0], [0, 1], [1, 1], [2, 1], [0, 2], [1, 2], [2, 2]], float) + 0.5
    value = np.array([0.0, 1, 1, 1, 1, 3, 3, 3, 3])
    for x, kept in ((0.0, False), (0.5, True), (3.4, True), (4.5, False)):
        value[0] = x
        keep, median = neighbour_median(uv, value, (3, 3), 2, 0.5, 6, False)
        assert keep[0] == kept == neighbour_consistency(uv, value, (3, 3), 2, 0.5, 6, False)[0], x
        assert median[0] == (2.0 if kept else x)  # the mean of the middle two, where kept


def test_neighbour_median_is_within_a_bin_of_the_exact_median():
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
