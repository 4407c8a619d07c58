"""The checks on SGM's disparities over the line images (:mod:`sefm_recon.matching.checks`)."""

import numpy as np



def _one_row_collision(d_far, d_near, colour_far, colour_near, colour2):
    """A row with two valid cells, 12 (parallax ``d_far``) and 16 (``d_near``), and image 2's
    column 2, where both land when the parallaxes are 10 and 14; returns the cells dropped."""
    from sefm_recon.matching.checks import drop_collisions

    bad = -1.0
    disp = np.full((1, 40), bad, np.float32)
    disp[0, 12], disp[0, 16] = d_far, d_near
    L1 = np.full((1, 40), 100, np.uint8)
    L2 = np.full((1, 40), 100, np.uint8)
    L1[0, 12], L1[0, 16], L2[0, 2] = colour_far, colour_near, colour2
    before = disp.copy()
    n = drop_collisions(disp, L1, L2, 0, bad)
    dropped = np.flatnonzero((disp[0] == bad) & (before[0] != bad)).tolist()
    assert n == len(dropped)
    return dropped


def _one_row_occlusion(before: float, strip_colour: int, gap_start: int = 40, holes=(), hole_parallax=30.0,
                       edge: int = 56):
    """A row: a valid cell (parallax ``before``) at ``gap_start - 1``, unmatched cells up to
    column 50, then a run at parallax 30: cells of ``strip_colour`` on 50 .. ``edge - 1``, the
    nearer surface's texture from ``edge`` on; the cells ``holes`` unmatched and the run's cells
    after them at ``hole_parallax``. The gap's colour is 100. Returns the cells dropped."""
    from sefm_recon.matching.checks import drop_occluded_plain
    from sefm_recon.matching.surfaces import plain_windows

    bad = -1.0
    disp = np.full((5, 100), bad, np.float32)
    disp[:, gap_start - 1] = before
    disp[:, 50:80] = 30.0
    if holes:
        disp[:, max(holes) + 1:80] = hole_parallax
        disp[:, list(holes)] = bad
    L1 = np.full((5, 100, 3), 100, np.uint8)
    L1[:, 50:edge] = strip_colour
    L1[:, edge:80] = np.random.default_rng(0).integers(0, 255, (5, 80 - edge, 3))
    span2 = np.tile(np.array([[0, 99]]), (5, 1))
    before_drop = disp.copy()
    n = drop_occluded_plain(disp, L1, plain_windows(L1), span2, 0, bad)
    dropped = np.flatnonzero((disp[2] == bad) & (before_drop[2] != bad)).tolist()
    assert n == 5 * len(dropped)
    return dropped


def _one_row_jump(near_colour: int, edge: int = 60, ramp: bool = False, far_plain: bool = True, unmatched=()):
    """A row: a plain farther surface (colour 100, parallax 10) on columns 0 .. 39, then
    the nearer parallax 20 from column 40 on, on cells of ``near_colour`` up to ``edge - 1``
    and the nearer surface's texture from ``edge`` on (with ``ramp``, instead, grey rising
    by 1.5 levels a column from column 40: plain windows throughout); the cells
    ``unmatched`` unmatched. Returns the cells dropped."""
    from sefm_recon.matching.checks import drop_carried_plain
    from sefm_recon.matching.surfaces import plain_windows

    bad = -1.0
    disp = np.full((5, 100), 10.0, np.float32)
    disp[:, 40:] = 20.0
    disp[:, list(unmatched)] = bad
    L1 = np.full((5, 100, 3), 100, np.uint8)
    if not far_plain:
        L1[:, :40] = np.random.default_rng(1).integers(0, 255, (5, 40, 3))
    L1[:, 40:edge] = near_colour
    L1[:, edge:] = np.random.default_rng(0).integers(0, 255, (5, 100 - edge, 3))
    if ramp:
        L1[:, 40:] = (100 + 1.5 * np.arange(60))[None, :, None].astype(np.uint8)
    before = disp.copy()
    n = drop_carried_plain(disp, L1, plain_windows(L1), bad)
    dropped = np.flatnonzero((disp[2] == bad) & (before[2] != bad)).tolist()
    assert n == 5 * len(dropped)
    return dropped


def test_windows_beyond_image_2_are_dropped():
    from sefm_recon.matching.checks import drop_outside_windows
    from sefm_recon.matching.stereo_sgbm import BLOCK

    half = BLOCK // 2
    span2 = np.array([[10, 40], [5, 4]])  # row 1 holds none of image 2
    x, shift = 50, 5
    # partner column x - (d - shift): 11.4 and 38.6 put a window cell beyond the span
    partners = np.array([10 + half - 0.6, 10 + half - 0.4, 40 - half + 0.4, 40 - half + 0.6, 25.0])
    disp = np.full((2, 60), -1.0, np.float32)
    disp[0, x - 2:x + 3] = np.arange(x - 2, x + 3) + shift - partners
    disp[1, 20] = 12.0
    before = disp.copy()
    assert drop_outside_windows(disp, span2, shift, -1.0) == 3
    assert list(disp[0, x - 2:x + 3] == -1.0) == [True, False, False, True, False]
    assert disp[1, 20] == -1.0
    kept = disp > -1.0
    np.testing.assert_array_equal(disp[kept], before[kept])


