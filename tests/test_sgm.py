"""Polar line images (matching/lines.py) and semi-global matching over them (matching/sgm.py)."""

import cv2
import numpy as np
import pytest

from sefm_recon.config import load_config
from sefm_recon.evaluate import covisibility_mask, evaluate_matches
from sefm_recon.geometry.epipolar import ray_angles
from sefm_recon.geometry.two_view import TwoView
from sefm_recon.matching.lines import COLUMN_SPACING_PX, ROW_SPACING_PX, line_grid, line_images, project, rays
from sefm_recon.matching.sgm import match_pair_sgm, parallax_columns
from sefm_recon.pipeline import reconstruct_pair

from .conftest import rot_y, two_view


@pytest.mark.parametrize("pose", ["lateral", "turned", "forward"])
def test_a_scene_point_lies_on_one_row_at_a_larger_angle_in_view_2(pose):
    R, t = {"lateral": (np.eye(3), [-1.0, 0, 0]),
            "turned": (rot_y(0.2), [-1.0, 0.1, 0.2]),
            "forward": (np.eye(3), [0.1, 0.0, -1.0])}[pose]
    tv = two_view(R, t)
    grid = line_grid(tv, (320, 240), (320, 240))
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.uniform(-2, 2, 200), rng.uniform(-1.5, 1.5, 200), rng.uniform(4, 12, 200)])
    X2 = X @ tv.R.T + tv.t
    phi1, a1 = ray_angles(tv.K1, np.eye(3), grid.basis, (X[:, :2] / X[:, 2:]) * 300 + [160, 120])
    phi2, a2 = ray_angles(tv.K2, tv.R.T, grid.basis, (X2[:, :2] / X2[:, 2:]) * 300 + [160, 120])
    dphi = np.angle(np.exp(1j * (phi2 - phi1)))
    assert np.abs(dphi).max() < 1e-9  # the same half-plane: the same row
    assert (a2 > a1).all()  # x2 = x1 - d with d > 0
    # back through the grid: a ray at (phi, alpha) projects onto the pixel it came from
    u, v, front = project(tv.K1, np.eye(3), rays(grid.basis, phi1, a1))
    assert front.all() and np.allclose(np.column_stack([u, v]), (X[:, :2] / X[:, 2:]) * 300 + [160, 120])
    # the parallax range for the points' distances holds their column differences
    d = grid.column(a1) - grid.column(a2)
    dist = np.linalg.norm(X, axis=1)
    lo, hi = parallax_columns(tv, grid, (320, 240), (dist.min(), dist.max()))
    assert lo - 1e-6 <= d.min() and d.max() <= hi + 1e-6


@pytest.mark.parametrize("R, t", [(rot_y(0.2), [-1.0, 0.1, 0.2]), (np.eye(3), [0.1, 0.0, -1.0])],
                         ids=["turned", "forward"])
def test_rows_are_at_most_the_row_spacing_apart_and_about_that_far(R, t):
    tv = two_view(R, t)
    grid = line_grid(tv, (320, 240), (320, 240))
    grid.pad = 0
    alpha = grid.alpha(np.arange(grid.columns))
    widest = np.zeros(len(grid.phi) - 1)  # each row's largest gap to the next, in either image
    for K, Rc in ((tv.K1, np.eye(3)), (tv.K2, tv.R.T)):
        u, v, _ = project(K, Rc, rays(grid.basis, grid.phi[:, None], alpha[None, :]))
        # between the outermost pixel centres, which are what the rows are read back at
        inside = (u >= 0.5) & (u <= 319.5) & (v >= 0.5) & (v <= 239.5)
        du, dv = np.diff(u, axis=0)[:, :-1], np.diff(v, axis=0)[:, :-1]  # to the next row
        tu, tv_ = np.diff(u, axis=1)[:-1], np.diff(v, axis=1)[:-1]  # along the row
        gap = np.abs(du * tv_ - dv * tu) / np.hypot(tu, tv_)  # distance between the lines
        both = (inside[1:] & inside[:-1])[:, :-1] & inside[:-1, 1:]
        assert gap[both].max() <= ROW_SPACING_PX + 1e-3
        widest = np.maximum(widest, np.where(both, gap, 0.0).max(axis=1))
    # no nearer than that needs: rows uniform in phi lie 0.6 px apart on average about the
    # forward motion's epipole, and a line near an image's corner is short (its far end
    # is not where the rows' spacing peaks), so a tenth of them may lie nearer
    seen = widest > 0
    assert np.percentile(widest[seen], 10) > 0.85 * ROW_SPACING_PX


def test_line_images_of_a_shifted_image_are_shifted_rows():
    import cv2

    tv = two_view(np.eye(3), [-1.0, 0, 0])
    rng = np.random.default_rng(1)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (240, 400)).astype(np.float32), (0, 0), 3.0)
    img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    img1, img2 = img[:, 40:360], img[:, 50:370]  # x2 = x1 - 10: disparity 10 px
    grid = line_grid(tv, (320, 240), (320, 240))
    grid.pad = 20
    L1, L2 = line_images(img1, img2, tv, grid, grid.pad + grid.columns + 20)
    r, c = len(grid.phi) // 2, grid.pad + grid.columns // 2  # near the image centre
    u1, v1, _ = project(tv.K1, np.eye(3), rays(grid.basis, grid.phi[r], grid.alpha(c)))
    un, _, _ = project(tv.K1, np.eye(3), rays(grid.basis, grid.phi[r], grid.alpha(c + 1)))
    assert 0.9 < abs(un - u1) < 1.1  # about 1 px a column (COLUMN_SPACING_PX)
    _, a2 = ray_angles(tv.K2, np.eye(3), grid.basis, np.array([[u1 - 10, v1]]))
    c2 = float(grid.column(a2)[0])
    assert abs((c - c2) * abs(un - u1) - 10) < 0.2  # 10 px in columns of that width
    # the same texture: interpolate row r of L2 at c2
    left = int(np.floor(c2))
    value2 = L2[r, left] * (left + 1 - c2) + L2[r, left + 1] * (c2 - left)
    assert abs(value2 - float(L1[r, c])) < 3
    assert abs(float(L2[r, left - 3]) - float(L1[r, c])) > abs(value2 - float(L1[r, c]))


