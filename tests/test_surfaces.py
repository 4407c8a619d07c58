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


def _line_images(truth: np.ndarray, shift: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Grey line images of a weak texture in which cell (r, c) of image 1 is seen at column
    c - (truth[r, c] - shift) of image 2 (image 2 shifted by ``shift`` columns, as SGM takes it)."""
    rows, cols = truth.shape

    def texture(r, x):  # smooth, a few grey levels a cell: a weak texture
        return 120.0 + 20.0 * np.sin(x / 3.1 + 0.7 * r) + 12.0 * np.sin(x / 1.7 - 0.4 * r)

    r, c = np.mgrid[0:rows, 0:cols].astype(np.float64)
    g1 = texture(r, c)
    # image 2's column x shows what image 1 shows at the column whose match lands there
    # (the disparities vary slowly, so each row's inverse comes from interpolation)
    g2 = np.empty_like(g1)
    for i in range(rows):
        g2[i] = texture(i, np.interp(c[i], c[i] - (truth[i] - shift), c[i]))
    return np.round(g1).astype(np.uint8), np.round(g2).astype(np.uint8)


def test_the_wide_plane_fit_takes_streaks_onto_their_plane():
    # SGM's streaks on a plain surface: runs along the lines a few rows tall, 1.5 columns
    # off either way; the wide window's plane matches there as well as the streak's value
    from sefm_recon.matching.surfaces import WIDE_FIT_MOVE, fit_wide_planes

    rng = np.random.default_rng(7)
    rows, cols = 80, 160
    r, c = np.mgrid[0:rows, 0:cols].astype(np.float64)
    truth = (30.0 + 0.3 * r + 0.05 * c).astype(np.float32)  # a floor sloping across the lines
    g1, g2 = _line_images(truth)
    disp = truth.copy()
    for _ in range(40):  # over a fifth of the cells, about a column root mean square
        i, j = rng.integers(0, rows - 3), rng.integers(0, cols - 30)
        disp[i:i + 3, j:j + 30] = truth[i:i + 3, j:j + 30] + rng.choice([-1.5, 1.5])
    disp[40:44, 70:80] = -1.0  # a hole stays a hole
    plain = np.ones((rows, cols), bool)
    plain[:, 140:] = False  # a textured band keeps its estimates
    out = disp.copy()
    moved = fit_wide_planes(out, plain, g1, g2, 5, -0.5)
    inner = (slice(12, rows - 12), slice(14, 126))  # (columns: the texture's windows inside image 2 too)
    off = np.abs(disp - truth)[inner] > 1.0
    assert moved > 0 and off.mean() > 0.2
    assert (np.abs(out - truth)[inner] > 1.0).mean() < 0.15 * off.mean()  # (where streaks crowd, the RMS gate holds)
    assert (out[40:44, 70:80] == -1.0).all()
    assert (out[:, 140:] == disp[:, 140:]).all()
    assert WIDE_FIT_MOVE[1] >= 1.5  # the streaks lie within the moves


def test_the_wide_plane_fit_keeps_a_relief_the_images_carry_and_gross_errors():
    from sefm_recon.matching.surfaces import WIDE_FIT_MOVE, fit_wide_planes

    rows, cols = 60, 120
    r, c = np.mgrid[0:rows, 0:cols].astype(np.float64)
    # a bump of 1.6 columns on a plane: its top lies 1-2 columns off the wide window's plane
    bump = 1.6 * np.exp(-((r - 30) ** 2 + (c - 60) ** 2) / (2 * 4.0**2))
    truth = (30.0 + 0.1 * r + bump).astype(np.float32)
    g1, g2 = _line_images(truth)
    disp = truth.copy()
    disp[10:13, 20:50] += 3.0  # a gross error, beyond the moves: another surface's
    assert WIDE_FIT_MOVE[1] < 3.0
    plain = np.ones((rows, cols), bool)
    out = disp.copy()
    fit_wide_planes(out, plain, g1, g2, 5, -0.5)
    assert (out[25:36, 55:66] == disp[25:36, 55:66]).all()  # the relief matches better than the plane
    assert (out[10:13, 20:50] == disp[10:13, 20:50]).all()
    # without the images' say (image 2 blank: every window matches alike) the bump would move
    flat = np.full_like(g2, 120)
    out2 = disp.copy()
    fit_wide_planes(out2, plain, np.full_like(g1, 120), flat, 5, -0.5)
    assert (out2[25:36, 55:66] != disp[25:36, 55:66]).any()