def test_the_nearer_surfaces_cell_at_a_depth_edge_is_dropped():
    from sefm_recon.matching.checks import FATTENED_CELLS, drop_fattened_cells

    assert FATTENED_CELLS == 1
    bad = -1.0
    rows = np.array([
        [10, 10, 10, 30, 30, 30, 30, 30],  # a jump between neighbours: 30 starts the nearer surface
        [30, 30, 30, 10, 10, 10, 10, 10],  # the nearer surface ends before the jump
        [10, 10, bad, bad, 30, 30, 30, 30],  # across an occlusion strip narrower than the jump
        [10, 10, 10, 11.5, 13, 14.5, 16, 17.5],  # a slanted surface: steps within 2 columns
        [12, bad, bad, bad, bad, bad, 15, 15],  # a jump of 3 across 5 cells: no occlusion strip, no edge
        [10, 10, 10, 10, 10, 10, 10, 10],
    ], np.float32)
    out = rows.copy()
    assert drop_fattened_cells(out, bad) == 3
    dropped = (out == bad) & (rows != bad)
    assert dropped[0].tolist() == [0, 0, 0, 1, 0, 0, 0, 0]
    assert dropped[1].tolist() == [0, 0, 1, 0, 0, 0, 0, 0]
    assert dropped[2].tolist() == [0, 0, 0, 0, 1, 0, 0, 0]
    assert not dropped[3:].any()


def test_of_two_surfaces_reaching_one_pixel_of_image_2_the_one_of_another_colour_is_dropped():
    # the nearer cell fattened past a depth edge: it has the farther surface's colour in
    # image 1, which image 2 does not show where its parallax sends it
    assert _one_row_collision(10, 14, colour_far=60, colour_near=200, colour2=60) == [16]
    # the farther cell hidden in image 2 by the nearer surface, whose colour is seen there
    assert _one_row_collision(10, 14, colour_far=200, colour_near=60, colour2=60) == [12]
    # within a grey level the images cannot tell them apart: both kept
    assert _one_row_collision(10, 14, colour_far=60, colour_near=61, colour2=60) == []
    # one slanted surface (parallax 2 columns apart at most) may reach a pixel twice
    assert _one_row_collision(10, 12, colour_far=60, colour_near=200, colour2=60) == []
    # a pixel apart in image 2 (parallax 10 and 15): no collision
    assert _one_row_collision(10, 15, colour_far=60, colour_near=200, colour2=60) == []


def test_plain_cells_a_nearer_surface_carries_into_an_unmatched_region_are_dropped():
    # a farther surface (parallax 10) before the gap: the plain strip of the gap's colour
    # is dropped up to the nearer surface's edge, with the two cells whose windows reach
    # the texture (not plain, but of the gap's colour)
    assert _one_row_occlusion(10.0, 100) == [50, 51, 52, 53, 54, 55]
    # ... within the plain test's noise of the gap's colour
    assert _one_row_occlusion(10.0, 104) == [50, 51, 52, 53, 54, 55]
    # a strip narrower than the window, none of its windows plain: its two cells of the
    # gap's colour are dropped, not the texture after them
    assert _one_row_occlusion(10.0, 100, edge=52) == [50, 51]
    assert _one_row_occlusion(10.0, 100, edge=53) == [50, 51, 52]
    # another colour than the gap's: the run's own surface, kept
    assert _one_row_occlusion(10.0, 140) == []
    # the surface before the gap as near (or nearer): no occlusion strip there
    assert _one_row_occlusion(29.0, 100) == []
    assert _one_row_occlusion(40.0, 100) == []
    # the gap, seen with the run's parallax, reaches beyond image 2's left edge where the
    # hidden strip (20 columns of parallax difference) would lie: kept
    assert _one_row_occlusion(10.0, 100, gap_start=25) == []
    # ... but a strip 5 columns wide lies inside image 2, whatever the gap's far end: dropped
    assert _one_row_occlusion(25.0, 100, gap_start=25) == [50, 51, 52, 53, 54, 55]
    # SGM left two cells unmatched where the strip meets the texture: the run goes on
    # across them on its surface, and the strip is dropped up to the texture's windows
    assert _one_row_occlusion(10.0, 100, holes=(54, 55)) == [50, 51, 52, 53]
    # ... but not across three cells, nor to another surface: the strip is a run of its
    # own, with no edge in it
    assert _one_row_occlusion(10.0, 100, holes=(52, 53, 54)) == []
    assert _one_row_occlusion(10.0, 100, holes=(54, 55), hole_parallax=25.0) == []