def test_image_2s_spans_hold_only_its_own_pixels():
    """Forward motion: image 2's lines end at its border, inside the line image. Up to its
    edge the samples are its own (its outermost pixels repeated where the interpolation
    reaches beyond them: no 0 blended in), 0 beyond. A span holds the cells whose sample,
    and those of the cells within a window's rows and a cell along the row, lie between
    image 2's outermost pixel centres, and every such cell (rows beyond the line image's
    first and last do not count)."""
    from sefm_recon.matching.stereo_sgbm import BLOCK

    tv = two_view(np.eye(3), [0.0, 0.0, -1.0])
    grid = line_grid(tv, (320, 240), (320, 240))
    grid.pad, shift2 = 10, 5
    width = grid.pad + grid.columns + 10
    flat = np.full((240, 320), 200, np.uint8)
    u, v, front = project(tv.K2, tv.R.T, rays(grid.basis, grid.phi[:, None], grid.alpha(np.arange(width) - shift2)[None, :]))
    beyond = np.maximum.reduce([-u, u - 320, -v, v - 240])  # px beyond image 2's edge (COLMAP positions)
    half = BLOCK // 2

    def own_cells(tol):
        """the cells whose window lies between image 2's pixel centres, ``tol`` px inside them"""
        between = front & (u >= 0.5 + tol) & (u <= 319.5 - tol) & (v >= 0.5 + tol) & (v <= 239.5 - tol)
        padded = np.pad(between, ((half, half), (1, 1)), constant_values=True)
        own = np.ones_like(between)
        for dr in range(-half, half + 1):
            for dc in (-1, 0, 1):
                own &= padded[half + dr:half + dr + between.shape[0], 1 + dc:1 + dc + width]
        return own

    # a sample within float32's rounding of a pixel centre (the maps cv2.remap reads) may
    # fall either way
    surely, maybe = own_cells(1e-4), own_cells(-1e-4)
    for bicubic in (True, False):
        _, L2, span2, frames = line_images(flat, flat, tv, grid, width, shift2=shift2, bicubic=bicubic, spans=True,
                                           window=BLOCK, frames=True)
        assert (L2[front & (beyond <= 0.0)] == 200).all()
        assert (L2[~front | (beyond > 0.0)] == 0).all()
        # the frames: each row's first and last cell inside image 2 (its samples not 0)
        held = L2 > 0
        assert held.any(axis=1).all()
        assert (frames[1, :, 0] == held.argmax(axis=1)).all()
        assert (frames[1, :, 1] == width - 1 - held[:, ::-1].argmax(axis=1)).all()
        assert (frames[0] >= 0).all() and (frames[0, :, 1] > frames[0, :, 0]).all()
        inside = (np.arange(width)[None, :] >= span2[:, :1]) & (np.arange(width)[None, :] <= span2[:, 1:])
        assert inside.sum() > 0.5 * L2.size
        assert (inside >= surely).all() and (inside <= maybe).all() and (surely != maybe).sum() < 10


def test_a_scale_change_about_the_epipole_is_a_shift_of_columns():
    # forward motion: a point at angle alpha from the baseline moves to about s * alpha;
    # in columns that is the same shift log(s) / u_step wherever the point lies
    tv = two_view(np.eye(3), [0.0, 0.0, -1.0])
    grid = line_grid(tv, (320, 240), (320, 240))
    a1 = np.array([0.015, 0.05, 0.1, 0.2, 0.3])
    shift = grid.column(a1) - grid.column(1.5 * a1)
    assert np.allclose(shift, np.log(1.5) / grid.u_step, rtol=0.03)
    # columns and angles are each other's inverse (rays nearer the epipole than the edge aside)
    cols = grid.column(a1)
    assert np.allclose(grid.alpha(cols), a1) and grid.edge < a1.min()
    assert grid.column(grid.edge / 2) == pytest.approx(grid.column(grid.edge))


def _lateral_pair(corrupt_rows=None, plain=None, near=30):
    """A rectified 320x240 pair: a textured background 10 px of disparity behind a
    textured square at ``near`` px (30). Returns the images, the pose with its SIFT-like inliers,
    and the true disparity of every pixel of image 1 (NaN where occluded in image 2).
    ``plain`` (x0, x1): the background is plain (one grey and each image's own noise of
    a grey level) over image 1's columns x0 .. x1 - 1."""
    import cv2

    rng = np.random.default_rng(3)

    def texture(h, w):
        t = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 1.2)
        return cv2.normalize(t, None, 20, 235, cv2.NORM_MINMAX)

    w, h, a, b, y0, y1 = 320, 240, 150, 230, 60, 180  # the square: x in [a, b), y in [y0, y1) in image 1
    B, F = texture(h, w + max(40, near + 10)), texture(h, w + max(40, near + 10))
    x = np.arange(w)
    B2 = B  # the background at image 1's column x1 (image 2's x2 + 10)
    if plain is not None:
        B, B2 = B.copy(), B.copy()
        for img in (B, B2):
            img[:, plain[0]:plain[1]] = 128 + rng.normal(0, 1, (h, plain[1] - plain[0]))
    fg1 = np.zeros((h, w), bool)
    fg1[y0:y1, a:b] = True
    img1 = np.where(fg1, F[:, x], B[:, x])
    fg2 = np.zeros((h, w), bool)
    fg2[y0:y1, a - near:b - near] = True
    img2 = np.where(fg2, F[:, x + near], B2[:, x + 10])  # x2 = x1 - d
    if corrupt_rows is not None:
        img2[corrupt_rows] = rng.uniform(20, 235, img2[corrupt_rows].shape)
    d = np.where(fg1, float(near), 10.0)
    d[y0:y1, a - (near - 10):a] = np.nan  # background hidden behind the square in image 2
    d[:, :near] = np.where(fg1[:, :near], np.nan, d[:, :near])
    d[:, :10] = np.nan  # leaves image 2
    f = 300.0
    kx, ky = np.meshgrid(np.arange(20, 300, 10) + 0.5, np.arange(20, 220, 10) + 0.5)
    kp1 = np.column_stack([kx.ravel(), ky.ravel()])
    kd = d[ky.ravel().astype(int), kx.ravel().astype(int)]
    kp1, kd = kp1[np.isfinite(kd)], kd[np.isfinite(kd)]
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    tv = TwoView(K, K, np.eye(3), np.array([-1.0, 0, 0]), kp1, kp1 - np.column_stack([kd, 0 * kd]), len(kp1))
    to_rgb = lambda g: np.repeat(np.clip(g, 0, 255).astype(np.uint8)[..., None], 3, axis=2)
    return to_rgb(img1), to_rgb(img2), tv, d


def _disparity_errors(res, d_true):
    """Per match: the true disparity at its pixel, and its error (px)."""
    ij = np.floor(res.uv1).astype(int)
    truth = d_true[ij[:, 1], ij[:, 0]]
    return ij, truth, np.abs((res.uv1[:, 0] - res.uv2[:, 0]) - truth)


def test_sgm_leaves_occluded_pixels_unmatched():
    from sefm_recon.matching.sgm import match_pair_sgm

    img1, img2, tv, d = _lateral_pair()
    res = match_pair_sgm(img1, img2, tv, load_config(None, []))
    ij, truth, err = _disparity_errors(res, d)
    seen = np.isfinite(truth)
    assert np.mean(err[seen] < 1.0) > 0.95 and seen.sum() > 0.85 * np.isfinite(d).sum()
    # the 20 px strip hidden behind the square in image 2: most of it left without a match
    strip = ~np.isfinite(d[60:180, 130:150])
    assert strip.all()
    matched = np.zeros(d.shape, bool)
    matched[ij[:, 1], ij[:, 0]] = True
    assert matched[60:180, 130:150].mean() < 0.25


