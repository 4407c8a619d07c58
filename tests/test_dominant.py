"""Matches a period off the scene's largest planes moved onto them (matching/dominant.py), on known answers."""

import cv2
import numpy as np

from sefm_recon.matching.dominant import MOVE_PX, move_onto_dominant_planes
from tests.test_plane_align import F, H, TV, W, _texture

WALL = 12.0  # the wall's parallax, px (x2 = x1 - parallax)
PERIOD = 8  # the stripes' period along the lines, px
BOX = (slice(60, 180), slice(40, 110))  # rows, columns of a box in front of the wall
BOX_PARALLAX = 24.0


def _striped_wall(seed=0):
    """Stripes along the lines (40 grey levels, :data:`PERIOD` px) over faint clouds (6 levels,
    blotches about 12 px across): (H, W) float32."""
    xs = np.arange(W, dtype=np.float32)
    stripes = 40.0 * np.sin(2 * np.pi * xs / PERIOD)
    return _texture(seed, 6.0, blur=6.0) + stripes[None, :]


def _shifted(image, parallax):
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    return cv2.remap(image, xs + np.float32(parallax), ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def _uint8(image, seed):
    noisy = image + np.random.default_rng(seed).normal(size=image.shape)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def _scene(box: bool):
    """Image 1, image 2 and the true parallax of each pixel of image 1 (NaN: hidden in view 2)."""
    wall = _striped_wall()
    one, two = wall.copy(), _shifted(wall, WALL)
    parallax = np.full((H, W), WALL)
    if box:
        face = _texture(5, 3.0, blur=1.5) + 40.0
        one[BOX] = face[BOX]
        inside = np.zeros((H, W), np.float32)
        inside[BOX] = 1.0
        seen = _shifted(inside, BOX_PARALLAX) > 0.5  # image 2's pixels that show the box
        two = np.where(seen, _shifted(face, BOX_PARALLAX), two)
        parallax[BOX] = BOX_PARALLAX
        xs = np.arange(W)[None, :] - parallax
        hidden = (np.take_along_axis(seen, np.clip(np.rint(xs - 0.5), 0, W - 1).astype(int), axis=1)
                  & (parallax == WALL))
        parallax[hidden] = np.nan
    return _uint8(one, 1), _uint8(two, 2), parallax


def _matches(parallax, wrong, margin=24):
    """Every pixel's true match (COLMAP positions) but a period farther where ``wrong`` (H, W);
    and their points (camera 1's frame) and true parallax."""
    ys, xs = np.mgrid[margin:H - margin, margin:W - margin]
    ok = np.isfinite(parallax[ys, xs])
    ys, xs = ys[ok], xs[ok]
    d = parallax[ys, xs] + np.where(wrong[ys, xs], PERIOD, 0)
    uv1 = np.column_stack([xs + 0.5, ys + 0.5]).astype(np.float64)
    uv2 = uv1 - np.column_stack([d, np.zeros_like(d)])
    X = (F / d)[:, None] * (np.column_stack([uv1, np.ones(len(d))]) @ np.linalg.inv(TV.K1).T)
    return uv1, uv2, X, parallax[ys, xs]  # (unit baseline: z = F / parallax)


def _patch():
    wrong = np.zeros((H, W), bool)
    wrong[90:170, 170:270] = True
    return wrong


def test_a_striped_wall_matched_a_period_off_in_a_patch_moves_onto_its_aligned_plane():
    """Stripes 8 px apart along the lines over faint clouds: a patch of 8,000 matches a period off
    moves onto the wall's plane (within 0.1 px of the truth), and no right match moves."""
    one, two, parallax = _scene(box=False)
    wrong = _patch()
    uv1, uv2, X, truth = _matches(parallax, wrong)
    got = move_onto_dominant_planes(one, two, TV, uv1, uv2, X)
    bad = wrong[uv1[:, 1].astype(int), uv1[:, 0].astype(int)]
    assert got.planes >= 1
    assert set(got.moved) <= set(np.flatnonzero(bad))
    assert len(got.moved) >= 0.95 * bad.sum()
    expected = uv1[got.moved] - np.column_stack([truth[got.moved], np.zeros(len(got.moved))])
    assert np.abs(got.uv2 - expected).max() < 0.1
    assert np.allclose(got.xyz[:, 2], F / WALL, rtol=0.01)


def test_a_box_in_front_of_the_wall_keeps_its_matches():
    """The same wall with a box in front of it (its own texture, twice the wall's parallax): the
    box's right matches, over 3 px off the wall's plane, stay where they are, beside the moved
    patch."""
    one, two, parallax = _scene(box=True)
    wrong = _patch()
    uv1, uv2, X, truth = _matches(parallax, wrong)
    got = move_onto_dominant_planes(one, two, TV, uv1, uv2, X)
    on_box = np.zeros((H, W), bool)
    on_box[BOX] = True
    ij = uv1[:, 1].astype(int), uv1[:, 0].astype(int)
    assert np.abs(truth[on_box[ij]] - WALL).min() > MOVE_PX
    assert not on_box[ij][got.moved].any()
    assert len(got.moved) >= 0.9 * wrong[ij].sum()


def test_the_largest_planes_are_the_wall_then_the_box_each_with_its_own_matches():
    """The plane RANSAC under the pose finds the wall (most matches) and then the box's face, each
    within 1 px of its true matches: the wall's plane at the wall's depth, and every match of
    each on its own plane; a second surface's matches are never the first's."""
    from sefm_recon.matching.dominant import _largest_planes
    from sefm_recon.matching.planes import _pose

    _, _, parallax = _scene(box=True)
    uv1, uv2, X, truth = _matches(parallax, np.zeros((H, W), bool))
    planes = list(_largest_planes(_pose(TV), uv1, uv2, X[:, 2], np.random.default_rng(0)))
    assert len(planes) == 2
    (wall, on_wall), (box, on_box) = planes
    assert set(on_wall) == set(np.flatnonzero(truth == WALL))
    assert set(on_box) == set(np.flatnonzero(truth == BOX_PARALLAX))
    # 1 / z = a u + b v + c: fronto-parallel planes at z = F / parallax (unit baseline)
    assert np.allclose(wall, [0, 0, WALL / F], atol=1e-6)
    assert np.allclose(box, [0, 0, BOX_PARALLAX / F], atol=1e-6)


def test_without_a_plane_of_enough_matches_nothing_moves():
    """Too few matches for any plane: nothing is aligned or moved."""
    one, two, parallax = _scene(box=False)
    uv1, uv2, X, _ = _matches(parallax, _patch())
    got = move_onto_dominant_planes(one, two, TV, uv1[:5], uv2[:5], X[:5])
    assert got.planes == 0 and len(got.moved) == 0


def test_a_view_over_the_alignment_size_is_judged_reduced_and_moved_at_its_own_size(monkeypatch):
    """Judged on copies reduced to half (the alignment size set to 160 px for the test's 320 px),
    the patch a period off still moves, its partners from the plane in the full-size pixels."""
    from sefm_recon.matching import dominant

    monkeypatch.setattr(dominant, "ALIGN_SIDE", W // 2)
    one, two, parallax = _scene(box=False)
    wrong = _patch()
    uv1, uv2, X, truth = _matches(parallax, wrong)
    got = dominant.move_onto_dominant_planes(one, two, TV, uv1, uv2, X)
    bad = wrong[uv1[:, 1].astype(int), uv1[:, 0].astype(int)]
    assert set(got.moved) <= set(np.flatnonzero(bad))
    assert len(got.moved) >= 0.9 * bad.sum()
    expected = uv1[got.moved] - np.column_stack([truth[got.moved], np.zeros(len(got.moved))])
    assert np.abs(got.uv2 - expected).max() < 0.2


def test_reduced_pixels_are_each_matchs_pixel_and_the_first_match_in_each():
    """A match's pixel of an image reduced by 0.3 (its position scaled and truncated, clipped to
    the reduced image) and the first match in each pixel, in the pixels' order: numpy's
    ``unique`` of those pixels (its first indices)."""
    from sefm_recon.matching.dominant import _reduced_pixels

    rng = np.random.default_rng(3)
    uv1 = rng.uniform(0, 1, (5000, 2)) * [320.0, 240.0]
    uv1[0] = [319.99, 239.99]  # (scaled onto the reduced image's last pixel: clipped there)
    w, h = 96, 72
    pixel, first = _reduced_pixels(uv1, 0.3, w, h)
    xy = np.minimum((uv1 * 0.3).astype(np.int64), [w - 1, h - 1])
    assert np.array_equal(pixel, xy[:, 1] * w + xy[:, 0])
    assert np.array_equal(first, np.unique(pixel, return_index=True)[1])


def _as_candidates(uv1, uv2, X, region):
    """The matches split into the step's own (outside ``region`` (H, W) bool) and its
    candidates (inside), with the candidates' indices among all."""
    inside = region[uv1[:, 1].astype(int), uv1[:, 0].astype(int)]
    own, cand = np.flatnonzero(~inside), np.flatnonzero(inside)
    return (uv1[own], uv2[own], X[own]), (uv1[cand], uv2[cand], X[cand]), cand


def test_candidates_on_an_aligned_plane_are_given_back_and_those_a_period_off_moved_onto_it():
    """The wall's matches in a band are candidates (the repeat check's drops), a patch of them
    a period off: the step gives every candidate back on the wall, the right ones as they were
    and those a period off on the plane (within 0.1 px of the truth); the wall's own matches,
    all right, do not move."""
    one, two, parallax = _scene(box=False)
    wrong = _patch()
    uv1, uv2, X, truth = _matches(parallax, wrong)
    band = np.zeros((H, W), bool)
    band[70:190, :] = True
    own, cands, idx = _as_candidates(uv1, uv2, X, band)
    got = move_onto_dominant_planes(one, two, TV, *own, candidates=cands)
    assert got.planes >= 1 and len(got.moved) == 0
    assert len(got.restored) >= 0.95 * len(idx)
    expected = cands[0][got.restored] - np.column_stack([truth[idx][got.restored], np.zeros(len(got.restored))])
    assert np.abs(got.restored_uv2 - expected).max() < 0.1
    assert np.allclose(got.restored_xyz[:, 2], F / WALL, rtol=0.01)
    right = ~wrong[uv1[idx, 1].astype(int), uv1[idx, 0].astype(int)][got.restored]
    assert np.array_equal(got.restored_uv2[right], cands[1][got.restored][right])  # (as SGM left them)


def test_candidates_off_every_plane_found_among_the_matches_are_not_given_back():
    """The box's matches and a band of the wall's are candidates: the box, on no plane of the
    step's own matches (its plane is found among those alone), gets none back, the wall's band
    all of its own; with only candidates and five matches, no plane is found and none comes back."""
    one, two, parallax = _scene(box=True)
    uv1, uv2, X, truth = _matches(parallax, np.zeros((H, W), bool))
    on_box = np.zeros((H, W), bool)
    on_box[BOX] = True
    band = on_box.copy()
    band[:, 200:260] = True
    own, cands, idx = _as_candidates(uv1, uv2, X, band)
    got = move_onto_dominant_planes(one, two, TV, *own, candidates=cands)
    boxed = on_box[uv1[idx, 1].astype(int), uv1[idx, 0].astype(int)]
    assert not boxed[got.restored].any()
    assert np.count_nonzero(~boxed[got.restored]) >= 0.9 * np.count_nonzero(~boxed)
    few = tuple(a[:5] for a in own)
    none = move_onto_dominant_planes(one, two, TV, *few, candidates=cands)
    assert none.planes == 0 and len(none.restored) == 0