def test_plain_cells_a_nearer_surface_carries_across_a_depth_jump_are_dropped():
    # the farther wall's colour at the nearer parallax up to the nearer surface's edge:
    # dropped, with the two cells whose windows reach the edge
    assert _one_row_jump(100) == list(range(40, 60))
    assert _one_row_jump(104, edge=45) == [40, 41, 42, 43, 44]
    # the jump on the intensity edge (another colour): the nearer surface's own cells, kept
    assert _one_row_jump(160) == []
    # a slow shading ramp, no intensity edge where the walk ends: kept
    assert _one_row_jump(100, ramp=True) == []
    # a textured farther surface: no plain wall to carry the depth into
    assert _one_row_jump(100, far_plain=False) == []
    # SGM left the wall's cells next to the jump unmatched: the jump across them
    assert _one_row_jump(100, unmatched=range(30, 40)) == list(range(40, 60))


def test_estimates_whose_window_reaches_into_an_area_of_one_value_are_dropped():
    # the fill left of a turned image's edge (columns 0 .. 19) beside texture: a window of
    # 5 reaches into the fill from column 21 leftwards, and column 22's no longer does
    from sefm_recon.matching.checks import drop_flat_windows

    L1 = np.random.default_rng(1).integers(1, 255, (12, 60, 3)).astype(np.uint8)
    L1[:, :20] = 0
    disp = np.full((12, 60), 5.0, np.float32)
    disp[:, 40] = -1.0  # an estimate already dropped stays so, uncounted
    n = drop_flat_windows(disp, L1, -1.0)
    dropped = disp[6] == -1.0
    assert dropped[:22].all() and not dropped[22:40].any() and not dropped[41:].any()
    assert n == 12 * 22