def _cells_a_check_drops(setting: str, *, extra=(), **pair):
    """On the lateral pair (``pair``: :func:`_lateral_pair`'s options), matched with the
    internal switch ``setting`` on and off: ``(at, wrong, kept, d)``, per match found
    with it off whether the check drops it and whether it is wrong (more than 1 px off,
    or hidden in image 2), the pixels matched with it on, and the true disparity."""
    from sefm_recon.matching.sgm import match_pair_sgm

    img1, img2, tv, d = _lateral_pair(**pair)
    found = {}
    for check in ("true", "false"):
        res = match_pair_sgm(img1, img2, tv, load_config(None, [f"{setting}={check}", *extra], internal=True))
        found[check] = {tuple(p) for p in np.floor(res.uv1).astype(int).tolist()}, res
    gone = found["false"][0] - found["true"][0]
    ij, truth, err = _disparity_errors(found["false"][1], d)
    at = np.array([tuple(p) in gone for p in ij.tolist()])
    return at, ~np.isfinite(truth) | (err > 1.0), found["true"][0], d


def test_the_cells_dropped_at_depth_edges_are_wrong_far_more_often_than_the_rest():
    """On the lateral pair, the square (30 px) in front of its background (10 px): the cells
    dropped at its edges, fattened by the windows to the square's depth or hidden in image 2,
    are wrong far more often than the matches overall (measured: 278 cells, 25 % wrong
    against 0.55 %)."""
    at, wrong, _, _ = _cells_a_check_drops("sgm.edge_check")
    assert 100 < at.sum() < 0.01 * len(at)  # about a cell a row at each edge of the square
    assert wrong[at].mean() > 5 * wrong.mean()


def test_the_left_right_check_drops_estimates_that_sgm_from_image_2_contradicts():
    # image 2's line image is image 1's shifted by 12 columns: every cell's parallax is 12;
    # a block of cells is given 30 instead (a surface matched onto the wrong texture), and
    # SGM from image 2 (at half size) finds each of their partners matched at 12
    import cv2

    from sefm_recon.matching.sgm import drop_left_right, halve_line_images

    rng = np.random.default_rng(4)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (64, 300, 3)).astype(np.float32), (0, 0), 1.5)
    tex = cv2.normalize(tex, None, 20, 235, cv2.NORM_MINMAX).astype(np.uint8)
    L1, L2 = np.ascontiguousarray(tex[:, :256]), np.ascontiguousarray(tex[:, 12:268])
    disp = np.full((64, 256), -1.0, np.float32)
    disp[:, 60:240] = 12.0
    disp[20:40, 120:150] = 30.0
    wrong = disp == 30.0
    right = disp == 12.0
    n = drop_left_right(disp, halve_line_images(L1, L2), 0, 48, 32, True, -1.0)
    assert n == np.count_nonzero(disp[wrong | right] == -1.0)
    assert np.all(disp[wrong] == -1.0)
    assert np.count_nonzero(disp[right] == 12.0) > 0.99 * right.sum()


def test_the_left_right_checks_drops_kept_for_the_planes_are_those_on_stripes():
    """Of the estimates the left-right check dropped, those on texture repeating along the
    lines (where its half-size SGM can go a period off) are kept for the dominant planes to
    judge; those on texture that does not repeat stay dropped, and none kept is None."""
    from sefm_recon.matching.periodic import repeat_score
    from sefm_recon.matching.sgm import repeating_drops

    rng = np.random.default_rng(4)
    cols = np.arange(256)
    stripes = 128 + 60 * np.sin(2 * np.pi * cols / 8.0) + rng.normal(0, 2, (64, 256))
    noise = cv2.GaussianBlur(rng.uniform(0, 255, (64, 256)).astype(np.float32), (0, 0), 1.5)
    noise = cv2.normalize(noise, None, 20, 235, cv2.NORM_MINMAX)
    image = np.clip(np.where(cols < 128, stripes, noise), 0, 255).astype(np.uint8)
    repeat = repeat_score(image, 48)
    drops = np.full((64, 256), -1.0, np.float32)
    drops[20:40, 30:100] = 12.0  # on the stripes
    drops[20:40, 160:230] = 30.0  # on the texture beside them
    kept = repeating_drops(drops.copy(), repeat, -1.0)
    assert np.mean(kept[20:40, 30:100] == 12.0) > 0.95
    assert np.all(kept[:, 128:] == -1.0) and np.all(kept[drops == -1.0] == -1.0)
    only_texture = np.where(cols[None, :] >= 128, drops, np.float32(-1.0))
    assert repeating_drops(only_texture, repeat, -1.0) is None
    assert repeating_drops(drops.copy(), None, -1.0) is None


def test_a_cell_beside_a_nearer_surface_fattened_over_its_partner_is_not_contradicted():
    """The second SGM's window fattens a nearer surface (parallax 15) over the farther (6) by
    up to half a block (2 reduced cells): an estimate of 6 whose partner's two cells hold 15
    stays where, walking over the 15s, a cell at most 2 beyond holds 6; not where the run
    of 15s is longer, nor where the cells hold a farther parallax than the estimate's, nor
    across a run that is no one surface."""
    from sefm_recon.matching.sgm import _beyond_fattening

    row = np.array([6.0] * 10 + [15.0] * 10, np.float32)
    assert _beyond_fattening(row, 10, 6.0, 1.0, 2)  # cells 10, 11 hold 15; cell 9 holds 6
    assert _beyond_fattening(row, 11, 6.0, 1.0, 2)  # cell 9 is 2 beyond cell 11
    assert not _beyond_fattening(row, 12, 6.0, 1.0, 2)  # three cells of 15 to cross
    assert not _beyond_fattening(row[::-1].copy(), 8, 15.0, 1.0, 2)  # a farther surface's cells
    noisy = np.array([6.0] * 10 + [15.0, 25.0] + [15.0] * 8, np.float32)
    assert not _beyond_fattening(noisy, 11, 6.0, 1.0, 2)  # 25 after 15: no one surface
    assert not _beyond_fattening(row, 10, 6.0, 1.0, 0)


def test_the_left_right_check_keeps_a_textured_cell_beside_a_fattened_nearer_surface():
    """The textured lateral pair: SGM from image 2, given (here, by hand) the nearer parallax
    over two reduced cells beside the partners of a band of right estimates, contradicts
    them; judged as textured they stay, as plain they are dropped."""
    from sefm_recon.matching import sgm

    disp0 = np.full((8, 64), 6.0, np.float32)
    back = np.full((4, 32), 3.0, np.float32)  # the estimates' own parallax at half size (6 / 2)
    back[:, 10:12] = 7.5  # a nearer surface (15 full-size columns) fattened over two cells
    # a cell x of parallax 6 has its partner at (x - 6 + 0.5) / 2 - 0.5 in the reduced row:
    # between cells 10 and 11 for x = 27
    drops = {}
    for textured in (True, False):
        disp = disp0.copy()
        sgm._drop_left_right(disp, back, 0.0, -1.0, 2.0, 1.0, np.full(disp.shape, textured), 2)
        drops[textured] = disp == -1.0
    assert drops[False][:, 27].all()
    assert not drops[True].any()


def _low_contrast_pair(rng, pattern, shift=12, noise=2.0):
    """Line images 64 x 256 (3 equal channels) of ``pattern`` (64 x 300 float, grey levels
    about 128) with sensor noise of ``noise`` levels drawn apart for each, image 2's shifted
    by ``shift`` columns: every cell's parallax is ``shift``."""
    def view(x0):
        grey = pattern[:, x0:x0 + 256] + rng.normal(0, noise, (64, 256))
        return np.ascontiguousarray(np.repeat(np.clip(grey, 0, 255).astype(np.uint8)[..., None], 3, axis=2))

    return view(0), view(shift)


