"""The median and plane fit over each surface (:mod:`sefm_recon.matching.surfaces`)."""

import numpy as np
import pytest

from sefm_recon.matching.surfaces import MEDIAN_SAME_SURFACE, surface_median


def test_the_surface_median_removes_scatter_and_keeps_depth_edges_and_holes():
    rng = np.random.default_rng(3)
    rows, cols = 60, 80
    c = np.arange(cols, dtype=np.float32)
    truth = np.where(c < 40, 10.0 + 0.05 * c, 30.0).astype(np.float32)  # a slanted surface, then a step
    truth = np.broadcast_to(truth, (rows, cols)).copy()
    disp = truth + rng.choice([-1.5, 0.0, 1.5], (rows, cols), p=[0.15, 0.7, 0.15]).astype(np.float32)
    disp[20:30, 10:20] = -1.0  # a hole: the matcher's checks rejected it
    disp[45:50, 60:70] = 0.0  # a block of cells at a low valid disparity
    before = np.abs(disp - truth) > 1.0
    out = disp.copy()
    surface_median(out, -0.5)
    assert (out[20:30, 10:20] == -1.0).all()  # holes stay holes
    inner = (np.abs(np.arange(cols) - 40) > 3)[None, :] & (disp > -0.5) & (np.abs(disp - truth) <= 2.0)
    assert before[inner].mean() > 0.25 and (np.abs(out - truth) > 1.0)[inner].mean() < 0.02  # the scatter goes
    # across the depth edge the other surface is more than MEDIAN_SAME_SURFACE away: no cell takes it
    assert 30.0 - (10.0 + 0.05 * 39) > MEDIAN_SAME_SURFACE
    assert (out[:, :40] < 15.0).all()
    assert (np.abs(out[:, 41:] - 30.0)[disp[:, 41:] > 20.0] <= 1.5).all()
    assert (out[45:50, 60:70] == 0.0).all()  # a block of its own is a surface of its own
    # the holes' cells do not pull their neighbours: the median next to a hole is the surface's
    ring = np.zeros_like(inner)
    ring[18:32, 8:22] = True
    ring[20:30, 10:20] = False
    assert (np.abs(out - truth)[ring & inner] <= 1.0).all()


def test_the_local_planes_are_the_least_squares_planes_of_each_window():
    from sefm_recon.matching.surfaces import PLAIN_FIT_HALF, local_planes

    rng = np.random.default_rng(5)
    rows, cols = 90, 70  # more rows than a block of PLANE_ROWS_A_BLOCK: the sums slide across blocks
    r, c = np.mgrid[:rows, :cols]
    disp = (40.0 + 0.4 * r - 0.1 * c + rng.normal(0.0, 0.5, (rows, cols))).astype(np.float32)
    disp[rng.random((rows, cols)) < 0.3] = -1.0
    plane, rms, slope = local_planes(disp, -0.5)
    h = PLAIN_FIT_HALF
    cells = [(0, 0), (5, 40), (31, 3), (32, 33), (64, 69), (89, 20)] + [tuple(x) for x in rng.integers(0, 70, (20, 2))]
    for i, j in cells:
        if disp[i, j] <= -0.5:
            assert plane[i, j] == disp[i, j] and np.isinf(rms[i, j]) and slope[i, j] == 0
            continue
        ys, xs = np.mgrid[max(i - h, 0):min(i + h + 1, rows), max(j - h, 0):min(j + h + 1, cols)]
        on = disp[ys, xs] > -0.5
        A = np.c_[xs[on] - j, ys[on] - i, np.ones(on.sum())]
        z = disp[ys, xs][on].astype(float)
        sol = np.linalg.lstsq(A, z, rcond=None)[0]
        assert plane[i, j] == pytest.approx(sol[2], abs=1e-4)
        assert rms[i, j] == pytest.approx(np.sqrt(np.mean((A @ sol - z) ** 2)), abs=1e-4)
        assert slope[i, j] == pytest.approx(max(abs(sol[0]), abs(sol[1])), abs=1e-4)


def test_the_median_about_the_plane_keeps_a_surface_sloping_towards_a_hole():
    # a surface sloping 0.6 columns a line (as a floor across the lines), cut by a hole below
    # row 30: the windows along the hole's rim hold only the rows above it
    rows, cols = 60, 80
    rng = np.random.default_rng(4)
    r, c = np.mgrid[:rows, :cols]
    truth = (20.0 + 0.6 * r + 0.05 * c).astype(np.float32)
    disp = truth + rng.uniform(-0.1, 0.1, (rows, cols)).astype(np.float32)
    disp[30:, 20:60] = -1.0
    rim = (slice(26, 30), slice(24, 56))
    plain, slanted = disp.copy(), disp.copy()
    surface_median(plain, -0.5, slanted=False)
    surface_median(slanted, -0.5)
    assert np.abs(plain - truth)[rim].max() > 0.5  # pulled up the ramp, away from the hole
    assert np.abs(slanted - truth)[rim].max() < 0.15
    assert (slanted[30:, 20:60] == -1.0).all()  # the hole stays a hole
    # a step of three columns between two flat surfaces: its windows lie on no one plane
    # (PLANE_RMS), so the cells by the step take the plain median and the step stays sharp
    step = np.where(c < 40, 10.0, 13.0).astype(np.float32) + rng.uniform(-0.1, 0.1, (rows, cols)).astype(np.float32)
    a, b = step.copy(), step.copy()
    surface_median(a, -0.5, slanted=False)
    surface_median(b, -0.5)
    near = np.abs(c - 39.5) < 2  # (the windows of cells farther out hold the plain surface alone)
    assert np.array_equal(a[near], b[near])
    assert (np.abs(b - np.where(c < 40, 10.0, 13.0)) < 0.15).all()