def test_far_end_estimates_of_cells_image_2_sees_only_there_are_dropped():
    from sefm_recon.matching.checks import drop_unseen_far
    from sefm_recon.matching.stereo_sgbm import BLOCK

    shift, end = 10, 20.0  # line image 2 shifted by 10; the far end columns below 20
    rows, width = 4, 60
    disp = np.full((rows, width), 15.0, np.float32)  # every cell at the far end
    disp[:, 40:] = 30.0  # and some within the range
    span2 = np.tile(np.array([15, 200]), (rows, 1))  # image 2's cells from column 15
    # a cell at x sees image 2 up to parallax x + shift - (15 + BLOCK // 2) + 0.5: below
    # the far end's 20 for x <= 26
    n = drop_unseen_far(disp, span2, shift, end, -1.0)
    x = np.arange(width)
    unseen = (x + shift - (15 + BLOCK // 2) + 0.5 < end) & (x < 40)
    assert unseen.sum() == 27 and (disp[:, unseen] == -1.0).all()
    assert (disp[:, ~unseen & (x < 40)] == 15.0).all() and (disp[:, 40:] == 30.0).all()
    assert n == rows * unseen.sum()


def test_runs_matching_image_1s_edge_to_image_2s_beyond_an_occlusions_width_are_dropped():
    from sefm_recon.matching.checks import drop_frame_end_runs
    from sefm_recon.matching.surfaces import MEDIAN_SAME_SURFACE

    shift, width = 10, 120
    # image 1's frame on each row from column 20 to 110, image 2's from 5 to 100
    frames = np.tile(np.array([[20, 110], [5, 100]])[:, None, :], (1, 6, 1))
    disp = np.full((6, width), -1.0, np.float32)
    # a run from 3 cells inside image 1's edge whose first cell matches 3 columns inside
    # image 2's (23 - (25 - shift) = 5 + 3), then a surface 10 columns nearer from x = 50.
    # Rows 0-1: a gap of 20 cells, wider than the 10 that the nearer surface hides in image
    # 2 (dropped); rows 2-3: a gap of 12, within MEDIAN_SAME_SURFACE of it (a background
    # beside a real occlusion: kept)
    disp[:5, 23:30] = 25.0
    disp[:5, 50:100] = 35.0
    disp[2:4, 30:38] = 25.0
    assert 12 - 10 <= MEDIAN_SAME_SURFACE < 20 - 10
    # row 4: the first cell matched 2 columns beyond image 2's edge, not aligned (kept)
    disp[4, 23:30] = 30.0
    # row 5, the row's end mirrored: image 1's last cells 3 inside its edge matched 3 inside
    # image 2's (107 - (20 - shift) = 100 - 3), a gap of 20, a surface 7 columns nearer
    disp[5, 104:108] = 20.0
    disp[5, 40:84] = 27.0
    before = disp.copy()
    n = drop_frame_end_runs(disp, frames, shift, -1.0)
    assert (disp[:2, 23:30] == -1.0).all() and (disp[:2, 50:] == before[:2, 50:]).all()
    assert (disp[2:5] == before[2:5]).all()
    assert (disp[5, 104:108] == -1.0).all() and (disp[5, 40:84] == 27.0).all()
    assert n == 2 * 7 + 4


def test_far_end_surfaces_that_image_2_sees_nowhere_at_every_parallax_are_dropped():
    from sefm_recon.matching.checks import drop_unanchored_far
    from sefm_recon.matching.stereo_sgbm import BLOCK

    shift, end, near = 10, 20.0, 60.0  # far end columns below 20; the range proper up to 60
    rows, width = 40, 120
    span2 = np.tile(np.array([15, 400]), (rows, 1))  # image 2's cells from column 15
    # a cell at x sees image 2 up to parallax x + shift - (15 + BLOCK // 2) + 0.5: at every
    # parallax up to `near` from x = 67 on
    x = np.arange(width)
    assert ((x + shift - (15 + BLOCK // 2) + 0.5 >= near) == (x >= 67)).all()
    disp = np.full((rows, width), -1.0, np.float32)
    disp[:, :30] = 15.0  # a far end patch wholly where image 2 does not see every parallax,
    disp[:, 30:70] = 30.0  # next to a surface 15 columns nearer that reaches x >= 67
    disp[:, 80:110] = 17.0  # a far end patch where image 2 sees every parallax
    before = disp.copy()
    n = drop_unanchored_far(disp, span2, shift, end, near, -1.0)
    assert (disp[:, :30] == -1.0).all() and n == rows * 30
    assert (disp[:, 30:] == before[:, 30:]).all()
    # the same patch going on as a surface whose parallax rises a column every 4 cells,
    # out of the far end columns, to cells image 2 sees at every parallax: it stays whole
    disp = before.copy()
    disp[:, 30:70] = 15.0 + (np.arange(40) // 4)[None, :]
    disp[3:6, 10:20] = 15.5  # (steps within a column join, across rows too)
    kept = disp.copy()
    assert drop_unanchored_far(disp, span2, shift, end, near, -1.0) == 0 and (disp == kept).all()
    # ... but not across a step of more than a column
    disp[:, 50:70] += 1.5
    assert drop_unanchored_far(disp, span2, shift, end, near, -1.0) == rows * 50
    # ... nor through ties (within a column of the first disparity, `shift`): a patch joined to
    # cells image 2 sees at every parallax only through ties goes, with the ties it does not see
    disp = np.full((rows, width), -1.0, np.float32)
    disp[:, :30] = 11.8
    disp[:, 30:70] = 10.9  # ties, within SAME_SURFACE_COLUMNS of the patch and of the cells after
    disp[:, 70:100] = 11.8
    before = disp.copy()
    assert drop_unanchored_far(disp, span2, shift, end, near, -1.0) == rows * 67
    assert (disp[:, :67] == -1.0).all() and (disp[:, 67:] == before[:, 67:]).all()


def test_islands_under_the_speckle_window_are_found_and_a_surface_joined_by_a_slope_is_not():
    """``speckle_islands``: a patch cut off from its surface by unmatched cells and smaller
    than the speckle window is an island, one across a jump of more than the speckle range
    too; a surface whose parallax slopes from cell to cell within the range is one patch
    however far it runs, and a patch of the window's size is none."""
    from sefm_recon.matching.checks import speckle_islands
    from sefm_recon.matching.stereo_sgbm import speckle_window

    bad = -1.0
    rows, width, num_d = 200, 400, 64
    window = speckle_window(rows, width, num_d)  # 1/500 of the 200 x 336 cells estimated
    assert window == 134
    disp = np.full((rows, width), bad, np.float32)
    disp[:, 100:] = 20.0 + 0.5 * np.arange(300)[None, :] / 10  # a slope of 0.05 columns a cell: one surface
    disp[10:20, 110:120] = 60.0  # 100 cells 20+ columns off their surroundings: an island
    disp[50:60, 20:30] = 30.0  # 100 cells cut off by unmatched cells: an island
    disp[100:112, 20:32] = 30.0  # 144 cells cut off: at the window, no island
    disp[150:160, 40:50] = 30.0  # two patches of 100 within the range of each other: one of 200
    disp[150:160, 50:60] = 31.5
    before = disp.copy()
    islands = speckle_islands(disp, num_d, bad)
    assert np.array_equal(disp, before)  # the map is not changed
    expected = np.zeros_like(islands)
    expected[10:20, 110:120] = expected[50:60, 20:30] = True
    assert np.array_equal(islands, expected)