def test_the_half_size_fill_matches_a_texture_of_low_contrast():
    # clouds of 4 grey levels under noise of 3: SGM at full size puts one cell in five more
    # than a column off (measured 81 % within it); at half size, its windows see twice the
    # texture and half the noise, and what it fills is right (measured 73 % filled, all right)
    import cv2

    from sefm_recon.matching.sgm import fill_from_half_size, half_size_sgm, halve_line_images
    from sefm_recon.matching.stereo_sgbm import sgbm_disparity

    rng = np.random.default_rng(5)
    clouds = cv2.GaussianBlur(rng.normal(0, 1, (64, 300)), (0, 0), 3.0)
    L1, L2 = _low_contrast_pair(rng, 128 + 4 * clouds / clouds.std(), noise=3.0)
    full, _ = sgbm_disparity(L1, L2, 0, 48, 10)
    assert np.mean(np.abs(full[:, 60:][full[:, 60:] >= 0] - 12.0) <= 1.0) < 0.9
    disp = np.full((64, 256), -1.0, np.float32)
    disp[:, :60] = 12.0  # cells with an estimate keep it
    halves = halve_line_images(L1, L2)
    n = fill_from_half_size(disp, halves, half_size_sgm(halves, 48, 32, True, 10, True), 0, -1.0)
    filled = disp[:, 60:] > -1.0
    assert n == filled.sum()
    assert filled[4:-4, 60:-4].mean() > 0.6  # (the first columns' partners lie beyond image 2)
    assert np.mean(np.abs(disp[:, 60:][filled] - 12.0) <= 1.0) > 0.99
    assert np.all(disp[:, :60] == 12.0)


def test_the_half_size_fill_leaves_a_shaded_plain_surface():
    # a ramp along the lines (shading) under noise of 2 levels: SGM at half size puts some
    # parallax on it, but the derivatives' correlation is the noise's, and nothing is filled
    # (measured: none; without the correlation test, 36 % of the cells)
    from sefm_recon.matching.sgm import fill_from_half_size, half_size_sgm, halve_line_images

    rng = np.random.default_rng(6)
    ramp = np.tile(np.linspace(90, 170, 300), (64, 1))
    L1, L2 = _low_contrast_pair(rng, ramp)
    disp = np.full((64, 256), -1.0, np.float32)
    halves = halve_line_images(L1, L2)
    n = fill_from_half_size(disp, halves, half_size_sgm(halves, 48, 32, True, 10, True), 0, -1.0)
    assert n == np.count_nonzero(disp > -1.0) < 0.01 * disp.size


def test_the_half_size_check_drops_an_estimate_on_another_surface_and_keeps_the_near_ones():
    # clouds of 20 grey levels under noise of 1, every cell's parallax 12: SGM at half size
    # is sure of them (measured 73 % of the reduced cells estimated, all within half a
    # reduced column); a block of full-size estimates at 20 is dropped, those at 12 and 13.5
    # (within the check's 3 columns) stay, with image 2's line image shifted or not
    import cv2

    from sefm_recon.matching.sgm import drop_off_half_size, half_size_sgm, halve_line_images

    rng = np.random.default_rng(7)
    clouds = cv2.GaussianBlur(rng.normal(0, 1, (64, 300)), (0, 0), 2.0)
    L1, L2 = _low_contrast_pair(rng, 128 + 20 * clouds / clouds.std(), noise=1.0)
    half = half_size_sgm(halve_line_images(L1, L2), 48, 32, True, 10, True)
    assert np.mean(np.abs(half[half >= 0] - 6.0) <= 0.5) > 0.99
    disp = np.full((64, 256), 12.0, np.float32)
    disp[:, :60] = -1.0  # (the first columns' partners lie beyond image 2)
    disp[20:40, 100:140] = 20.0
    disp[40:50, 150:200] = 13.5
    for shift in (0, 5):  # image 2's line image shifted by 5 columns: every parallax 5 more
        d = np.where(disp >= 0, disp + shift, shift - 1.0).astype(np.float32)
        n = drop_off_half_size(d, half, shift, shift - 1.0)
        dropped = d < shift
        assert n == 20 * 40 == np.count_nonzero(dropped[:, 60:])
        assert dropped[20:40, 100:140].all()


def test_the_cells_the_left_right_check_drops_are_wrong_far_more_often():
    """On the lateral pair: the cells that SGM from image 2 contradicts are wrong (more than
    1 px off, or hidden in image 2) far more often than the matches overall (measured: 82
    cells, 21 % wrong against 0.27 %; 93 and 30 % before the cells beyond a fattened nearer
    surface were kept: the 11 kept here are the hidden strip's first columns, whose partners
    lie within two reduced cells inside the square in image 2)."""
    at, wrong, _, _ = _cells_a_check_drops("sgm.lr_check")
    assert 20 < at.sum() < 0.01 * len(at)
    assert wrong[at].mean() > 5 * wrong.mean()


def test_the_cells_dropped_where_two_surfaces_reach_one_pixel_are_wrong_far_more_often():
    """On the lateral pair (the square at 30 px in front of its background at 10 px), with
    the other depth-edge step off: the cells the collision test drops are wrong (more than
    1 px off, or hidden in image 2) far more often than the matches overall (measured: 191
    cells, 95 % wrong against 0.55 %)."""
    at, wrong, _, _ = _cells_a_check_drops("sgm.collision_check", extra=["sgm.edge_check=false"])
    assert 20 < at.sum() < 0.01 * len(at)
    assert wrong[at].mean() > 5 * wrong.mean()


def test_the_plain_cells_carried_across_a_jump_are_wrong_far_more_often():
    """On the lateral pair with its background plain over image 1's columns 70 .. 149: the
    cells the check drops are wrong (more than 1 px off, or hidden in image 2) several times
    as often as the matches overall (measured: 457 cells, 13 % wrong against 2.6 %; the rest
    are the plain background's own cells where a wrong farther estimate inside the plain
    band made the jump: on the real pairs 83-86 % of the cells it drops are more than 3 px
    off). The median about each window's plane is off: it runs after the check, and beside
    the holes the check leaves it moves plain cells that the plane fill then gives or takes,
    so the pixels found with and without the check differ by more than its own drops
    (measured with it on: 764 cells, 7.7 % wrong against 2.7 %; the check still takes 106
    wrong matches and 159 right ones from the total, against 94 and 276 with it off)."""
    at, wrong, _, _ = _cells_a_check_drops("sgm.carried_check", plain=(70, 150), extra=("sgm.slanted_median=false",))
    assert at.sum() > 50
    assert wrong[at].mean() > 3 * wrong.mean()


