"""A plane aligned between the images by their intensities (matching/plane_align.py), on known answers."""

import cv2
import numpy as np

from sefm_recon.geometry.triangulate import triangulate
from sefm_recon.geometry.two_view import TwoView
from sefm_recon.matching.plane_align import agreement, align_images, align_plane, halves_agree
from sefm_recon.matching.planes import fill_planes

W, H, F = 320, 240, 300.0
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])
TV = TwoView(K, K, np.eye(3), np.array([-1.0, 0, 0]))  # lateral, unit baseline: x2 = x1 - F / z
A, E = K @ TV.R @ np.linalg.inv(K), K @ TV.t
# a floor: parallax F / z from 8 px at the top row to 16 px at the bottom one (COLMAP positions)
FLOOR = np.array([0.0, 8.0 / (H * F), 8.0 / F])


def _parallax(abc, uv):
    return F * (uv @ abc[:2] + abc[2])


def _texture(seed, amplitude, blur=3.0):
    """A faint, smooth texture: (H, W) float32 about 128 with ``amplitude`` grey levels' deviation."""
    g = cv2.GaussianBlur(np.random.default_rng(seed).normal(size=(H, W)).astype(np.float32), (0, 0), blur)
    return 128 + g * (amplitude / g.std())


def _view2(image1, parallax_of_row, gain=0.8, offset=20.0, noise=1.0, seed=1):
    """Image 2 of a surface whose parallax depends on the row (``parallax_of_row``: (H,) px):
    image 1 shifted left by it, under another gain and offset and its own sensor noise; uint8."""
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    img = cv2.remap(image1, xs + parallax_of_row[:, None].astype(np.float32), ys, cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REFLECT)
    img = gain * img + offset + np.random.default_rng(seed).normal(scale=noise, size=img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _floor_pair(amplitude=3.0, seed=0):
    one = _texture(seed, amplitude)
    rows = np.arange(H) + 0.5
    two = _view2(one, F * (rows * FLOOR[1] + FLOOR[2]))
    return np.clip(np.rint(one), 0, 255).astype(np.uint8), two


def _pixels(step=2, margin=24):
    ys, xs = np.mgrid[margin:H - margin:step, margin:W - margin:step]
    return np.column_stack([xs.ravel() + 0.5, ys.ravel() + 0.5])


def test_a_faint_floor_3_px_off_is_aligned_to_a_tenth_of_a_pixel_under_another_gain_and_offset():
    """Texture of 3 grey levels under 1 level of noise, image 2 at 0.8 x the brightness plus
    20: started 3 px off at the bottom and 1 px at the top, the plane comes within 0.1 px."""
    one, two = _floor_pair()
    px = _pixels()
    start = FLOOR + np.array([0.0, 2.0 / (H * F), 1.0 / F])
    assert np.abs(_parallax(start, px) - _parallax(FLOOR, px)).max() > 2.5
    got = align_plane(align_images(one, two, px), A, E, px, start)
    assert np.abs(_parallax(got, px) - _parallax(FLOOR, px)).max() < 0.1


def test_a_steep_floor_with_blotches_as_wide_as_the_normalisation_window_is_aligned_without_a_bias():
    """A floor whose parallax grows from 8 px at the top row to 128 px at the bottom one (image 2
    sheared by half a pixel a row) under blotches about 24 px across, 20 grey levels deep:
    blurred and normalised in its own frame, image 2's windows would cover other parts of the
    floor than image 1's and the plane would settle 0.2-0.7 px (median) off. Warped into image
    1's frame first, it comes within 0.1 px everywhere, from 3 px off."""
    floor = np.array([0.0, 120.0 / (H * F), 8.0 / F])
    to1 = np.array([[1.0, 0, 0.5], [0, 1.0, 0.5], [0, 0, 1.0]])  # pixel index to COLMAP position
    from2 = np.linalg.inv(to1)
    px = _pixels()
    px = px[px[:, 0] - _parallax(floor, px) >= 24]  # (their partners inside image 2)
    start = floor + np.array([0.0, 2.0 / (H * F), 1.0 / F])  # 1 px off at the top, 3 px at the bottom
    for seed in range(2):
        texture = _texture(seed, 20.0, blur=24.0)
        two = cv2.warpPerspective(texture, from2 @ (A + np.outer(E, floor)) @ to1, (W, H), flags=cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_REFLECT)
        noise = np.random.default_rng(seed + 10).normal(size=two.shape)
        two = np.clip(np.rint(0.8 * two + 20 + noise), 0, 255).astype(np.uint8)
        one = np.clip(np.rint(texture), 0, 255).astype(np.uint8)
        assert np.abs(_parallax(start, px) - _parallax(floor, px)).max() > 2.5
        got = align_plane(align_images(one, two, px), A, E, px, start)
        assert np.abs(_parallax(got, px) - _parallax(floor, px)).max() < 0.1


def test_the_agreement_of_image_2_under_the_true_plane_is_the_same_whether_it_is_zoomed_or_not():
    """Image 2 the same texture zoomed 1x, 1.5x and 2x about the centre (a frontal plane, the
    camera moved towards it): warped by the true homography, it correlates with image 1 as
    well at every zoom (0.99). Blurred and normalised in its own frame before the warp, its
    windows would hold other scales than image 1's and the correlation fall (0.85 at 2x)."""
    to1 = np.array([[1.0, 0, 0.5], [0, 1.0, 0.5], [0, 0, 1.0]])  # pixel index to COLMAP position
    texture = _texture(0, 10.0, blur=1.5)
    one = np.clip(np.rint(texture), 0, 255).astype(np.uint8)
    region = np.ones((80, 100), bool)
    medians = []
    for s in (1.0, 1.5, 2.0):
        zoom = np.array([[s, 0, W / 2 * (1 - s)], [0, s, H / 2 * (1 - s)], [0, 0, 1.0]])
        two = cv2.warpPerspective(texture, np.linalg.inv(to1) @ zoom @ to1, (W, H), flags=cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_REFLECT)
        noise = np.random.default_rng(1).normal(size=two.shape)
        two = np.clip(np.rint(0.8 * two + 20 + noise), 0, 255).astype(np.float32)
        z, = agreement(one, two, zoom, 110, 80, region, (region,))
        medians.append(np.nanmedian(z))
    assert min(medians) > 0.98 and max(medians) - min(medians) < 0.01


def test_the_halves_of_one_plane_agree_and_those_of_a_fold_or_of_noise_do_not():
    """A fold, or a plain surface whose images hold only their own sensor noise (no signal
    to align: each half's plane wanders), is no one plane the images fix."""
    one, two = _floor_pair()
    px = _pixels()
    images = align_images(one, two, px)
    assert halves_agree(images, A, E, px, align_plane(images, A, E, px, FLOOR))
    # the same texture on two planes, the upper half frontal at 10 px and the lower at 16 px
    rows = np.arange(H)
    fold = _view2(one.astype(np.float32), np.where(rows < H // 2, 10.0, 16.0))
    mid = np.array([0.0, 0.0, 13.0 / F])
    images = align_images(one, fold, px)
    assert not halves_agree(images, A, E, px, align_plane(images, A, E, px, mid))
    for seed in range(3):
        rng = np.random.default_rng(seed)
        grey1, grey2 = (np.clip(np.rint(128 + rng.normal(size=(H, W))), 0, 255).astype(np.uint8) for _ in range(2))
        images = align_images(grey1, grey2, px)
        assert not halves_agree(images, A, E, px, align_plane(images, A, E, px, FLOOR))


def test_halves_whose_tilts_part_beyond_them_agree_each_on_its_own_pixels_and_a_fold_does_not():
    """A faint floor seen in two strips 16 px high at its top and bottom (the pixels among a
    mostly unmatched floor's matches can cluster so): the plane aligned on both is within
    0.15 px of the truth, but each strip fixes its own tilt so loosely that the strips' planes
    part by over 1 px across the whole floor, and the halves test fails for most textures.
    Each strip's plane gives its own pixels the whole plane's partners (``each_own``). A fold
    of 6 px, a plane on neither half, still fails, as does a pair of noise images."""
    rows = np.arange(H) + 0.5
    px = _pixels(step=1)
    strips = px[(px[:, 1] < 40) | (px[:, 1] > H - 40)]
    strict = []
    for seed in range(3):
        one = _texture(seed, 2.0)
        two = _view2(one, F * (rows * FLOOR[1] + FLOOR[2]), seed=seed + 7)
        images = align_images(np.clip(np.rint(one), 0, 255).astype(np.uint8), two, strips)
        abc = align_plane(images, A, E, strips, FLOOR)
        assert np.median(np.abs(_parallax(abc, strips) - _parallax(FLOOR, strips))) < 0.15
        strict.append(halves_agree(images, A, E, strips, abc))
        assert halves_agree(images, A, E, strips, abc, each_own=True)
    assert strict.count(False) >= 2
    one, _ = _floor_pair()
    px = _pixels()
    fold = _view2(one.astype(np.float32), np.where(np.arange(H) < H // 2, 10.0, 16.0))
    images = align_images(one, fold, px)
    assert not halves_agree(images, A, E, px, align_plane(images, A, E, px, np.array([0.0, 0.0, 13.0 / F])),
                            each_own=True)
    for seed in range(3):
        rng = np.random.default_rng(seed)
        grey1, grey2 = (np.clip(np.rint(128 + rng.normal(size=(H, W))), 0, 255).astype(np.uint8) for _ in range(2))
        images = align_images(grey1, grey2, px)
        assert not halves_agree(images, A, E, px, align_plane(images, A, E, px, FLOOR), each_own=True)


def _plain_floor_scene(seed=0, right_share=0.4, matched=0.3, sign=None):
    """Image 1: the faint floor framed by strong texture (its own plain region); image 2 as
    the floor gives it; and matches on ``matched`` of the floor's pixels, ``right_share`` of
    them on the floor (0.3 px noise) and the rest 2-8 px off it (nearer or farther at random,
    or by ``sign``: 1 nearer, -1 farther), as SGM's on a weakly textured floor."""
    one, two = _floor_pair()
    rng = np.random.default_rng(seed)
    frame = np.ones((H, W), bool)
    frame[12:H - 12, 12:W - 12] = False
    one[frame] = rng.integers(0, 256, np.count_nonzero(frame))
    px = _pixels(step=1, margin=16)
    px = px[rng.random(len(px)) < matched]
    right = rng.random(len(px)) < right_share
    side = rng.choice([-1, 1], len(px)) if sign is None else sign
    err = np.where(right, rng.normal(scale=0.3, size=len(px)), side * rng.uniform(2, 8, len(px)))
    uv2 = px - np.column_stack([_parallax(FLOOR, px) + err, np.zeros(len(px))])
    X, ok, _ = triangulate(TV.K1, TV.K2, TV.R, TV.t, px, uv2)
    return one, two, px[ok], uv2[ok], X[ok], np.abs(err[ok])


def test_a_mostly_unmatched_floor_whose_plane_aligns_is_kept_moved_onto_it_and_filled():
    """Without image 2 the floor's matches lie mostly off one plane and go (the scattered
    check); with it the plane aligns and its halves agree: the matches within 3 px of it move
    onto it, the others go, and the unmatched pixels among them take its partners."""
    one, two, uv1, uv2, X, err = _plain_floor_scene()
    size = (W, H)
    region = np.zeros(len(uv1), bool)  # the floor's matches (the region stops short of its edges)
    region[fill_planes(one, size, TV, uv1, uv2, X).dropped] = True
    assert region.mean() > 0.95
    out = fill_planes(one, size, TV, uv1, uv2, X, gray2=two)
    gone = np.zeros(len(uv1), bool)
    gone[out.dropped] = True
    assert not gone[err <= 2.9].any() and gone[region & (err > 3.1)].all()
    moved_par = out.moved_uv2[:, 0] - uv1[out.moved, 0]
    assert np.abs(-moved_par - _parallax(FLOOR, uv1[out.moved])).max() < 0.15
    assert len(out.uv1) > 2 * len(uv1)  # the holes between them
    assert np.abs(out.uv1[:, 0] - out.uv2[:, 0] - _parallax(FLOOR, out.uv1)).max() < 0.15
    assert np.abs(out.uv1[:, 1] - out.uv2[:, 1]).max() < 1e-6  # on their epipolar lines


def test_a_mostly_unmatched_floor_with_too_few_matches_on_its_plane_to_fill_is_aligned_and_filled():
    """55 % of the matches on the floor: too many for the scattered check to drop them, too
    few for the fill from the matches alone (60 %); without image 2 nothing is filled, with it
    the plane aligns, the matches off it go and the floor is filled."""
    one, two, uv1, uv2, X, err = _plain_floor_scene(right_share=0.55)
    without = fill_planes(one, (W, H), TV, uv1, uv2, X)
    assert len(without.uv1) == 0 and len(without.moved) == 0
    out = fill_planes(one, (W, H), TV, uv1, uv2, X, gray2=two)
    gone = np.zeros(len(uv1), bool)
    gone[out.dropped] = True
    assert not gone[err <= 2.9].any() and gone[err > 3.1].mean() > 0.95
    assert len(out.uv1) > 2 * len(uv1)
    assert np.abs(out.uv1[:, 0] - out.uv2[:, 0] - _parallax(FLOOR, out.uv1)).max() < 0.15


def _repeats_off(uv1, share, seed=3):
    """Estimates the repeat check dropped on ``share`` of the pixels of ``uv1`` (a quarter px
    below each), 2-8 px off the floor, nearer or farther at random."""
    rng = np.random.default_rng(seed)
    rep1 = uv1[rng.choice(len(uv1), int(share * len(uv1)), replace=False)] + [0.0, 0.25]
    off = rng.choice([-1, 1], len(rep1)) * rng.uniform(2, 8, len(rep1))
    return rep1, rep1 - np.column_stack([_parallax(FLOOR, rep1) + off, np.zeros(len(rep1))])


def test_a_scattered_floor_with_repeats_is_dropped_whole_though_its_plane_would_align():
    """The floor whose plane the intensities align without repeats (40 % of its matches on
    it; test_a_mostly_unmatched_floor_whose_plane_aligns_is_kept_moved_onto_it_and_filled)
    is dropped whole, image 2 or not, once the repeat check dropped
    estimates there and they with its matches lie on no one plane: texture repeating along
    the lines, where an aligned plane can be a period off or SGM's own wrong surface
    (generated seed 6 at 1600x1200, a floor aligned at a median ZNCC of 0.991 and filled
    15 px off: 0.925 at 3 px, 0.996 dropped). So is a floor whose own matches lie on one plane
    (55 %) and only the drops, a fifth as many, take the share under half."""
    for right_share, share in ((0.4, 0.01), (0.55, 0.2)):
        one, two, uv1, uv2, X, err = _plain_floor_scene(right_share=right_share)
        for gray2 in (None, two):
            out = fill_planes(one, (W, H), TV, uv1, uv2, X, gray2=gray2, repeats=_repeats_off(uv1, share))
            assert len(out.dropped) > 0.95 * len(uv1) and len(out.uv1) == 0
        # without the repeats the first floor's plane aligns and fills it
        if right_share == 0.4:
            assert len(fill_planes(one, (W, H), TV, uv1, uv2, X, gray2=two).uv1) > 2 * len(uv1)


def test_a_mostly_matched_floor_with_too_few_matches_on_one_plane_is_filled_where_its_plane_aligns():
    """70 % of the floor matched, 55 % of those on it: too few on one plane for the fill from
    the matches alone, and too many matched for the scattered check. With image 2 the plane
    aligns and the unmatched pixels take it; SGM's matches stay as they are (too few lie on
    the aligned plane to call the others noise). (The matches off the floor lie farther, so
    that they hide none of it in view 2.)"""
    one, two, uv1, uv2, X, _ = _plain_floor_scene(right_share=0.55, matched=0.7, sign=-1)
    without = fill_planes(one, (W, H), TV, uv1, uv2, X)
    assert len(without.uv1) == 0 and len(without.moved) == 0 and len(without.dropped) == 0
    out = fill_planes(one, (W, H), TV, uv1, uv2, X, gray2=two)
    assert len(out.moved) == 0 and len(out.dropped) == 0
    # 3 / 7 of the floor is unmatched; a part of it stays hidden in view 2 behind the matches
    # on the floor, whose 0.3 px of noise is 2-4 % of the depth (HIDDEN_DEPTH_SHARE: 1 %)
    assert len(out.uv1) > 0.1 * len(uv1)
    assert np.abs(out.uv1[:, 0] - out.uv2[:, 0] - _parallax(FLOOR, out.uv1)).max() < 0.15


def test_scattered_matches_1_to_3_px_off_an_aligned_floor_move_onto_it_and_a_patch_off_it_stays():
    """75 % of a mostly matched floor's matches on it, the rest scattered 1-3 px off (SGM's
    noise on a weakly textured floor), and one band of rows whose matches all lie 1.5 px off
    (as a surface leaving the plane would). The plane aligns: the scattered matches move onto
    it, the band's stay as they are (most matches about them are off the plane), and so do
    those 3 px or more off."""
    one, two, uv1, uv2, X, err = _plain_floor_scene(right_share=0.75, matched=0.7, sign=-1)
    rng = np.random.default_rng(3)
    scattered = (err > 0.9) & (rng.random(len(err)) < 0.5)  # half of the matches off the floor: 1-3 px off
    err[scattered] = rng.uniform(1.2, 2.8, scattered.sum())
    band = (uv1[:, 1] > 150) & (uv1[:, 1] < 190)
    err[band] = 1.5
    uv2 = uv1 - np.column_stack([_parallax(FLOOR, uv1) - err, np.zeros(len(uv1))])  # (farther)
    X, ok, _ = triangulate(TV.K1, TV.K2, TV.R, TV.t, uv1, uv2)
    assert ok.all()
    out = fill_planes(one, (W, H), TV, uv1, uv2, X, gray2=two)
    moved = np.zeros(len(uv1), bool)
    moved[out.moved] = True
    away = (uv1[:, 1] < 150 - 16) | (uv1[:, 1] > 190 + 16)  # (windows about them reach no band)
    assert moved[scattered & away].mean() > 0.95
    assert not moved[band].any() and not moved[err > 3.1].any() and not moved[err < 0.9].any()
    assert np.abs(uv1[out.moved, 0] - out.moved_uv2[:, 0] - _parallax(FLOOR, uv1[out.moved])).max() < 0.15


def test_noise_both_ways_about_an_aligned_floor_moves_onto_it_where_it_is_the_local_majority():
    """A band of rows where two thirds of the floor's matches lie 1-3 px off it, half of them
    nearer and half farther (SGM's noise outnumbering the right matches there): they move
    onto the aligned plane, as a band all on one side would not (a surface leaving it)."""
    one, two, uv1, uv2, X, err = _plain_floor_scene(right_share=0.8, matched=0.7, sign=-1)
    rng = np.random.default_rng(4)
    band = (uv1[:, 1] > 128) & (uv1[:, 1] < 184)
    noisy = band & (rng.random(len(uv1)) < 2 / 3)
    off = np.where(noisy, rng.choice([-1.0, 1.0], len(uv1)) * rng.uniform(1.2, 2.8, len(uv1)), 0.0)
    err = np.where(noisy, np.abs(off), err)
    uv2 = np.where(noisy[:, None], uv1 - np.column_stack([_parallax(FLOOR, uv1) + off, np.zeros(len(uv1))]), uv2)
    X, ok, _ = triangulate(TV.K1, TV.K2, TV.R, TV.t, uv1, uv2)
    assert ok.all()
    out = fill_planes(one, (W, H), TV, uv1, uv2, X, gray2=two)
    moved = np.zeros(len(uv1), bool)
    moved[out.moved] = True
    inner = noisy & (uv1[:, 1] > 128 + 16) & (uv1[:, 1] < 184 - 16) & (uv1[:, 0] > 32) & (uv1[:, 0] < W - 32)
    assert inner.sum() > 1000 and moved[inner].mean() > 0.95
    assert np.abs(uv1[out.moved, 0] - out.moved_uv2[:, 0] - _parallax(FLOOR, uv1[out.moved])).max() < 0.15


def test_a_plane_image_2_shows_nothing_of_is_not_aligned_though_its_halves_agree():
    """Image 2 of one value where the floor would be (a surface hidden in view 2, or beyond
    its edge): the alignment has no gradient to follow, so both halves stay on RANSAC's
    plane and agree. Image 2 under the plane does not match image 1, so it is no aligned
    plane: nothing is filled or moved onto it, as where image 2 shows another texture."""
    one, two, uv1, uv2, X, _ = _plain_floor_scene(right_share=0.55)
    two[:] = 140
    other = np.clip(np.rint(_texture(11, 3.0)), 0, 255).astype(np.uint8)
    for image2 in (two, other):
        out = fill_planes(one, (W, H), TV, uv1, uv2, X, gray2=image2)
        assert len(out.uv1) == 0 and len(out.moved) == 0
        assert 0.3 * len(uv1) < len(out.dropped) < 0.6 * len(uv1)  # the matches off the plane


def test_a_region_whose_matches_are_too_sparse_to_align_is_dropped_as_before():
    """Matches on 1 % of the floor, at depths drawn at random: too sparse for any pixel to
    lie among matches on one plane, so there is nothing to align and they go (as without
    image 2), with no error."""
    one, two, *_ = _plain_floor_scene()
    rng = np.random.default_rng(7)
    px = _pixels(step=1, margin=16)
    px = px[rng.random(len(px)) < 0.01]
    uv2 = px - np.column_stack([rng.uniform(4, 30, len(px)), np.zeros(len(px))])
    X, ok, _ = triangulate(TV.K1, TV.K2, TV.R, TV.t, px, uv2)
    px, uv2, X = px[ok], uv2[ok], X[ok]
    without = fill_planes(one, (W, H), TV, px, uv2, X)
    out = fill_planes(one, (W, H), TV, px, uv2, X, gray2=two)
    assert len(without.dropped) > 0.9 * len(px)
    np.testing.assert_array_equal(out.dropped, without.dropped)
    assert len(out.uv1) == 0 and len(out.moved) == 0


def _floor_cut_in_two(matched_left=0.6):
    """The faint floor cut into two plain regions by a band of strong texture (an object
    standing on it, columns 150-170 of image 1): the left one ``matched_left`` matched, 90 %
    of them on the floor (0.3 px noise), the right one 1 % matched at random depths (SGM's
    ties and noise on a plain surface). ``(image 1, image 2, uv1, uv2, X, right)``, ``right``
    (N,) bool: the matches of the right region."""
    one, two, uv1, uv2, X, _ = _plain_floor_scene(right_share=0.9, matched=matched_left)
    rng = np.random.default_rng(5)
    one[:, 150:170] = rng.integers(0, 256, (H, 20))
    left = uv1[:, 0] < 145
    px = _pixels(step=1, margin=16)
    px = px[(px[:, 0] > 175) & (rng.random(len(px)) < 0.01)]
    px2 = px - np.column_stack([rng.uniform(4, 30, len(px)), np.zeros(len(px))])
    Xr, ok, _ = triangulate(TV.K1, TV.K2, TV.R, TV.t, px, px2)
    uv1, uv2 = np.concatenate([uv1[left], px[ok]]), np.concatenate([uv2[left], px2[ok]])
    X = np.concatenate([X[left], Xr[ok]])
    return one, two, uv1, uv2, X, np.arange(len(uv1)) >= np.count_nonzero(left)


def test_a_plain_region_with_no_surface_of_its_own_is_filled_from_the_plane_of_the_floor_beside_it():
    """The floor's right region holds no surface the matcher found: its matches go. The plane
    of the left region, aligned on the right one's pixels, converges onto the floor there
    (the same floor), its halves agree and image 2 under it matches image 1: the right region
    is filled from it. Without borrowing, or where image 2 shows nothing there (one value),
    it stays unmatched."""
    one, two, uv1, uv2, X, right = _floor_cut_in_two()
    out = fill_planes(one, (W, H), TV, uv1, uv2, X, gray2=two)
    assert right[out.dropped].all() and np.count_nonzero(right[out.dropped]) > 0.9 * np.count_nonzero(right)
    filled = np.zeros((H, W), bool)
    filled[out.uv1[:, 1].astype(int), out.uv1[:, 0].astype(int)] = True
    assert filled[24:H - 24, 180:W - 24].mean() > 0.95
    on_right = out.uv1[:, 0] > 170
    assert np.abs(out.uv1[on_right, 0] - out.uv2[on_right, 0] - _parallax(FLOOR, out.uv1[on_right])).max() < 0.25
    without = fill_planes(one, (W, H), TV, uv1, uv2, X, gray2=two, borrow=False)
    assert not (without.uv1[:, 0] > 170).any()
    np.testing.assert_array_equal(without.dropped, out.dropped)
    two[:, 150:] = 140  # image 2 shows nothing of the right region
    out = fill_planes(one, (W, H), TV, uv1, uv2, X, gray2=two)
    assert not (out.uv1[:, 0] > 170).any()


def test_a_borrowed_plane_is_the_start_that_converges_onto_the_surface_and_only_once_converged(monkeypatch):
    """On the right region of the floor cut in two: from a start 12 px of parallax off, the
    alignment settles on no surface (its halves or image 2 reject it) and nothing is borrowed;
    given a start 6 px off as well, that one reaches the floor. With an alignment that only
    halves the distance each time (still 0.4 px off after the further alignments allowed), the
    plane is not kept: only a converged alignment is."""
    import sefm_recon.matching.plane_align as plane_align
    import sefm_recon.matching.planes as planes

    one, two, uv1, uv2, X, _ = _floor_cut_in_two()
    labels, stats = planes.plain_regions(one)
    x0, y0, region, _ = planes._among_plane_matches(labels, stats, labels[H // 2, 250], np.zeros((0, 2)))
    pose, two = planes._pose(TV), two.astype(np.float32)
    px = np.column_stack([np.nonzero(region)[1] + x0 + 0.5, np.nonzero(region)[0] + y0 + 0.5])

    def borrowed(*offsets):
        starts = [FLOOR + np.array([0.0, 0.0, o / F]) for o in offsets]
        return planes._borrowed_plane(one, two, pose, x0, y0, region, starts, np.random.default_rng(0))

    assert borrowed(12.0) is None
    abc, _ = borrowed(12.0, 6.0)
    assert np.abs(_parallax(abc, px) - _parallax(FLOOR, px)).max() < 0.25

    def halfway(images, A, e, uv1, abc):
        return abc + 0.5 * (plane_align.align_plane(images, A, e, uv1, abc) - abc)

    monkeypatch.setattr(planes, "align_plane", halfway)
    assert borrowed(6.0) is None


def test_an_aligned_floor_is_filled_beyond_its_matches_where_image_2_shows_it_and_not_where_it_is_hidden():
    """Matches on the left half of the floor only; image 2 shows the floor's lower right
    part behind another surface (strong texture of its own). The plane aligned on the left
    half fills the upper right part, beyond the matches, on the floor; the hidden part,
    whose window in image 2 under the plane shows the other surface, stays unfilled."""
    one, two, uv1, uv2, X, _ = _plain_floor_scene()
    left = uv1[:, 0] < W / 2
    uv1, uv2, X = uv1[left], uv2[left], X[left]
    occluder = np.random.default_rng(5).integers(0, 256, (H // 2, W // 4 + 16))
    two[H // 2:, W - occluder.shape[1]:] = occluder
    out = fill_planes(one, (W, H), TV, uv1, uv2, X, gray2=two)
    filled = np.zeros((H, W), bool)
    filled[out.uv1[:, 1].astype(int), out.uv1[:, 0].astype(int)] = True
    upper_right = filled[24:H // 2 - 16, W // 2 + 16:W - 16]
    assert upper_right.mean() > 0.95
    # (the plane aligned on the left half, carried across the right: 0.16 px off at its far edge)
    assert np.abs(out.uv1[:, 0] - out.uv2[:, 0] - _parallax(FLOOR, out.uv1)).max() < 0.25
    # image 1's pixels whose partners on the floor lie 16 px or more inside the occluder
    ys, xs = np.mgrid[H // 2 + 16:H - 16, 0:W - 16]
    px = np.column_stack([xs.ravel() + 0.5, ys.ravel() + 0.5])
    hidden = px[px[:, 0] - _parallax(FLOOR, px) >= W - occluder.shape[1] + 16]
    assert len(hidden) > 1000
    assert filled[hidden[:, 1].astype(int), hidden[:, 0].astype(int)].mean() < 0.05
    # without image 2 nothing is aligned: the floor's scattered matches go, nothing is filled
    assert len(fill_planes(one, (W, H), TV, uv1, uv2, X).uv1) == 0


def test_a_plane_whose_halves_part_among_its_matches_is_judged_again_where_image_2_agrees(monkeypatch):
    """Matches on the floor's left quarter alone. Where the halves test fails on the pixels
    among them (here forced: any set of at most that many pixels), the plane is judged again
    over those and the floor's pixels where image 2 under it agrees, four times as many (each
    half then also on its own pixels): its halves agree there and the floor is filled. Where
    image 2 bears the plane out nowhere (one value), there is nothing wider to judge it on,
    and nothing is filled."""
    import sefm_recon.matching.planes as planes

    one, two, uv1, uv2, X, _ = _plain_floor_scene()
    left = uv1[:, 0] < W / 4
    uv1, uv2, X = uv1[left], uv2[left], X[left]
    asked = []
    honest = planes.halves_agree
    assert len(fill_planes(one, (W, H), TV, uv1, uv2, X, gray2=two).uv1) > 3 * len(uv1)  # (agreeing at once)

    owns = []

    def halves(images, A, e, px, abc, **kw):
        asked.append(len(px))
        owns.append(kw.get("each_own", False))
        return len(px) > W / 3 * H and honest(images, A, e, px, abc, **kw)

    monkeypatch.setattr(planes, "halves_agree", halves)
    out = fill_planes(one, (W, H), TV, uv1, uv2, X, gray2=two)
    assert len(asked) == 2 and asked[0] < W / 3 * H < asked[1]
    assert owns == [False, True]  # (each half on its own pixels at the second asking alone)
    filled = np.zeros((H, W), bool)
    filled[out.uv1[:, 1].astype(int), out.uv1[:, 0].astype(int)] = True
    assert filled[24:H - 24, W // 2:W - 24].mean() > 0.95
    assert np.abs(out.uv1[:, 0] - out.uv2[:, 0] - _parallax(FLOOR, out.uv1)).max() < 0.25
    asked.clear()
    two[:] = 140
    out = fill_planes(one, (W, H), TV, uv1, uv2, X, gray2=two)
    assert len(asked) == 1 and len(out.uv1) == 0 and len(out.moved) == 0  # (no second test)


def test_an_object_in_front_of_an_aligned_floor_keeps_its_matches():
    """The mostly unmatched floor of the tests above, and on it a plain box face of 48 x 48 px
    with no intensity edge between them, its pixels 70 % matched 6 px nearer (one patch well
    over 1/500 of the view) and its faint texture not the floor's (image 2 under the floor's
    plane does not match it). The floor's plane aligns; the box's matches stay where they are,
    off the plane, and the floor's own matches off the plane go as before: farther ones, and
    nearer ones scattered in patches of a few pixels. With the floor's own texture where the
    box is in image 1, the same patch is noise on the floor (image 2 under the plane matches
    it) and goes."""
    one, two, uv1, uv2, X, err = _plain_floor_scene()
    floor_only = one.copy()
    # the box face in image 1: a faint texture of its own, blended in over a few pixels (no edge)
    face = np.zeros((H, W), np.float32)
    face[100:148, 130:178] = 1.0
    face = cv2.GaussianBlur(face, (0, 0), 3.0)
    one = np.clip(np.rint(one * (1 - face) + _texture(13, 3.0) * face), 0, 255).astype(np.uint8)
    box = (uv1[:, 0] > 130) & (uv1[:, 0] < 178) & (uv1[:, 1] > 100) & (uv1[:, 1] < 148)
    floor1, floor2, err = uv1[~box], uv2[~box], err[~box]
    ys, xs = np.mgrid[101:148, 131:178]
    px = np.column_stack([xs.ravel() + 0.5, ys.ravel() + 0.5])
    px = px[np.random.default_rng(9).random(len(px)) < 0.7]
    box2 = px - np.column_stack([_parallax(FLOOR, px) + 6.0, np.zeros(len(px))])
    uv1, uv2 = np.concatenate([floor1, px]), np.concatenate([floor2, box2])
    X, ok, _ = triangulate(TV.K1, TV.K2, TV.R, TV.t, uv1, uv2)
    assert ok.all()
    on_box = np.arange(len(uv1)) >= len(floor1)
    region = np.zeros(len(uv1), bool)  # the floor's matches (without image 2 they scatter, and go)
    region[fill_planes(one, (W, H), TV, uv1, uv2, X).dropped] = True
    assert region[~on_box].mean() > 0.95
    out = fill_planes(one, (W, H), TV, uv1, uv2, X, gray2=two)
    gone = np.zeros(len(uv1), bool)
    gone[out.dropped] = True
    moved = np.zeros(len(uv1), bool)
    moved[out.moved] = True
    # (a box pixel whose neighbours all went unmatched is a patch of its own, and goes)
    assert gone[on_box].mean() < 0.01 and not moved[on_box].any()
    # (the floor's nearer matches touching the box join its patch)
    by_box = (floor1[:, 0] > 128) & (floor1[:, 0] < 180) & (floor1[:, 1] > 98) & (floor1[:, 1] < 150)
    floor_gone = gone[~on_box]
    assert floor_gone[region[~on_box] & ~by_box & (err > 3.1)].all() and not floor_gone[err <= 2.9].any()
    assert len(out.uv1) > len(floor1)  # the floor is filled
    # where image 1 shows the floor's own texture, image 2 under the plane matches it there:
    # the patch is SGM's noise on the floor, and goes
    gone[:] = False
    gone[fill_planes(floor_only, (W, H), TV, uv1, uv2, X, gray2=two).dropped] = True
    assert gone[on_box].all()


#: The row where the floor of the test below ends, before a wall farther back.
JOIN = 120
#: The wall's parallax, px: farther than the floor's far end (8-12 px there).
WALL_PAR = 6.0


def _wall_parallax(uv):
    return np.where(uv[:, 1] < JOIN, WALL_PAR, _parallax(FLOOR, uv))


def _wall_and_floor(seed=0):
    """One plain region holding two surfaces with no intensity edge between them: a wall above
    row ``JOIN`` (parallax ``WALL_PAR``) and the floor below it, each its own faint texture
    blended over 8 rows. A third of its pixels matched: the wall's 95 % right (0.3 px of noise),
    the floor's 60 %, the rest 2-8 px off either way (SGM on a floor fainter than the wall).
    Returns the images, the matches, their points, errors (px) and which lie on the wall."""
    rng = np.random.default_rng(seed)
    blend = np.clip((np.arange(H) - (JOIN - 4)) / 8.0, 0, 1)[:, None]
    one = _texture(seed, 3.0) * (1 - blend) + _texture(seed + 7, 3.0) * blend
    rows = np.arange(H) + 0.5
    two = _view2(one, np.where(rows < JOIN, WALL_PAR, F * (rows * FLOOR[1] + FLOOR[2])))
    one = np.clip(np.rint(one), 0, 255).astype(np.uint8)
    frame = np.ones((H, W), bool)
    frame[12:H - 12, 12:W - 12] = False
    one[frame] = rng.integers(0, 256, np.count_nonzero(frame))
    px = _pixels(step=1, margin=16)
    px = px[rng.random(len(px)) < 0.3]
    wall = px[:, 1] < JOIN
    right = rng.random(len(px)) < np.where(wall, 0.95, 0.6)
    wrong = rng.choice([-1, 1], len(px)) * rng.uniform(2, 8, len(px))
    err = np.where(right, rng.normal(scale=0.3, size=len(px)), wrong)
    uv2 = px - np.column_stack([_wall_parallax(px) + err, np.zeros(len(px))])
    X, ok, _ = triangulate(TV.K1, TV.K2, TV.R, TV.t, px, uv2)
    return one, two, px[ok], uv2[ok], X[ok], np.abs(err[ok]), wall[ok]


def test_a_second_surface_in_an_aligned_planes_region_keeps_its_matches_and_takes_none_of_its_fill():
    """Under half of the region's matches lie on one plane (the wall's), which aligns: alone,
    it drops the floor's right matches as noise about it and fills floor pixels with its own
    partners. The floor's matches off it lie on one homography that image 2 bears out better
    there: they stay, and the wall's plane fills the wall alone (up to the few rows where
    the pixels nearest to each surface's matches meet)."""
    one, two, uv1, uv2, X, err, wall = _wall_and_floor()
    floor_right = ~wall & (err <= 1.0)  # (0.3 px of noise; the wrong ones 2-8 px off)

    def run(two_surfaces):
        out = fill_planes(one, (W, H), TV, uv1, uv2, X, gray2=two, two=two_surfaces)
        gone = np.zeros(len(uv1), bool)
        gone[out.dropped] = True
        off = np.abs(out.uv1[:, 0] - out.uv2[:, 0] - _wall_parallax(out.uv1))
        return gone, out.uv1, off

    gone, filled, off = run(False)
    assert gone[floor_right].mean() > 0.9 and np.count_nonzero(off > 1) > 500
    gone, filled, off = run(True)
    assert not gone[floor_right].any() and not gone[wall & (err <= 1.0)].any()
    assert gone[~wall & (err > 3.1)].mean() > 0.5  # (those off the floor's homography too)
    on_wall = filled[:, 1] < JOIN
    assert on_wall.sum() > 15000 and off[on_wall].max() < 0.3
    assert (filled[~on_wall, 1] < JOIN + 8).all()


#: A surface 6 px nearer than the floor (in parallax) beside it, and the period (px) and
#: amplitude (grey levels) of the shading both share: stripes across the epipolar lines,
#: which correlate under any shift along them (a linear ramp would not: the local
#: normalisation takes it out), at most 1.3 grey levels a px (8 x 2 pi / 40), under the
#: intensity edges' bar (:data:`.planes.EDGE_GREY_PER_PX`).
NEARER = FLOOR + np.array([0.0, 0.0, 6.0 / F])
STRIPES, SHADE = 40.0, 8.0


def _floor_and_nearer_surface(seed=0):
    """One plain region: the floor on the left half, a surface 6 px nearer on the right, each
    its own faint texture blended over 8 columns, both under the same shading stripes; image 2
    as the two give it (the nearer one hiding the floor's right edge). A third of the left
    half's pixels matched, 40 % right (0.3 px of noise), the rest 2-8 px off; none on the right."""
    rng = np.random.default_rng(seed)
    blend = np.clip((np.arange(W) - (W // 2 - 4)) / 8.0, 0, 1)[None, :]
    rows = np.arange(H, dtype=np.float32)[:, None]
    one = (_texture(seed, 3.0) * (1 - blend) + _texture(seed + 7, 3.0) * blend
           + SHADE * np.cos(2 * np.pi * rows / STRIPES))
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    floor, nearer = F * ((ys + 0.5) * FLOOR[1] + FLOOR[2]), F * ((ys + 0.5) * NEARER[1] + NEARER[2])
    shift = np.where(xs + nearer >= W // 2, nearer, floor).astype(np.float32)
    two = cv2.remap(one.astype(np.float32), xs + shift, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    two = np.clip(np.rint(0.8 * two + 20 + rng.normal(scale=1.0, size=two.shape)), 0, 255).astype(np.uint8)
    one = np.clip(np.rint(one), 0, 255).astype(np.uint8)
    frame = np.ones((H, W), bool)
    frame[12:H - 12, 12:W - 12] = False
    one[frame] = rng.integers(0, 256, np.count_nonzero(frame))
    px = _pixels(step=1, margin=16)
    px = px[(rng.random(len(px)) < 0.3) & (px[:, 0] < W / 2 - 8)]
    err = np.where(rng.random(len(px)) < 0.4, rng.normal(scale=0.3, size=len(px)),
                   rng.choice([-1, 1], len(px)) * rng.uniform(2, 8, len(px)))
    uv2 = px - np.column_stack([_parallax(FLOOR, px) + err, np.zeros(len(px))])
    X, ok, _ = triangulate(TV.K1, TV.K2, TV.R, TV.t, px, uv2)
    return one, two, px[ok], uv2[ok], X[ok]


def test_an_aligned_floor_fills_no_surface_beside_it_that_its_shading_correlates_on(monkeypatch):
    """The floor's plane aligns on its matches, and image 2 under it correlates with image 1
    over the nearer surface too (the shading, at 0.8 and more on over half of it): judged by
    that alone, 20,000 of its pixels took the floor's partners, 6 px off. Aligned on those
    pixels, the plane converges onto another one over 1 px away (median), which gives none
    of them the floor's partner within 1 px: none is filled, while the floor's holes are, on
    the floor."""
    import sefm_recon.matching.planes as planes

    one, two, uv1, uv2, X = _floor_and_nearer_surface()

    def filled():
        out = fill_planes(one, (W, H), TV, uv1, uv2, X, gray2=two)
        right = out.uv1[:, 0] >= W / 2
        off = np.abs(out.uv1[:, 0] - out.uv2[:, 0] - _parallax(FLOOR, out.uv1))
        return np.count_nonzero(~right), np.count_nonzero(right), off[~right]

    on_floor, beside, off = filled()
    assert on_floor > 15000 and beside == 0 and off.max() < 0.2
    with monkeypatch.context() as m:  # (the plane judged by image 2's correlation alone)
        m.setattr(planes, "_realigned_apart", lambda *args: np.zeros(np.count_nonzero(args[6])))
        assert filled()[1] > 15000


def test_gradient_along_depth_is_the_warped_gradient_through_the_jacobian():
    """Image 2's gradient along the partners' move by depth: the warped image's gradient through
    the inverse of the warp's Jacobian, dotted with the partner's derivative by depth (written
    out with the derivatives of the dehomogenised partners), and not finite for a singular warp."""
    from sefm_recon.matching.plane_align import _gradient_along_depth, _moved

    rng = np.random.default_rng(1)
    H = np.eye(3) + 0.05 * rng.normal(size=(3, 3))
    e = np.array([12.0, -3.0, 0.02])
    p = np.column_stack([rng.uniform(0, 300, (50, 2)), np.ones(50)])
    gx, gy = rng.normal(size=50), rng.normal(size=50)
    x = p @ H.T
    ju, jv, dq = _moved(x, H[:, 0]), _moved(x, H[:, 1]), _moved(x, e)
    g2 = np.linalg.solve(np.stack([ju, jv], axis=1), np.column_stack([gx, gy])[:, :, None])[:, :, 0]
    got, ok = _gradient_along_depth(x, H[:, 0].copy(), H[:, 1].copy(), e, gx, gy)
    assert ok
    assert np.allclose(got, np.sum(g2 * dq, axis=1), rtol=1e-9, atol=1e-12)
    flat = H.copy()
    flat[:, 1] = flat[:, 0]  # (u and v move the partner alike: no inverse)
    assert not _gradient_along_depth(p @ flat.T, flat[:, 0].copy(), flat[:, 1].copy(), e, gx, gy)[1]
