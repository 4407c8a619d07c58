"""Plain surfaces filled from their own matches (matching/planes.py), on known answers."""

import cv2
import numpy as np

from sefm_recon.geometry.triangulate import triangulate
from sefm_recon.geometry.two_view import TwoView
from sefm_recon.matching.planes import fill_planes, plain_regions
from sefm_recon.matching.surfaces import plain_windows

W, H, F = 240, 180, 300.0
DISP = 12.0  # a frontal plane at depth F / DISP (unit baseline): x2 = x1 - DISP


def _scene(seed=0, plain=np.s_[20:160, 40:220]):
    """A lateral pair and image 1: a ``plain`` grey rectangle framed by texture (its own region)."""
    K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])
    tv = TwoView(K, K, np.eye(3), np.array([-1.0, 0, 0]))
    rng = np.random.default_rng(seed)
    gray = rng.integers(0, 256, (H, W)).astype(np.uint8)
    gray[plain] = 128
    return tv, gray


def _matches(tv, pixels, disp=DISP):
    """Matches of pixel (x, y) index pairs on a frontal plane of parallax ``disp``, with their points."""
    uv1 = pixels[:, ::-1] + 0.5
    uv2 = uv1 - [disp, 0.0]
    X, ok, _ = triangulate(tv.K1, tv.K2, tv.R, tv.t, uv1, uv2)
    assert ok.all()
    return uv1, uv2, X


def _plain_pixels():
    yy, xx = np.mgrid[24:156, 44:216]  # inside the square, clear of the region's edge
    return np.column_stack([yy.ravel(), xx.ravel()])


def test_a_plain_square_framed_by_texture_is_one_region():
    _, gray = _scene()
    labels, stats = plain_regions(gray)
    inner = labels[24:156, 44:216]
    assert len(np.unique(inner)) == 1 and inner[0, 0] > 0
    left, top, width, height, area = stats[inner[0, 0]]
    assert area >= (156 - 24) * (216 - 44)
    assert 40 <= left <= 44 and 20 <= top <= 24 and left + width <= 220 and top + height <= 160


def test_the_holes_of_a_matched_plane_take_its_partners_on_their_epipolar_lines():
    tv, gray = _scene()
    rng = np.random.default_rng(1)
    px = _plain_pixels()
    hole = rng.random(len(px)) < 0.3
    uv1, uv2, X = _matches(tv, px[~hole])
    fill = fill_planes(gray, (W, H), tv, uv1, uv2, X)
    assert fill.regions == 1
    holes = {tuple(p) for p in (px[hole][:, ::-1] + 0.5)}
    got = {tuple(p) for p in fill.uv1}
    assert len(holes & got) >= 0.95 * len(holes)  # nearly every hole (the edge rows stay out)
    assert not ({tuple(p) for p in uv1} & got)  # a matched pixel is never touched
    assert np.abs(fill.uv2 - (fill.uv1 - [DISP, 0.0])).max() < 0.01  # the plane's partner
    assert np.allclose(fill.xyz[:, 2], F / DISP, rtol=1e-3)


def test_a_surface_beyond_the_matches_is_not_filled():
    # the square's left part matched, its right part not at all: that part may be
    # another surface, and only the strip next to the matches counts as holes
    tv, gray = _scene()
    px = _plain_pixels()
    left = px[:, 1] < 150  # 55 % of the region
    uv1, uv2, X = _matches(tv, px[left])
    fill = fill_planes(gray, (W, H), tv, uv1, uv2, X)
    assert len(fill.uv1) > 0  # the region's margins next to the matches
    assert fill.uv1[:, 0].max() < 150 + 8  # within the hole window's reach of the matches