def test_the_plain_cells_dropped_beside_an_occlusion_are_wrong_far_more_often():
    """On the lateral pair with its background plain over image 1's columns 70 .. 149 (the
    20 px strip hidden behind the square in image 2 among them): the cells the occlusion
    check drops are wrong (more than 1 px off, or hidden in image 2) far more often than
    the matches overall, and most of the hidden strip is left unmatched. Without the
    half-size fill and check, which leave the check less to drop (measured with the fill:
    240 cells, 11 % wrong against 2.5 %; with the check alone, 468); measured without: 400
    cells, 39 % wrong against 2.7 % (572 and 27 % while the plain regions' planes were
    homographies), the strip 23 % matched with the check."""
    at, wrong, kept, d = _cells_a_check_drops("sgm.occlusion_check", plain=(70, 150),
                                              extra=("sgm.half_fill=false", "sgm.half_check=false"))
    assert at.sum() > 300
    assert wrong[at].mean() > 5 * wrong.mean()
    strip = np.zeros(d.shape, bool)
    ij_kept = np.array(sorted(kept))
    strip[ij_kept[:, 1], ij_kept[:, 0]] = True
    assert strip[60:180, 130:150].mean() < 0.5


def _island(side: int):
    """Line images 400 x 700 of one texture at 20 columns of parallax, with a ``side`` x ``side``
    patch in front at 40; the patch's interior (2 px in from its edges)."""
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur((rng.random((400, 764, 3)) * 255).astype(np.uint8), (3, 3), 0.7)
    L1 = np.ascontiguousarray(texture[:, :700])
    L2 = np.ascontiguousarray(texture[:, 20:720])  # x2 = x1 - 20
    L2[150:150 + side, 260:260 + side] = L1[150:150 + side, 300:300 + side]  # x2 = x1 - 40
    return L1, L2, (slice(152, 148 + side), slice(302, 298 + side))


def test_the_speckle_filter_drops_islands_under_a_share_of_the_view(monkeypatch):
    # SGM finds a 30 px patch in front as an island of 320 cells and a 48 px one as 1395
    # (its edges fatten into the background or drop). The window over 254,400 estimated cells
    # is 508: the first is dropped, the second kept; the 100 cells alone keep both.
    from sefm_recon.matching import stereo_sgbm as sgm

    assert sgm.speckle_window(400, 700, 64) == 508 and sgm.speckle_window(100, 164, 64) == sgm.SPECKLE_WINDOW
    for side, kept in ((30, False), (48, True)):
        L1, L2, patch = _island(side)
        d, _ = sgm.sgbm_disparity(L1, L2, 0, 64, 10)
        assert np.mean(np.abs(d[50:120, 100:600] - 20) < 1) > 0.99  # the background stays
        found = np.mean(np.abs(d[patch] - 40) < 1)
        assert found > 0.5 if kept else found < 0.05
    monkeypatch.setattr(sgm, "SPECKLE_SHARE", 0.0)
    L1, L2, patch = _island(30)
    d, _ = sgm.sgbm_disparity(L1, L2, 0, 64, 10)
    assert np.mean(np.abs(d[patch] - 40) < 1) > 0.3


def test_four_paths_run_over_strips_of_rows_where_their_volume_does_not_fit(monkeypatch):
    # the island scenes with a budget of 81 rows: strips of 17 rows kept (32 more above and
    # below), 24 of them. The four paths still run, the estimates are those of the whole run
    # (measured: 99.98 % within a column, the island found on 38 % and 64 % of its cells both
    # ways) and the speckle filter judges an island whole across the strips it spans (30 px:
    # 3 strips): the 30 px island dropped and the 48 px one kept, as in one run.
    from sefm_recon.matching import stereo_sgbm as sgm

    for side, kept in ((30, False), (48, True)):
        L1, L2, patch = _island(side)
        whole, full = sgm.sgbm_disparity(L1, L2, 0, 64, 10, speckle=False)
        assert full
        monkeypatch.setattr(sgm, "MAX_FULL_VOLUME", (17 + 2 * sgm.STRIP_MARGIN) * L1.shape[1] * 64)
        assert sgm.strip_rows(L1.shape[1], 64) == 17
        striped, full = sgm.sgbm_disparity(L1, L2, 0, 64, 10, speckle=False)
        assert full
        both = (whole >= 0) & (striped >= 0)
        assert both.mean() > 0.85 and np.mean(np.abs(whole - striped)[both] <= 1) > 0.99
        found = np.mean(np.abs(striped[patch] - 40) < 1)
        assert found > 0.3 and abs(found - np.mean(np.abs(whole[patch] - 40) < 1)) < 0.02
        d, _ = sgm.sgbm_disparity(L1, L2, 0, 64, 10)
        assert np.mean(np.abs(d[50:120, 100:600] - 20) < 1) > 0.99
        assert np.mean(np.abs(d[patch] - 40) < 1) > 0.3 if kept else np.all(d[patch] < 39)
        monkeypatch.undo()
    # a budget under the margins' rows: OpenCV's 3 directions
    monkeypatch.setattr(sgm, "MAX_FULL_VOLUME", 2 * sgm.STRIP_MARGIN * L1.shape[1] * 64)
    assert sgm.strip_rows(L1.shape[1], 64) == 0 and not sgm.four_paths_fit(L1, 64)
    assert not sgm.sgbm_disparity(L1, L2, 0, 64, 10)[1]


@pytest.mark.parametrize("bad_rows, within_px", [(slice(119, 122), 1.0), (slice(117, 124), 3.0)])
def test_sgm_aggregation_across_lines_repairs_lines_without_signal(bad_rows, within_px):
    # rows of image 2 replaced by noise: on these lines alone no matcher finds the
    # partners (with 7 rows, a window of 5 on the middle ones is all noise); the paths
    # from the lines above and below carry the right disparity across them. Measured: 96 %
    # of the 3 rows matched, all within 1 px; 58 % of the 7 rows' middle three, 99 % within
    # 3 px and 95 % within 1 px (the left-right check drops some of the estimates that image
    # 2's noise cannot confirm: without it 61 %, 97 % and 89 %).
    from sefm_recon.matching.sgm import match_pair_sgm

    img1, img2, tv, d = _lateral_pair(corrupt_rows=bad_rows)
    res = match_pair_sgm(img1, img2, tv, load_config(None, []))
    ij, truth, err = _disparity_errors(res, d)
    on = (ij[:, 1] >= 119) & (ij[:, 1] <= 121) & np.isfinite(truth)
    assert on.sum() > 0.5 * np.isfinite(d[119:122]).sum()  # most of the bad lines are matched
    assert np.mean(err[on] < within_px) > 0.95  # and matched right


