"""Estimates on texture that repeats along the lines (:mod:`sefm_recon.matching.periodic`)."""

import cv2
import numpy as np

from sefm_recon.matching.periodic import (LEVEL_SHIFTS, ONCE_ZNCC, REPEAT_ZNCC, WINDOW_HALF, drop_repeating,
                                          repeat_score)


def _stripes(rows, cols, period, rng, noise=2.0):
    """Diagonal stripes of ``period`` columns along the rows, with sensor noise."""
    r, c = np.mgrid[0:rows, 0:cols]
    return 128 + 60 * np.sin(2 * np.pi * (c + 0.3 * r) / period) + rng.normal(0, noise, (rows, cols))


def _random_texture(rows, cols, rng):
    """A random texture smoothed over about 2 px, as a cloudy wall's."""
    import cv2

    return cv2.GaussianBlur(rng.normal(128, 40, (rows, cols)), (0, 0), 2.0)


def test_stripes_repeat_at_every_period_tried_and_a_random_texture_does_not():
    rng = np.random.default_rng(0)
    # (the windows of two halvings reach 4 x WINDOW_HALF columns, their shifts 4 x LEVEL_SHIFTS)
    inner = (slice(4, -4), slice(4 * WINDOW_HALF, -4 * (WINDOW_HALF + LEVEL_SHIFTS)))
    # a fine period at full size, one found at the first halving (12 columns there), one at the second
    for period in (5, 3 * LEVEL_SHIFTS // 2, 3 * LEVEL_SHIFTS):
        score = repeat_score(_stripes(64, 400, period, rng), 4 * LEVEL_SHIFTS)
        assert (score[inner] >= REPEAT_ZNCC).mean() > 0.95, period
    # not within the shifts tried: a period beyond the search's width misleads no match
    score = repeat_score(_stripes(64, 400, 3 * LEVEL_SHIFTS, rng), LEVEL_SHIFTS)
    assert (score[inner] >= REPEAT_ZNCC).mean() < 0.05
    score = repeat_score(_random_texture(64, 400, rng), 4 * LEVEL_SHIFTS)
    assert (score[inner] >= REPEAT_ZNCC).mean() < 0.02 and (score[inner] > -2).all()
    assert ((score[inner] < ONCE_ZNCC)).mean() > 0.8  # anchors
    plain = (np.full((64, 400), 90.0) + rng.normal(0, 1.0, (64, 400))).astype(np.float32)
    given = plain.copy()
    assert (repeat_score(plain, 64) == -2).all()  # plain: neither
    np.testing.assert_array_equal(plain, given)  # (the image given is left as it was)


def test_stripes_repeat_up_to_the_rows_end():
    """A window near the row's right end, whose copies ahead run out of the row before the
    stripes come back, is scored on its copies behind: it repeats like the others."""
    rng = np.random.default_rng(5)
    cols = 400
    # a period found at full size, at the first halving and at the second (their windows and
    # shifts 1, 2 and 4 times as wide): the windows within the row at the level that finds it,
    # whose copies ahead reach past the row's end before a period
    for period, step in ((9, 1), (3 * LEVEL_SHIFTS // 2, 2), (3 * LEVEL_SHIFTS, 4)):
        score = repeat_score(_stripes(64, cols, period, rng), 4 * LEVEL_SHIFTS)
        end = score[4:-4, cols - step * (WINDOW_HALF + LEVEL_SHIFTS):cols - step * (WINDOW_HALF + 1)]
        assert (end >= REPEAT_ZNCC).mean() > 0.95, period


def test_a_striped_patch_at_the_rows_end_is_dropped():
    """Stripes matched a period off up to the row's end (unseen seed 204's floor at image 1's
    edge): the windows at the patch's end, scored on their copies behind, repeat and anchor
    nothing."""
    rng = np.random.default_rng(6)
    rows, cols = 40, 400
    gray = _strong_texture(rows, cols, rng)
    # a period of 14 columns: the copies ahead of the last 14 windows run out of the row before
    # it, over a tenth of the patch (ANCHOR_SHARE), as many as the windows beside the texture
    gray[:, 250:] = _stripes(rows, 150, 14, rng)
    disp = np.full((rows, cols), -1.0, np.float32)
    disp[:, :240] = 40.0  # the textured surface, a jump (no estimates) before the stripes
    disp[:, 250:] = 29.0  # the stripes, to the row's end
    out = disp.copy()
    drop_repeating(out, repeat_score(gray, 64), -1.0)
    assert (out[:, 270:cols - WINDOW_HALF] == -1.0).mean() > 0.95
    assert (out[:, :240] == 40.0).all()


def _colour(grey, chroma):
    """RGB (rows, cols, 3) uint8 of ``grey`` plus ``chroma`` times a red-green axis of no grey value."""
    axis = np.array([1.0, -0.299 / 0.587, 0.0])  # (0.299 r + 0.587 g = 0)
    return np.clip(grey[..., None] + chroma[..., None] * axis, 0, 255).round().astype(np.uint8)


def test_stripes_of_two_colours_of_one_brightness_repeat():
    # SGM matches the colour line images: red and green stripes of one grey value mislead it
    # as grey stripes do (unseen seed 89's floor), and their grey values alone are plain
    rng = np.random.default_rng(2)
    rows, cols = 64, 400
    inner = (slice(4, -4), slice(4 * WINDOW_HALF, -4 * (WINDOW_HALF + LEVEL_SHIFTS)))
    flat = np.full((rows, cols), 120.0)
    stripes = _stripes(rows, cols, 9, rng, noise=0.0) - 128
    noise = rng.normal(0, 2.0, (rows, cols, 3))
    image = np.clip(_colour(flat, stripes) + noise, 0, 255).astype(np.uint8)
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    assert grey.std() < 3.0  # (the stripes are not in the grey values)
    assert (repeat_score(grey, 64)[inner] == -2).mean() > 0.95  # plain in grey
    assert (repeat_score(image, 64)[inner] >= REPEAT_ZNCC).mean() > 0.95
    # a random colour texture of one brightness does not repeat: its windows anchor their surface
    image = np.clip(_colour(flat, 4 * (_random_texture(rows, cols, rng) - 128)) + noise, 0, 255).astype(np.uint8)
    score = repeat_score(image, 64)[inner]
    assert (score >= REPEAT_ZNCC).mean() < 0.02 and (score > -2).all() and (score < ONCE_ZNCC).mean() > 0.8
    # the same noise alone, in colour, is plain (the chroma's own noise bound)
    image = np.clip(flat[..., None] + noise, 0, 255).astype(np.uint8)
    assert (repeat_score(image, 64) == -2).all()
    # grey stripes score the same in colour (no chroma to add)
    grey = np.clip(_stripes(rows, cols, 9, rng), 0, 255).round().astype(np.uint8)
    np.testing.assert_array_equal(repeat_score(np.repeat(grey[..., None], 3, axis=2), 64), repeat_score(grey, 64))


def test_a_striped_patch_alone_is_dropped_and_one_on_a_textured_surface_kept():
    rng = np.random.default_rng(1)
    rows, cols = 80, 400
    gray = _random_texture(rows, cols, rng)
    gray[:, 200:] = _stripes(rows, 200, 9, rng)  # right half: stripes
    disp = np.full((rows, cols), 20.0, np.float32)
    disp[:40, 200:] = 29.0  # the stripes' top half a period off, a surface of its own
    disp[:, 198:202] = -1.0  # (the jump between the halves: no cell joins them)
    disp[40:, 198:202] = 20.0  # the bottom half joined to the textured surface
    out = disp.copy()
    n = drop_repeating(out, repeat_score(gray, 64), -1.0)
    top, bottom = (slice(4, 36), slice(220, 360)), (slice(44, 76), slice(220, 360))
    assert (out[top] == -1.0).mean() > 0.95  # dropped: repeats, no texture of its own
    assert (out[bottom] == 20.0).all()  # kept: its surface is the random texture's
    assert (out[:, :190] == 20.0).all()
    assert n == np.count_nonzero((out == -1.0) & (disp != -1.0))
    # the same with no repeat within the search: nothing dropped
    out = disp.copy()
    assert drop_repeating(out, repeat_score(gray, 4), -1.0) == 0 and (out == disp).all()


def _strong_texture(rows, cols, rng):
    """A random texture of as much contrast as :func:`_stripes`' (80 grey levels' deviation)."""
    texture = _random_texture(rows, cols, rng)
    return 128 + (texture - 128) * (80 / texture.std())


def _stripes_beside_a_box():
    """Line image 1 of a textured box (columns 0-199, parallax 40) and stripes beside it
    matched a period off (200-259, parallax 29), no estimate beyond; and its repeat score."""
    rng = np.random.default_rng(2)
    rows, cols = 40, 400
    gray = _strong_texture(rows, cols, rng)
    gray[:, 200:] = _stripes(rows, 200, 9, rng)
    disp = np.full((rows, cols), -1.0, np.float32)
    disp[:, :200] = 40.0
    disp[:, 200:260] = 29.0
    return disp, repeat_score(gray, 64)


def test_a_striped_patch_is_not_anchored_by_the_texture_of_a_surface_beside_it():
    """A patch of stripes a period off beside a textured box: the windows of its cells near the
    box take in the box's texture and do not repeat, but the box is another surface (a depth
    jump between them), so they anchor nothing and the patch goes; the box stays."""
    disp, score = _stripes_beside_a_box()
    near_box = score[4:36, 200:200 + WINDOW_HALF]
    assert ((near_box > -2) & (near_box < ONCE_ZNCC)).mean() > 0.5  # (windows that take in the box's texture)
    out = disp.copy()
    drop_repeating(out, score, -1.0)
    assert (out[4:36, 215:250] == -1.0).mean() > 0.95
    assert (out[:, :200] == 40.0).all()


def test_windows_that_reach_cells_without_an_estimate_still_anchor_their_surface():
    """A narrow strip of the surface's own texture beside its stripes, unmatched cells all
    around (as SGM leaves them on a fragmented floor): its windows reach those cells, which
    hold no other surface, and anchor it; past image 1's frame they would not."""
    rng = np.random.default_rng(3)
    rows, cols = 40, 400
    gray = _strong_texture(rows, cols, rng)
    gray[:, 230:] = _stripes(rows, 170, 9, rng)
    disp = np.full((rows, cols), -1.0, np.float32)
    disp[:, 200:300] = 20.0  # 30 columns of texture, then 70 of stripes, one surface
    score = repeat_score(gray, 64)
    out = disp.copy()
    assert drop_repeating(out, score, -1.0) == 0 and (out == disp).all()
    # the same cells with image 1's frame ending 5 columns past the surface: the windows at
    # its right end reach beyond the image, the texture's at its left end still anchor it
    frame = np.tile(np.array([180, 305], np.int64), (rows, 1))
    out = disp.copy()
    assert drop_repeating(out, score, -1.0, frame) == 0
    # ...and with the frame starting where the texture does, nothing anchors it
    frame[:, 0] = 200 + 2 * WINDOW_HALF
    out = disp.copy()
    assert drop_repeating(out, score, -1.0, frame) > 0


def test_a_surface_mostly_of_stripes_and_unanchored_goes_whole():
    """The patch beside the box again: its cells whose windows take in the box's texture do
    not repeat, but the surface is mostly stripes and its own texture anchors none of it, so
    those cells go with it; a surface with a minority of repeating cells keeps the rest."""
    disp, score = _stripes_beside_a_box()
    assert ((score[4:36, 200:260] > -2) & (score[4:36, 200:260] < REPEAT_ZNCC)).any()  # (cells that do not repeat)
    out = disp.copy()
    drop_repeating(out, score, -1.0)
    assert (out[:, 200:260] == -1.0).all()
    assert (out[:, :200] == 40.0).all()
    # a plain surface with a strip of stripes: unanchored too, but mostly plain: its stripes go
    rng = np.random.default_rng(4)
    rows, cols = disp.shape
    gray = 128 + rng.normal(0, 0.5, (rows, cols))
    gray[:, 300:340] = _stripes(rows, 40, 9, rng)
    disp = np.full((rows, cols), -1.0, np.float32)
    disp[:, 150:340] = 29.0
    score = repeat_score(gray, 64)
    out = disp.copy()
    assert drop_repeating(out, score, -1.0) > 0
    repeats = (score >= REPEAT_ZNCC) & (disp > -1.0)
    assert repeats[:, 300:340].mean() > 0.3 and (out[repeats] == -1.0).all()
    assert (out[:, 150:280] == 29.0).all()