def test_the_plane_fit_restores_a_plain_slanted_surface_and_keeps_texture_and_depth_edges():
    from sefm_recon.matching.surfaces import PLAIN_LEVELS, fit_plain_surfaces, plain_windows

    rows, cols = 40, 90
    c = np.arange(cols, dtype=np.float64)
    truth = np.where(c < 60, 10.0 + 0.3 * c, 40.0)  # a slanted plane, then a step to a far wall
    truth = np.broadcast_to(truth, (rows, cols)).astype(np.float32)
    # SGM's staircase on a plain slope: whole columns, off by up to half a column
    disp = np.round(truth).astype(np.float32)
    disp[10:14, 20:24] = -1.0  # a hole stays a hole
    # line image 1: plain (one grey level of noise) left of column 30, textured beyond
    rng = np.random.default_rng(5)
    L1 = np.full((rows, cols, 3), 120.0) + rng.normal(0.0, 1.0, (rows, cols, 1))
    L1[:, 30:] += rng.uniform(-40.0, 40.0, (rows, cols - 30, 1))
    plain = plain_windows(np.clip(L1, 0, 255).astype(np.uint8))
    assert plain[:, 3:27].all() and not plain[:, 33:].any()
    assert PLAIN_LEVELS > 1.0  # the plain side's noise is below the level

    out = disp.copy()
    moved = fit_plain_surfaces(out, plain, -0.5)
    assert moved > 0
    left = (disp > -0.5) & (c < 28)[None, :]
    assert np.abs(disp - truth)[left].max() > 0.4  # the staircase
    # the plane through the steps: under 0.15 of a column (most off where the window is cut at the borders)
    assert np.abs(out - truth)[left].max() < 0.15 and np.abs(out - truth)[left].mean() < 0.05
    assert (out[10:14, 20:24] == -1.0).all()  # holes stay holes
    assert (out[:, 30:] == disp[:, 30:]).all()  # textured windows keep their own estimate
    # a plain window across the depth edge fits its own surface only (the wall is more than
    # MEDIAN_SAME_SURFACE columns away): nothing of the wall reaches the slope, and back
    edge = np.zeros((rows, cols), bool)
    edge[:, 50:70] = True
    out2 = disp.copy()
    fit_plain_surfaces(out2, edge, -0.5)
    assert (out2[:, 60:70] == 40.0).all()
    slope = np.abs(out2 - truth)[:, 50:60]  # one-sided windows next to the edge: off by a step at most
    assert slope.max() <= 0.35 and slope.mean() < np.abs(disp - truth)[:, 50:60].mean()


def test_the_plane_fit_equals_least_squares_cell_by_cell():
    # the running sums (windows on one surface) and the direct sums (windows across a depth
    # edge) give each cell the least-squares plane of its window's cells on its surface
    from sefm_recon.matching.surfaces import MEDIAN_SAME_SURFACE, PLAIN_FIT_HALF, PLAIN_FIT_SUPPORT, fit_plain_surfaces

    rng = np.random.default_rng(11)
    rows, cols = 30, 40
    r, c = np.mgrid[0:rows, 0:cols].astype(np.float64)
    disp = np.where(c + 0.3 * r < 22, 20.0 + 0.2 * c - 0.1 * r, 8.0 + 0.05 * c)  # two planes, a slanted edge
    disp = (disp + rng.normal(0.0, 0.4, disp.shape)).astype(np.float32)
    disp[rng.random(disp.shape) < 0.15] = -1.0  # scattered holes
    disp[5:9, 30:36] = -1.0  # and a block of them
    plain = rng.random(disp.shape) < 0.8
    out = disp.copy()
    fit_plain_surfaces(out, plain, -0.5)

    side = 2 * PLAIN_FIT_HALF + 1
    need = max(3, int(np.ceil(PLAIN_FIT_SUPPORT * side * side)))
    expected = disp.copy()
    for i in range(rows):
        for j in range(cols):
            d0 = disp[i, j]
            if d0 <= -0.5 or not plain[i, j]:
                continue
            win = (slice(max(i - PLAIN_FIT_HALF, 0), i + PLAIN_FIT_HALF + 1),
                   slice(max(j - PLAIN_FIT_HALF, 0), j + PLAIN_FIT_HALF + 1))
            d, rr, cc = disp[win].astype(np.float64), r[win], c[win]
            on = (d > -0.5) & (np.abs(d - d0) <= MEDIAN_SAME_SURFACE)
            if on.sum() < need:
                continue
            A = np.column_stack([np.ones(on.sum()), cc[on] - j, rr[on] - i])
            expected[i, j] = np.linalg.lstsq(A, d[on], rcond=None)[0][0]
    assert (out != disp).sum() > 300  # most plain cells moved
    np.testing.assert_allclose(out, expected, atol=1e-4)