def test_sgm_matches_a_slanted_floor_along_the_edge_of_the_line_images():
    # A rectified pair: a plane at 10 px of disparity above a floor in the last 16 rows
    # whose disparity grows by 1 px a row. At the edge of the line images, paths across
    # the lines arrive only from the plane; with the diagonals too (OpenCV's 8 paths)
    # they outvote the paths along the lines. Measured: 77 % of the floor matched and
    # 65 % of that within 1 px with 8 paths; 96 % and 80 % with the four full paths. (The
    # left-right check is off: at half size a row averages two lines, a column of parallax
    # apart on this floor, and keeps 78 % of it; at half a column a line, every match.)
    import cv2

    from sefm_recon.matching.sgm import match_pair_sgm

    rng = np.random.default_rng(5)
    w, h, s = 320, 240, 16
    T = cv2.GaussianBlur(rng.uniform(0, 255, (h, w + 40)).astype(np.float32), (0, 0), 1.2)
    T = cv2.normalize(T, None, 20, 235, cv2.NORM_MINMAX)
    d = np.full(h, 10.0)
    d[h - s:] = 10 + np.arange(1, s + 1)
    x = np.arange(w)
    img2 = np.stack([T[y, x + int(d[y])] for y in range(h)])  # x2 = x1 - d
    kx, ky = np.meshgrid(np.arange(20, 300, 10) + 0.5, np.arange(20, 240, 10) + 0.5)
    kp1 = np.column_stack([kx.ravel(), ky.ravel()])
    kd = d[ky.ravel().astype(int)]
    tv = two_view(np.eye(3), [-1.0, 0, 0])
    tv.kp1, tv.kp2 = kp1, kp1 - np.column_stack([kd, 0 * kd])
    to_rgb = lambda g: np.repeat(np.clip(g, 0, 255).astype(np.uint8)[..., None], 3, axis=2)
    res = match_pair_sgm(to_rgb(T[:, x]), to_rgb(img2), tv, load_config(None, ["sgm.lr_check=false"], internal=True))
    ij = np.floor(res.uv1).astype(int)
    err = np.abs(res.uv1[:, 0] - res.uv2[:, 0] - d[ij[:, 1]])
    floor = (ij[:, 1] >= h - s) & (ij[:, 0] >= 40)  # left of x = 40 some pixels leave image 2
    assert floor.sum() > 0.9 * s * (w - 40)
    assert np.mean(err[floor] < 1.0) > 0.75


def _scene_pose(scene):
    v1, v2 = scene.views
    R = v2.R @ v1.R.T
    return v1, v2, (R, v2.t - R @ v1.t)


def test_sgm_matches_a_rendered_pair(small_scene):
    v1, v2, pose = _scene_pose(small_scene)
    cfg = load_config(None, ["output.mesh=false", "dense.method=sgm"])
    res = reconstruct_pair(v1.image, v2.image, v1.camera(1), v2.camera(2), cfg, pose=pose)
    m = evaluate_matches(res.uv1, res.uv2, v1, v2)
    assert m["precision@1"] > 0.9 and m["coverage@1"] > 0.8
    assert res.counts["valid_matches"] == len(res.uv1) and res.counts["rough_matches"] == 0


def test_sgm_cost_survives_a_gain_and_offset_change(small_scene):
    v1, v2, pose = _scene_pose(small_scene)
    cfg = load_config(None, ["output.mesh=false", "dense.method=sgm"])
    cov = covisibility_mask(v1, v2)
    brighter = (v2.image.astype(np.float32) * 0.75 + 20).astype(np.uint8)  # an exposure change, no saturation
    base, changed = (evaluate_matches(r.uv1, r.uv2, v1, v2, covisible=cov) for r in (
        reconstruct_pair(v1.image, img, v1.camera(1), v2.camera(2), cfg, pose=pose) for img in (v2.image, brighter)))
    assert changed["precision@1"] > base["precision@1"] - 0.02
    assert changed["coverage@1"] > base["coverage@1"] - 0.03


def test_sgm_matches_forward_motion_where_no_planar_rectification_exists():
    from sefm_recon.baselines import epipoles_inside
    from sefm_recon.synthetic import render_scene

    scene = render_scene(seed=2, width=320, height=240, motion="forward")
    v1, v2, pose = _scene_pose(scene)
    assert epipoles_inside(v1.K, v1.R, v1.t, v2.K, v2.R, v2.t, (320, 240), (320, 240))
    cfg = load_config(None, ["output.mesh=false", "dense.method=sgm"])
    res = reconstruct_pair(v1.image, v2.image, v1.camera(1), v2.camera(2), cfg, pose=pose)
    m = evaluate_matches(res.uv1, res.uv2, v1, v2)
    assert m["precision@3"] > 0.65 and m["coverage@3"] > 0.6  # measured 0.73 / 0.70 (one match a pixel)


def test_sgm_drops_estimates_at_the_edge_of_its_search():
    # A smooth texture shifted by 10 px, while the SIFT inliers say 34 px: the search
    # starts at about 12 px, the true parallax lies below it, the cost falls all the way
    # to the search's first column, and OpenCV reports that edge as the disparity. Those
    # estimates are not minima found and are dropped. Measured: 72,550 matches within
    # 2 px of the edge without the check, none with it.
    import cv2

    from sefm_recon.matching.sgm import match_pair_sgm, search_range

    rng = np.random.default_rng(5)
    w, h = 320, 240
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (h, w + 40)).astype(np.float32), (0, 0), 12)
    tex = cv2.normalize(tex, None, 20, 235, cv2.NORM_MINMAX)
    to_rgb = lambda g: np.repeat(np.clip(g, 0, 255).astype(np.uint8)[..., None], 3, axis=2)
    x = np.arange(w)
    img1, img2 = to_rgb(tex[:, x + 20]), to_rgb(tex[:, x + 30])  # x2 = x1 - 10
    kx, ky = np.meshgrid(np.arange(40, 300, 20) + 0.5, np.arange(20, 220, 20) + 0.5)
    kp1 = np.column_stack([kx.ravel(), ky.ravel()])
    base = two_view(np.eye(3), [-1.0, 0, 0])
    tv = TwoView(base.K1, base.K2, base.R, base.t, kp1, kp1 - [34.0, 0], len(kp1))
    lo, _ = search_range(tv, line_grid(tv, (w, h), (w, h)), (w, h))
    assert lo > 11  # the truth (10 px, about 10 columns) lies below the search
    found = {}
    for check in (False, True):
        res = match_pair_sgm(img1, img2, tv, load_config(None, [f"sgm.end_check={str(check).lower()}"], internal=True))
        found[check] = res.uv1[:, 0] - res.uv2[:, 0]
    edge = found[False]
    assert len(edge) > 0.6 * w * h and np.percentile(edge, 95) < lo + 3  # at the edge, not at 10 px
    assert len(found[True]) < 0.05 * len(edge)


def test_sgm_drops_estimates_on_windows_without_signal():
    # A textured plane 10 px of disparity away with a clipped black patch on it (a
    # black object in front of a black background looks the same): inside the patch
    # every disparity costs alike, and the aggregation paths carry the plane's depth
    # in. Those estimates come from the surroundings, not from the patch.
    from sefm_recon.matching.sgm import match_pair_sgm

    img1, img2, tv, d = _lateral_pair()
    img1, img2 = img1.copy(), img2.copy()
    img1[80:160, 60:140] = 0
    img2[80:160, 50:130] = 0  # the patch on the background, at its 10 px
    inside = {}
    for check in (False, True):
        res = match_pair_sgm(img1, img2, tv, load_config(None, [f"sgm.flat_check={str(check).lower()}"], internal=True))
        u, v = res.uv1[:, 0], res.uv1[:, 1]
        # more than half a window (2 px) inside the patch, away from its edges' signal
        inside[check] = np.count_nonzero((u > 63) & (u < 137) & (v > 83) & (v < 157))
        assert len(res.uv1) > 0.7 * 320 * 240
    assert inside[False] > 0.5 * 74 * 74  # without the check, the paths fill most of it
    assert inside[True] == 0