def test_matches_split_over_two_depths_or_too_few_fill_nothing():
    tv, gray = _scene()
    rng = np.random.default_rng(2)
    px = _plain_pixels()
    px = px[rng.random(len(px)) < 0.7]
    half = rng.random(len(px)) < 0.5
    a, b = _matches(tv, px[half]), _matches(tv, px[~half], disp=DISP + 5)
    split = [np.concatenate([x, y]) for x, y in zip(a, b)]
    assert len(fill_planes(gray, (W, H), tv, *split).uv1) == 0
    # a patch matched whole over a sixth of the region: its margin holds the plane's matches
    # nearby (as a wall's holes do), but the region is too little matched for the plane to be its own
    px = _plain_pixels()
    patch = px[px[:, 1] < 44 + 30]
    assert 0.1 < len(patch) / len(px) < 0.2
    assert len(fill_planes(gray, (W, H), tv, *_matches(tv, patch)).uv1) == 0
    wider = px[px[:, 1] < 44 + 45]  # over a quarter: the strip beside it is filled
    assert len(fill_planes(gray, (W, H), tv, *_matches(tv, wider)).uv1) > 0


def test_a_plain_wall_matched_in_a_quarter_of_its_pixels_is_filled_between_them():
    # SGM leaves a plain wall's matches scattered (Midd1's back wall: 24-37 % matched, and
    # the share swings with the pose); where they lie on one plane, the holes between take
    # it, also where the matches are sparser (here a third on the left, 15 % on the right)
    tv, gray = _scene()
    rng = np.random.default_rng(4)
    px = _plain_pixels()
    some = rng.random(len(px)) < np.where(px[:, 1] < 130, 0.33, 0.15)
    fill = fill_planes(gray, (W, H), tv, *_matches(tv, px[some]))
    holes = {tuple(p) for p in (px[~some][:, ::-1] + 0.5)}
    got = {tuple(p) for p in fill.uv1}
    assert len(holes & got) >= 0.9 * len(holes)
    assert np.abs(fill.uv2 - (fill.uv1 - [DISP, 0.0])).max() < 0.01