def test_a_coarse_pass_bounds_the_search_where_sift_gives_no_range():
    # No SIFT inliers: the search would span every parallax from a fifth of the
    # baseline to infinity (hundreds of columns here). The coarse pass at half size finds
    # the two surfaces (10 and 30 px) and the search spans them.
    from sefm_recon.matching.sgm import MARGIN_COLUMNS, coarse_range, match_pair_sgm, search_range

    img1, img2, tv, d = _lateral_pair()
    bare = TwoView(tv.K1, tv.K2, tv.R, tv.t)
    cfg = load_config(None, [])
    grid = line_grid(bare, (320, 240), (320, 240))
    lo, hi = search_range(bare, grid, (320, 240))
    assert hi - lo > 500
    found = coarse_range(img1, img2, bare, grid, cfg, lo, hi)
    near, far = 30 / COLUMN_SPACING_PX, 10 / COLUMN_SPACING_PX  # the surfaces in columns (at the centre)
    # within the margin the search adds to it (MARGIN_COLUMNS): a little short at the 99.5th percentile
    assert found is not None and found[0] < far and found[1] + MARGIN_COLUMNS > near and found[1] - found[0] < 60
    res = match_pair_sgm(img1, img2, bare, cfg)
    ij, truth, err = _disparity_errors(res, d)
    seen = np.isfinite(truth)
    assert np.mean(err[seen] < 1.0) > 0.95 and seen.sum() > 0.85 * np.isfinite(d).sum()


def test_the_near_extension_follows_a_surface_without_gaps_and_stops_at_one():
    from sefm_recon.matching.sgm import MARGIN_COLUMNS, CoarseParallax, extend_near

    step = 4.0  # full-size columns per coarse column
    surface = np.arange(100.0, 141.0, step)  # a floor coming nearer: 100 .. 140 without a gap
    stray = np.array([140.0 + MARGIN_COLUMNS + step + 1, 300.0])  # apart from it: a wrong match
    plain = np.array([150.0])  # within reach, but on a plain window: not evidence
    p = np.concatenate([surface, stray, plain, [20.0, 60.0]])  # and the far side, never followed
    textured = np.ones(len(p), bool)
    textured[len(surface) + len(stray)] = False
    found = CoarseParallax(p[None, :].astype(np.float32), textured[None, :], step)
    assert extend_near(96.0, found) == 140.0
    assert extend_near(100.0 - MARGIN_COLUMNS - step - 0.5, found) == 100.0 - MARGIN_COLUMNS - step - 0.5
    assert extend_near(200.0, found) == 200.0  # the one estimate beyond lies 100 columns off


def test_the_near_extension_follows_the_plain_cells_of_a_textured_surface_but_not_a_plain_one():
    from sefm_recon.matching.sgm import CoarseParallax, extend_near

    step = 2.0
    p = np.full((3, 11), np.nan, np.float32)
    p[0] = np.arange(50.0, 71.0, step)  # a weakly textured surface coming nearer: 50 .. 70
    p[2] = np.arange(92.0, 71.0, -step)  # a plain one beyond it, 72 under 70, not joined (row 1 holds nothing)
    textured = np.zeros(p.shape, bool)
    textured[0, [0, -1]] = True  # the first surface's texture at its two ends alone, 20 columns apart
    found = CoarseParallax(p, textured, step)
    assert extend_near(48.0, found) == 70.0
    textured[0, -1] = False  # a textured cell at 50 still vouches for its surface up to 70
    assert extend_near(48.0, found) == 70.0
    textured[0, 0] = False  # no textured cell left: no surface to follow
    assert extend_near(48.0, found) == 48.0
    p[1, -1] = 71.0  # the plain surface joined to the textured one through a neighbour within one coarse column
    textured[0, 0] = True
    assert extend_near(48.0, CoarseParallax(p, textured, step)) == 92.0


def test_estimates_at_the_near_end_stay_only_where_the_coarse_pass_found_a_surface_that_near():
    from sefm_recon.matching.sgm import CoarseParallax, drop_unsupported_near

    _, _, tv, _ = _lateral_pair()
    grid = line_grid(tv, (320, 240), (320, 240))
    rows, cols = len(grid.phi), 60
    near, end = 40.0, 48.0  # the SIFT points' near end; the search's before its end columns
    disp = np.full((rows, cols), 30.0, np.float32)
    disp[:, 10:20] = 55.0  # at the near end: a surface the coarse pass saw there ...
    disp[:, 30:40] = 55.0  # ... and a plateau where it saw the surface at 30
    disp[:, 50:55] = 55.0  # ... and where it found nothing
    disp[0, 0] = -1.0  # invalid stays so
    coarse = np.full((rows, cols), 30.0, np.float32)
    coarse[:, 8:22] = 52.0
    coarse[:, 50:55] = np.nan
    found = CoarseParallax(coarse, np.ones((rows, cols), bool), 2.0, grid)  # the same grid: cell for cell
    n = drop_unsupported_near(disp, grid, found, near, end, -1.0)
    assert (disp[:, 10:20] == 55.0).all() and (disp[:, 20:30] == 30.0).all()
    assert (disp[:, 30:40] == -1.0).all() and (disp[:, 50:55] == -1.0).all()
    assert n == rows * 15 and disp[0, 0] == -1.0


def test_estimates_far_from_the_coarse_pass_are_dropped_only_where_it_is_sure():
    """Sure: the 3x3 coarse cells about the place all estimated, on textured windows that do
    not repeat along the lines at that scale, within a coarse column of each other."""
    from sefm_recon.matching.sgm import COARSE_CHECK_COLUMNS, COARSE_CHECK_MARGIN, CoarseParallax, drop_off_coarse

    _, _, tv, _ = _lateral_pair()
    grid = line_grid(tv, (320, 240), (320, 240))
    rows, cols, step = len(grid.phi), 80, 2.0
    tol = COARSE_CHECK_COLUMNS * step + COARSE_CHECK_MARGIN  # 6 columns
    coarse = np.full((rows, cols), 30.0, np.float32)  # one textured surface at 30 ...
    textured = np.ones((rows, cols), bool)
    coarse[:, 40:50] = np.nan  # ... with a band the coarse pass left without an estimate
    textured[:, 60:70] = False  # and a plain one (its estimates are ties)
    once = np.ones((rows, cols), bool)
    once[:, 70:78] = False  # and stripes at the coarse scale (its estimate may be a period off too)
    disp = np.full((rows, cols), 30.0, np.float32)
    disp[:, 10:20] = 30.0 + tol + 2.0  # a patch a period off: dropped
    disp[:, 22:26] = 30.0 + tol - 0.5  # within the tolerance: kept
    disp[:, 39] = 50.0  # off, beside the band: the 3x3 square about the coarse cell holds no estimate there
    disp[:, 50] = 50.0
    disp[:, 37] = 50.0  # one cell further the square is whole again: dropped
    disp[:, 61:69] = 50.0  # off, on the plain band: not sure either
    disp[:, 71:77] = 50.0  # off, on the stripes: not sure either
    disp[0, 0] = -1.0  # invalid stays so
    before = disp.copy()
    n = drop_off_coarse(disp, grid, CoarseParallax(coarse, textured, step, grid, once=once), -1.0)
    assert (disp[:, 10:20] == -1.0).all() and (disp[:, 37] == -1.0).all()
    keep = np.ones(cols, bool)
    keep[10:20] = keep[37] = False
    assert (disp[:, keep] == before[:, keep]).all()
    assert n == rows * 11


def test_the_coarse_parallax_on_the_whole_grid_is_its_value_at_each_cell():
    from sefm_recon.matching.sgm import CoarseParallax

    _, _, tv, _ = _lateral_pair()
    grid = line_grid(tv, (320, 240), (320, 240))
    Kc = np.diag([0.25, 0.25, 1.0]) @ tv.K1  # a quarter-size pass: its own, coarser grid
    coarse_grid = line_grid(TwoView(Kc, Kc, tv.R, tv.t), (80, 60), (80, 60))
    rng = np.random.default_rng(0)
    P = rng.uniform(0, 40, (len(coarse_grid.phi), coarse_grid.columns)).astype(np.float32)
    P[rng.random(P.shape) < 0.2] = np.nan
    found = CoarseParallax(P, np.ones(P.shape, bool), 4.0, coarse_grid)
    columns = grid.columns + 20  # beyond the coarse line images too
    whole = found.on_grid(grid, columns)
    rows, cols = np.indices(whole.shape).reshape(2, -1)
    np.testing.assert_array_equal(whole.ravel(), found.at(grid, rows, cols))
    assert np.isnan(whole).any() and np.isfinite(whole).mean() > 0.5


def test_the_search_follows_a_floor_nearer_than_its_sift_points():
    # A rectified pair of one slanted surface (a floor towards the camera): disparity
    # from 10 px at the top row to 100 px at the bottom. SIFT points on the top third
    # alone (10..40 px): the bottom rows lie beyond their range, its margin and OpenCV's
    # rounding. The coarse pass finds the floor beyond them, and the search follows it.
    import cv2

    rng = np.random.default_rng(5)
    w, h, f = 320, 240, 300.0
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (h, w + 110)).astype(np.float32), (0, 0), 1.2)
    tex = cv2.normalize(tex, None, 20, 235, cv2.NORM_MINMAX)
    d = np.broadcast_to((10.0 + 90.0 * np.arange(h) / (h - 1))[:, None], (h, w)).copy()
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    img1 = tex[:, :w].astype(np.uint8)
    img2 = cv2.remap(tex, xs + d.astype(np.float32), ys, cv2.INTER_LINEAR).astype(np.uint8)  # x2 = x1 - d
    d[:, w - 110:] = np.nan  # the texture ends at image 1's column w + 110
    img1, img2 = (np.repeat(im[..., None], 3, axis=2) for im in (img1, img2))
    kx, ky = np.meshgrid(np.arange(20, 200, 10) + 0.5, np.arange(10, h // 3, 10) + 0.5)
    kp1 = np.column_stack([kx.ravel(), ky.ravel()])
    kd = d[ky.ravel().astype(int), kx.ravel().astype(int)]
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    tv = TwoView(K, K, np.eye(3), np.array([-1.0, 0, 0]), kp1, kp1 - np.column_stack([kd, 0 * kd]), len(kp1))
    bottom = np.zeros((h, w), bool)
    bottom[d[:, 0] > 80.0, 110:w - 110] = True  # beyond the search without the extension, seen in image 2
    for near_range in (False, True):
        cfg = load_config(None, [f"sgm.near_range={str(near_range).lower()}"], internal=True)
        res = match_pair_sgm(img1, img2, tv, cfg)
        ij, truth, err = _disparity_errors(res, d)
        on_bottom = bottom[ij[:, 1], ij[:, 0]]
        right = np.count_nonzero(on_bottom & (err < 1.0)) / bottom.sum()
        if near_range:
            assert right > 0.9, right
        else:
            assert right < 0.05, right  # beyond the search: none right


@pytest.mark.parametrize("gains, expected", [
    ({}, 32),  # every penalty keeps as many cells: OpenCV's stays
    ({8: 1.2, 16: 1.1}, 8),  # fewer cells with each doubling: down to P1, no further
    ({64: 1.1, 128: 1.2, 256: 1.3}, 128),  # more with each doubling: up to 4x OpenCV's, no further
    ({16: 1.005, 8: 1.01}, 32),  # within the margin: counts that differ by noise move nothing
    ({64: 1.05, 128: 1.055}, 64),  # the step to 128 gains less than the margin
    ({16: 1.03, 64: 1.05, 8: 1.0}, 64),  # the better neighbour sets the direction
])
def test_the_jump_penalty_climbs_while_sgm_keeps_more_cells(gains, expected):
    from sefm_recon.matching.sgm import JUMP_MARGIN, jump_ladder

    assert JUMP_MARGIN == 0.01
    asked = []

    def count(jump):
        asked.append(jump)
        return int(100_000 * gains.get(jump, 1.0))

    assert jump_ladder(count) == expected
    assert 256 not in asked and 4 not in asked  # never beyond the bounds


def _shifted_line_images(d, plain=slice(0, 0), noise=0.0, seed=0):
    """Rectified 'line images' (240x400 RGB) of one texture, image 2's column c holding
    image 1's column c + d (``d`` (240, 400) disparities, searched 0..48); the texture is
    flat grey over the columns ``plain``, and Gaussian noise of ``noise`` grey levels is added."""
    import cv2

    rng = np.random.default_rng(seed)
    h, w = d.shape
    T = cv2.GaussianBlur(rng.uniform(0, 255, (h, w + 128)).astype(np.float32), (0, 0), 2.5)
    T = cv2.normalize(T, None, 20, 235, cv2.NORM_MINMAX)
    T[:, plain] = 128.0
    x = np.arange(w, dtype=np.float32)[None, :] + 56
    rows = np.repeat(np.arange(h, dtype=np.float32)[:, None], w, 1)
    L1 = cv2.remap(T, np.repeat(x, h, 0), rows, cv2.INTER_LINEAR)
    L2 = cv2.remap(T, (x + d).astype(np.float32), rows, cv2.INTER_LINEAR)
    to_rgb = lambda a: np.repeat(np.clip(a + rng.normal(0, noise, a.shape), 0, 255).astype(np.uint8)[..., None], 3, 2)
    return to_rgb(L1), to_rgb(L2)


def test_the_jump_penalty_is_opencvs_on_texture_and_larger_on_a_plain_slanted_surface():
    # On a textured surface every penalty finds it: OpenCV's 32 stays. On a plain surface
    # (flat grey under noise of a grey level) slanted by 30 px across the image, only the
    # paths carry the disparity across it, and a larger penalty keeps more of it through
    # the checks (measured on these images: 16,161 cells with 32, 17,271 with 64 and 17,351
    # with 128 at half size, so 64; the texture's quarter-size counts lie within 0.4 %).
    from sefm_recon.matching.sgm import choose_jump_penalty
    from sefm_recon.matching.stereo_sgbm import JUMP_PENALTY

    opt = load_config(None, []).sgm
    h, w = 240, 400
    flat = np.full((h, w), 20.0)
    assert choose_jump_penalty(*_shifted_line_images(flat), 48, opt) == JUMP_PENALTY
    slant = np.repeat(5.0 + 30.0 * np.arange(w)[None, :] / w, h, axis=0)
    assert choose_jump_penalty(*_shifted_line_images(slant, plain=slice(100, 400), noise=1.0), 48, opt) > JUMP_PENALTY