def test_a_mostly_unmatched_region_whose_matches_lie_on_no_one_plane_drops_them():
    """A third of the plain square matched in patches (8 px squares) at three depths, each
    drawn at random (a third of them on any one plane): the matcher found no surface there,
    and every one of its matches is to drop. The same pixels on one plane (a plain wall found
    in part) and 70 % of the square over two depths (mostly matched) keep theirs, as the
    patches do with ``drop=False``."""
    tv, gray = _scene()
    rng = np.random.default_rng(3)
    px = _plain_pixels()
    some = px[rng.random(len(px)) < 0.3]
    depth = rng.integers(0, 3, (H // 8 + 1, W // 8 + 1))[some[:, 0] // 8, some[:, 1] // 8]
    patches = [np.concatenate(a) for a in zip(*(_matches(tv, some[depth == b], disp=DISP + 4 * b) for b in range(3)))]
    out = fill_planes(gray, (W, H), tv, *patches)
    assert len(out.dropped) == len(some) and len(out.uv1) == 0
    np.testing.assert_array_equal(np.sort(out.dropped), np.arange(len(some)))
    assert len(fill_planes(gray, (W, H), tv, *_matches(tv, some)).dropped) == 0
    assert len(fill_planes(gray, (W, H), tv, *patches, drop=False).dropped) == 0
    most = px[rng.random(len(px)) < 0.7]
    half = rng.random(len(most)) < 0.5
    split = [np.concatenate([x, y]) for x, y in zip(_matches(tv, most[half]), _matches(tv, most[~half], disp=DISP + 5))]
    assert len(fill_planes(gray, (W, H), tv, *split).dropped) == 0


def test_a_region_is_judged_with_the_matches_the_repeat_check_dropped():
    """A tenth of the plain square matched on one plane (the matches left beside an object)
    and a fifth more dropped by the repeat check, in 8 px patches at three other depths: judged
    with those, the region holds no surface the matcher found, and its matches go. Without
    them, or with them on the region's plane, or where the region is mostly matched with
    them, its matches stay."""
    tv, gray = _scene()
    rng = np.random.default_rng(7)
    px = _plain_pixels()
    draw = rng.random(len(px))
    kept, rest = px[draw < 0.1], px[(draw >= 0.1) & (draw < 0.3)]
    depth = rng.integers(1, 4, (H // 8 + 1, W // 8 + 1))[rest[:, 0] // 8, rest[:, 1] // 8]
    scattered = [np.concatenate(a) for a in zip(*(_matches(tv, rest[depth == b], disp=DISP + 4 * b)
                                                  for b in range(1, 4)))][:2]
    own = _matches(tv, kept)
    out = fill_planes(gray, (W, H), tv, *own, repeats=tuple(scattered))
    np.testing.assert_array_equal(np.sort(out.dropped), np.arange(len(kept)))
    assert len(fill_planes(gray, (W, H), tv, *own).dropped) == 0
    assert len(fill_planes(gray, (W, H), tv, *own, repeats=_matches(tv, rest)[:2]).dropped) == 0
    assert len(fill_planes(gray, (W, H), tv, *own, repeats=tuple(scattered), drop=False).dropped) == 0
    more = px[(draw >= 0.1) & (draw < 0.6)]
    depth = rng.integers(1, 4, (H // 8 + 1, W // 8 + 1))[more[:, 0] // 8, more[:, 1] // 8]
    many = [np.concatenate(a) for a in zip(*(_matches(tv, more[depth == b], disp=DISP + 4 * b)
                                             for b in range(1, 4)))][:2]
    assert len(fill_planes(gray, (W, H), tv, *own, repeats=tuple(many)).dropped) == 0


def test_a_mostly_unmatched_regions_matches_off_its_plane_go_unless_they_are_a_second_surface():
    """A third of the plain square matched: 80 % on one plane, the rest in 8 px patches at
    three other depths drawn at random (a third of them on any one plane): those are dropped,
    the plane's stay, and the patches' pixels are filled from the plane. The same rest on one
    second plane (a second surface in the region) stays, as it does with ``drop=False``; on a
    plane 1.5 px off the first (SGM's wave about the surface, not a second one) it goes. With
    the patches 45 % of the matches, they go too, but the plane fills nothing: its support is
    judged on every match of the region (55 %, under the fill's 60 %)."""
    tv, gray = _scene()
    rng = np.random.default_rng(5)
    px = _plain_pixels()
    some = px[rng.random(len(px)) < 0.3]
    cell = rng.random((H // 8 + 1, W // 8 + 1))
    off = cell[some[:, 0] // 8, some[:, 1] // 8] < 0.2
    depth = rng.integers(1, 4, cell.shape)[some[:, 0] // 8, some[:, 1] // 8]
    parts = [_matches(tv, some[~off])] + [_matches(tv, some[off & (depth == b)], disp=DISP + 4 * b) for b in (1, 2, 3)]
    patches = [np.concatenate(a) for a in zip(*parts)]
    n_on = int(np.count_nonzero(~off))
    assert 0.1 < np.mean(off) < 0.3
    out = fill_planes(gray, (W, H), tv, *patches)
    np.testing.assert_array_equal(np.sort(out.dropped), np.arange(n_on, len(some)))
    gone = {tuple(p) for p in patches[0][n_on:]}  # their pixels are holes of the plane, filled
    assert len(gone & {tuple(p) for p in out.uv1}) >= 0.9 * len(gone)
    assert len(fill_planes(gray, (W, H), tv, *patches, drop=False).dropped) == 0
    second = [np.concatenate(a) for a in zip(_matches(tv, some[~off]), _matches(tv, some[off], disp=DISP + 4))]
    assert len(fill_planes(gray, (W, H), tv, *second).dropped) == 0
    wave = [np.concatenate(a) for a in zip(_matches(tv, some[~off]), _matches(tv, some[off], disp=DISP + 1.5))]
    out = fill_planes(gray, (W, H), tv, *wave)
    np.testing.assert_array_equal(np.sort(out.dropped), np.arange(n_on, len(some)))
    off = cell[some[:, 0] // 8, some[:, 1] // 8] < 0.45
    parts = [_matches(tv, some[~off])] + [_matches(tv, some[off & (depth == b)], disp=DISP + 4 * b) for b in (1, 2, 3)]
    assert 0.4 < np.mean(off) < 0.5
    out = fill_planes(gray, (W, H), tv, *[np.concatenate(a) for a in zip(*parts)])
    assert len(out.dropped) == np.count_nonzero(off) and len(out.uv1) == 0


def test_a_hole_whose_partner_a_nearer_surface_covers_in_view_2_stays_empty():
    tv, gray = _scene()
    px = _plain_pixels()
    hole = (px[:, 0] >= 80) & (px[:, 0] < 84) & (px[:, 1] >= 100) & (px[:, 1] < 104)
    uv1, uv2, X = _matches(tv, px[~hole])
    in_hole = lambda uv: (uv[:, 0] > 100) & (uv[:, 0] < 104) & (uv[:, 1] > 80) & (uv[:, 1] < 84)
    assert in_hole(fill_planes(gray, (W, H), tv, uv1, uv2, X).uv1).sum() == 16
    # a nearer surface (20 px more parallax) lands in image 2 where the hole's partners would
    near = np.array([[y, x + 20] for y in range(80, 84) for x in range(100, 104)])
    n1, n2, nX = _matches(tv, near, disp=DISP + 20)
    fill = fill_planes(gray, (W, H), tv, np.concatenate([uv1, n1]), np.concatenate([uv2, n2]),
                       np.concatenate([X, nX]))
    assert in_hole(fill.uv1).sum() == 0


def _slanted(tv, pixels, wave):
    """Matches on a slanted plane (parallax DISP + 0.04 per column from the centre) whose
    estimates are off by ``wave`` (N,) columns, as SGM's steps leave a plain slanted surface,
    and the true partners."""
    uv1 = pixels[:, ::-1] + 0.5
    true2 = uv1 - np.column_stack([DISP + 0.04 * (uv1[:, 0] - W / 2), np.zeros(len(uv1))])
    uv2 = true2 - np.column_stack([wave, np.zeros(len(uv1))])
    X, ok, _ = triangulate(tv.K1, tv.K2, tv.R, tv.t, uv1, uv2)
    assert ok.all()
    return uv1, uv2, X, true2


def test_a_plain_slanted_planes_steps_move_onto_the_plane_where_the_window_has_no_signal():
    tv, gray = _scene()
    rng = np.random.default_rng(3)
    gray[100:130, 150:190] = np.clip(128 + rng.normal(0, 3, (30, 40)), 0, 255)  # faint grain: signal
    px = _plain_pixels()
    x = px[:, 1] + 0.5
    true_d = DISP + 0.04 * (x - W / 2)
    # steps, and runs 1.2 columns off to either side (SGM's wave about the plane)
    run = lambda a, b: (x >= a) & (x < b)
    wave = np.round(true_d) - true_d + 1.2 * run(110, 150) - 1.2 * (run(70, 90) | run(170, 190))
    uv1, uv2, X, true2 = _slanted(tv, px, wave)
    labels, _ = plain_regions(gray)
    assert len(np.unique(labels[24:156, 44:216])) == 1  # the grain is no edge: one region
    fill = fill_planes(gray, (W, H), tv, uv1, uv2, X)
    inside = lambda x0, x1, y0, y1: (uv1[:, 0] > x0) & (uv1[:, 0] < x1) & (uv1[:, 1] > y0) & (uv1[:, 1] < y1)
    moved = np.zeros(len(uv1), bool)
    moved[fill.moved] = True
    assert not moved[inside(152, 188, 102, 128)].any()  # SGM's own estimate where the window has signal
    assert moved[~inside(146, 194, 96, 134)].mean() > 0.95  # the rest, steps and runs alike
    assert np.abs(fill.moved_uv2 - true2[fill.moved]).max() < 0.1  # onto the plane
    Xm, _, _ = triangulate(tv.K1, tv.K2, tv.R, tv.t, uv1[fill.moved], fill.moved_uv2)
    assert np.allclose(fill.moved_xyz, Xm, rtol=1e-6)  # each point on both its rays
    Xt, _, _ = triangulate(tv.K1, tv.K2, tv.R, tv.t, uv1[fill.moved], true2[fill.moved])
    assert np.allclose(fill.moved_xyz, Xt, rtol=0.01)
    assert np.abs(wave[fill.moved]).max() > 1.5  # it did move matches more than 1 px off
    # switched off: nothing moves, and the fill alone does not depend on it
    off = fill_planes(gray, (W, H), tv, uv1, uv2, X, snap=False)
    assert len(off.moved) == 0
    only = fill_planes(gray, (W, H), tv, uv1, uv2, X, fill=False)
    assert len(only.uv1) == 0 and np.array_equal(only.moved, fill.moved)


def test_a_region_not_one_plane_all_through_keeps_its_matches():
    # 12 % of the region lies 3 px off the plane (a fold, another surface): the plane still
    # fills its holes, but moves none of its matches
    tv, gray = _scene()
    rng = np.random.default_rng(4)
    px = _plain_pixels()
    px = px[rng.random(len(px)) < 0.8]
    x = px[:, 1] + 0.5
    true_d = DISP + 0.04 * (x - W / 2)
    wave = np.round(true_d) - true_d + np.where(x >= 195, 3.0, 0.0)
    assert 0.08 < np.mean(x >= 195) < 0.15
    uv1, uv2, X, _ = _slanted(tv, px, wave)
    fill = fill_planes(gray, (W, H), tv, uv1, uv2, X)
    assert len(fill.uv1) > 0 and len(fill.moved) == 0
    # nearly all of it on the plane: the steps move
    wave = np.round(true_d) - true_d + np.where(x >= 212, 3.0, 0.0)
    assert np.mean(x >= 212) < 0.05
    uv1, uv2, X, _ = _slanted(tv, px, wave)
    fill = fill_planes(gray, (W, H), tv, uv1, uv2, X)
    assert len(fill.moved) > 0.9 * len(uv1) and (uv1[fill.moved, 0] < 212).all()


def _small_square_scene(seed=5):
    """Image 1 textured all over but for a plain 16 px square (its region, a pixel short of its
    blurred edges: about 100 px, a small one), every pixel of image 1 as (y, x) index pairs,
    and which of them lie on the region (its label, once)."""
    tv, gray = _scene(seed, np.s_[80:96, 110:126])
    labels, stats = plain_regions(gray)
    k = labels[88, 118]
    assert k > 0 and 100 <= stats[k, 4] < 0.01 * W * H  # one small region
    yy, xx = np.mgrid[0:H, 0:W]
    return tv, gray, np.column_stack([yy.ravel(), xx.ravel()]), labels.ravel() == k


def test_a_small_plain_region_takes_the_plane_of_its_rim():
    tv, gray, px, square = _small_square_scene()
    rng = np.random.default_rng(6)
    # the region's matches: half of them, scattered 0.5-1.5 columns either side of the plane
    # (set by SGM's smoothness penalties, no signal), the other half unmatched
    kept = ~square | (rng.random(len(px)) < 0.5)
    wave = np.where(square, rng.choice([-1.0, 1.0], len(px)) * rng.uniform(0.5, 1.5, len(px)), 0.0)[kept]
    uv1, uv2, X, true2 = _slanted(tv, px[kept], wave)
    fill = fill_planes(gray, (W, H), tv, uv1, uv2, X)
    holes = {tuple(p) for p in px[square & ~kept][:, ::-1] + 0.5}
    got = {tuple(p) for p in fill.uv1}
    assert holes and holes <= got  # every unmatched pixel of the region
    truth = fill.uv1 - np.column_stack([DISP + 0.04 * (fill.uv1[:, 0] - W / 2), np.zeros(len(fill.uv1))])
    assert np.abs(fill.uv2 - truth).max() < 0.05  # on the rim's plane
    moved = np.zeros(len(uv1), bool)
    moved[fill.moved] = True
    on_region = square.reshape(H, W)[uv1[:, 1].astype(int), uv1[:, 0].astype(int)]
    plain = plain_windows(gray)[uv1[:, 1].astype(int), uv1[:, 0].astype(int)]
    assert moved[on_region].all() and not moved[~on_region & ~plain].any()  # and of the rim, its plain band alone
    assert np.abs(fill.moved_uv2 - true2[fill.moved]).max() < 0.05
    # switched off: the small region stays as it was
    off = fill_planes(gray, (W, H), tv, uv1, uv2, X, rims=False)
    assert len(off.uv1) == 0 and len(off.moved) == 0


def test_a_small_regions_plain_band_outside_every_region_moves_onto_its_rims_plane():
    """A plain square (its region) inside a plain frame 8 levels brighter, texture beyond: the
    weak edge between them and the frame, too narrow for a region of its own, are plain windows
    outside every region. Their matches, 1.5 columns either side of the plane (SGM's wave), move
    onto the plane of the square's rim where they lie on that rim; the frame beyond the rim and
    the texture keep theirs."""
    tv, gray = _scene(5, np.s_[74:102, 104:132])
    gray[74:102, 104:132] = 136
    gray[80:96, 110:126] = 128
    labels, _ = plain_regions(gray)
    k = labels[88, 118]
    assert k > 0 and labels[75, 118] == 0  # the square a region, the frame none
    band = plain_windows(gray) & (labels == 0)
    rim = cv2.dilate((labels == k).astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool) & (labels != k)
    yy, xx = np.mgrid[0:H, 0:W]
    px = np.column_stack([yy.ravel(), xx.ravel()])
    side = np.where((px[:, 0] + px[:, 1]) % 2 == 0, 1.5, -1.5)
    uv1, uv2, X, true2 = _slanted(tv, px, np.where(band.ravel(), side, 0.0))
    fill = fill_planes(gray, (W, H), tv, uv1, uv2, X)
    moved = np.zeros(len(uv1), bool)
    moved[fill.moved] = True
    assert moved[(band & rim).ravel()].all() and not moved[(band & ~rim).ravel()].any()
    assert not moved[~plain_windows(gray).ravel()].any()
    assert np.abs(fill.moved_uv2 - true2[fill.moved]).max() < 0.01  # on the plane of the rim's wave


def test_a_rim_whose_matches_scatter_up_to_two_px_about_its_plane_still_gives_it():
    # a floor seen while moving forward: the rim's own matches lie 1.2-1.8 columns either side
    # of the plane (none within 1 px), the region's matches on 40 % of it, scattered as SGM leaves
    # them (its holes then more than the fill's least share, MIN_FILL_SHARE)
    tv, gray, px, square = _small_square_scene()
    rng = np.random.default_rng(8)
    kept = ~square | (rng.random(len(px)) < 0.4)
    side = rng.choice([-1.0, 1.0], len(px))
    wave = np.where(square, side * rng.uniform(0.5, 1.5, len(px)), side * rng.uniform(1.2, 1.8, len(px)))[kept]
    uv1, uv2, X, true2 = _slanted(tv, px[kept], wave)
    fill = fill_planes(gray, (W, H), tv, uv1, uv2, X)
    holes = {tuple(p) for p in px[square & ~kept][:, ::-1] + 0.5}
    filled = {tuple(p) for p in fill.uv1}
    # (beside the rim, a rim match 1.2-1.8 columns nearer than its plane may hide a hole in view 2)
    assert filled <= holes and len(filled) > 0.5 * len(holes)
    truth = fill.uv1 - np.column_stack([DISP + 0.04 * (fill.uv1[:, 0] - W / 2), np.zeros(len(fill.uv1))])
    assert np.abs(fill.uv2 - truth).max() < 0.3  # the plane of the rim's scatter, not of its extremes
    assert len(fill.moved) > 0 and np.abs(fill.moved_uv2 - true2[fill.moved]).max() < 0.3
    # the rim's matches 2.5-3 columns either side of it (beyond SGM's wave: no one plane): nothing filled
    wave = np.where(square, 0.0, side * rng.uniform(2.5, 3.0, len(px)))[kept]
    uv1, uv2, X, _ = _slanted(tv, px[kept], wave)
    assert len(fill_planes(gray, (W, H), tv, uv1, uv2, X).uv1) == 0


def test_a_small_region_holding_another_surface_open_on_one_side_or_with_a_rim_on_two_surfaces_stays():
    tv, gray, px, square = _small_square_scene()
    # half of the region matched on one plane of its own within 0.1 px, a nearer surface seen
    # through it 4 columns off the rim's plane (beyond RIM_SNAP_PX): neither moved nor filled
    rng = np.random.default_rng(7)
    kept = ~square | (rng.random(len(px)) < 0.5)
    wave = np.where(square, 4.0 + rng.uniform(-0.1, 0.1, len(px)), 0.0)[kept]
    uv1, uv2, X, _ = _slanted(tv, px[kept], wave)
    fill = fill_planes(gray, (W, H), tv, uv1, uv2, X)
    assert len(fill.moved) == 0 and len(fill.uv1) == 0
    # the same within 0.1 px of the rim's plane: moved onto it, and its holes filled
    wave = np.where(square, rng.uniform(-0.1, 0.1, len(px)), 0.0)[kept]
    uv1, uv2, X, true2 = _slanted(tv, px[kept], wave)
    fill = fill_planes(gray, (W, H), tv, uv1, uv2, X)
    on_region = square.reshape(H, W)[uv1[:, 1].astype(int), uv1[:, 0].astype(int)]
    plain = plain_windows(gray)[uv1[:, 1].astype(int), uv1[:, 0].astype(int)]
    assert len(fill.uv1) > 0 and set(np.flatnonzero(on_region)) <= set(fill.moved)
    assert set(fill.moved) <= set(np.flatnonzero(on_region | plain))
    assert np.abs(fill.moved_uv2 - true2[fill.moved]).max() < 0.05
    # the region's right part unmatched, and its rim there too (a band along an occlusion):
    # only the holes with the plane's matches on all four sides are filled
    open_right = (px[:, 1] >= 118) & (px[:, 1] < 127) & (px[:, 0] >= 83) & (px[:, 0] < 93)
    assert 0.3 < (square & open_right).sum() / square.sum() < 0.7
    kept = ~open_right
    uv1, uv2, X, _ = _slanted(tv, px[kept], np.zeros(int(kept.sum())))
    fill = fill_planes(gray, (W, H), tv, uv1, uv2, X)
    assert len(fill.uv1) == 0
    # the rim on two surfaces (its top side, a third of it, 4 columns nearer): no plane,
    # nothing filled, though the region's own matches lie on the plane of the rest
    kept = ~square | (rng.random(len(px)) < 0.5)
    wave = np.where(~square & (px[:, 0] < 83), 4.0, 0.0)[kept]
    uv1, uv2, X, _ = _slanted(tv, px[kept], wave)
    fill = fill_planes(gray, (W, H), tv, uv1, uv2, X)
    assert len(fill.uv1) == 0


def test_a_mostly_unmatched_region_on_the_ties_at_the_searchs_first_parallax_drops_them():
    """A third of the plain square matched on one plane: a plain wall found in part, filled
    between its matches. Where that plane is the first parallax SGM searched (within
    TIE_COLUMNS of it), it is where OpenCV breaks the ties of a cost without a minimum: the
    matches go and nothing is filled. A plane 5 columns beyond the first parallax (Midd1's
    wall past the SIFT points) stays."""
    from sefm_recon.matching.lines import line_grid, match_parallax
    from sefm_recon.matching.planes import TIE_COLUMNS, SearchStart

    tv, gray = _scene()
    rng = np.random.default_rng(3)
    px = _plain_pixels()
    some = px[rng.random(len(px)) < 0.3]
    uv1, uv2, X = _matches(tv, some)
    grid = line_grid(tv, (W, H), (W, H))
    d = match_parallax(grid, tv, uv1, uv2)
    assert np.ptp(d) < 1.0 and 10 < np.median(d) < 14  # a frontal plane: about a column a px
    at_ties = SearchStart(grid, float(d.max()) - TIE_COLUMNS + 0.5)
    out = fill_planes(gray, (W, H), tv, uv1, uv2, X, start=at_ties)
    assert len(out.uv1) == 0 and len(out.dropped) == len(uv1)
    kept = fill_planes(gray, (W, H), tv, uv1, uv2, X, start=at_ties, drop=False)
    assert len(kept.uv1) == 0 and len(kept.dropped) == 0  # neither dropped nor filled
    beyond = fill_planes(gray, (W, H), tv, uv1, uv2, X, start=SearchStart(grid, float(d.min()) - 5.0))
    assert len(beyond.dropped) == 0 and len(beyond.uv1) > 0.5 * (len(px) - len(some))
    most = px[rng.random(len(px)) < 0.7]  # mostly matched: SGM found the surface there
    assert len(fill_planes(gray, (W, H), tv, *_matches(tv, most), start=at_ties).dropped) == 0
