"""Polar line images (matching/lines.py) and semi-global matching over them (matching/sgm.py)."""

import cv2
import numpy as np
import pytest

from sefm_recon.config import load_config
from sefm_recon.evaluate import covisibility_mask, evaluate_matches
from sefm_recon.geometry.epipolar import ray_angles
from sefm_recon.geometry.two_view import TwoView
from sefm_recon.matching.lines import COLUMN_SPACING_PX, ROW_SPACING_PX, line_grid, line_images, project, rays
from sefm_recon.matching.sgm import MEDIAN_SAME_SURFACE, match_pair_sgm, parallax_columns, surface_median
from sefm_recon.pipeline import reconstruct_pair

from .conftest import rot_y


def _two_view(R, t, f=300.0, w=320, h=240):
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    return TwoView(K, K, np.asarray(R, float), np.asarray(t, float), np.zeros((0, 2)), np.zeros((0, 2)), 0)


@pytest.mark.parametrize("pose", ["lateral", "turned", "forward"])
def test_a_scene_point_lies_on_one_row_at_a_larger_angle_in_view_2(pose):
    R, t = {"lateral": (np.eye(3), [-1.0, 0, 0]),
            "turned": (rot_y(0.2), [-1.0, 0.1, 0.2]),
            "forward": (np.eye(3), [0.1, 0.0, -1.0])}[pose]
    tv = _two_view(R, t)
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
    tv = _two_view(R, t)
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

    tv = _two_view(np.eye(3), [-1.0, 0, 0])
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
    from sefm_recon.matching.sgm import BLOCK

    tv = _two_view(np.eye(3), [0.0, 0.0, -1.0])
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


def test_windows_beyond_image_2_are_dropped():
    from sefm_recon.matching.sgm import BLOCK, drop_outside_windows

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


def test_a_scale_change_about_the_epipole_is_a_shift_of_columns():
    # forward motion: a point at angle alpha from the baseline moves to about s * alpha;
    # in columns that is the same shift log(s) / u_step wherever the point lies
    tv = _two_view(np.eye(3), [0.0, 0.0, -1.0])
    grid = line_grid(tv, (320, 240), (320, 240))
    a1 = np.array([0.015, 0.05, 0.1, 0.2, 0.3])
    shift = grid.column(a1) - grid.column(1.5 * a1)
    assert np.allclose(shift, np.log(1.5) / grid.u_step, rtol=0.03)
    # columns and angles are each other's inverse (rays nearer the epipole than the edge aside)
    cols = grid.column(a1)
    assert np.allclose(grid.alpha(cols), a1) and grid.edge < a1.min()
    assert grid.column(grid.edge / 2) == pytest.approx(grid.column(grid.edge))


def _plane_disparities(tv, grid, width, depth):
    """Disparity map (rows, width) of the line images for a fronto-parallel plane at ``depth``."""
    alpha = grid.alpha(np.arange(width))
    r1 = rays(grid.basis, grid.phi[:, None], alpha[None, :])
    X = r1 * (depth / r1[..., 2])[..., None]  # camera-1 axes
    d2 = X - (-tv.R.T @ tv.t)  # from camera 2's centre, camera-1 axes
    a2 = np.arccos(np.clip((d2 @ grid.basis[0]) / np.linalg.norm(d2, axis=-1), -1, 1))
    return (np.arange(width)[None, :] - grid.column(a2)).astype(np.float32)


def test_disparities_read_back_at_every_pixel_lie_on_its_epipolar_line(monkeypatch):
    from sefm_recon.matching.sgm import pixel_matches

    tv = _two_view(rot_y(0.1), [-1.0, 0.05, 0.1])
    grid = line_grid(tv, (320, 240), (320, 240))
    grid.pad = 40
    width = grid.pad + grid.columns + 1
    near, far = _plane_disparities(tv, grid, width, 8.0), _plane_disparities(tv, grid, width, 20.0)
    # two surfaces side by side in the line images, and a hole the matcher left
    disp = np.where(np.arange(width)[None, :] < grid.pad + grid.columns // 2, near, far)
    disp[100:120, :] = -1.0
    uv1, uv2, X, rows = pixel_matches(disp, 0.0, grid, tv, (320, 240), (320, 240))
    assert len(uv1) > 0.75 * 320 * 240 and np.all(np.mod(uv1, 1.0) == 0.5)  # pixel centres, most of them
    assert len(np.unique(uv1, axis=0)) == len(uv1)  # one match a pixel
    # each match is the projection of a point on one of the two planes, never between them
    ray = np.column_stack([uv1, np.ones(len(uv1))]) @ np.linalg.inv(tv.K1).T
    err = []
    for depth in (8.0, 20.0):
        X2 = (ray * depth / ray[:, 2:]) @ tv.R.T + tv.t
        err.append(np.linalg.norm(X2[:, :2] / X2[:, 2:] @ tv.K2[:2, :2].T + tv.K2[:2, 2] - uv2, axis=1))
    err = np.minimum(*err)
    assert np.percentile(err, 99) < 0.05 and err.max() < 0.5
    # each point is where the pixel's ray meets its match's: it projects onto both, as the
    # midpoint triangulation of the pair puts it
    from sefm_recon.geometry.triangulate import project, triangulate

    assert np.abs(project(tv.K1, np.eye(3), np.zeros(3), X) - uv1).max() < 1e-6
    assert np.abs(project(tv.K2, tv.R, tv.t, X) - uv2).max() < 1e-6
    X2, valid, _ = triangulate(tv.K1, tv.K2, tv.R, tv.t, uv1, uv2)
    assert valid.all() and np.abs(X - X2).max() < 1e-9 * np.abs(X2).max()
    assert len(X.base) == 320 * 240  # room after them for the plane fill's points (arrays.append_rows)
    # no match from the hole's rows, except where a pixel's nearest row is outside it
    assert not np.any((rows > 101) & (rows < 118))
    # read back a few image rows at a time (as a large photo is): the same matches, in order
    import sefm_recon.matching.sgm as sgm

    monkeypatch.setattr(sgm, "_CHUNK_PIXELS", 7 * 320 + 5)
    chunked = pixel_matches(disp, 0.0, grid, tv, (320, 240), (320, 240))
    for a, b in zip(chunked, (uv1, uv2, X, rows)):
        assert np.array_equal(a, b)


def test_disparities_read_back_all_round_an_epipole_inside_the_image():
    """Forward motion: the rows go all round the epipole, spaced by what each direction
    needs; a plane's disparities read back at every pixel that image 2 sees, in every
    direction from the epipole (across the rows' first and last), onto the plane's points."""
    from sefm_recon.matching.sgm import pixel_matches

    tv = _two_view(np.eye(3), [0.1, 0.0, -1.0])  # camera 2 1 unit nearer the plane at 8
    grid = line_grid(tv, (320, 240), (320, 240))
    assert grid.joined.all()  # a closed circle of rows
    grid.pad = 40
    width = grid.pad + grid.columns + 1
    uv1, uv2, X, _ = pixel_matches(_plane_disparities(tv, grid, width, 8.0), 0.0, grid, tv, (320, 240), (320, 240))
    ray = np.column_stack([uv1, np.ones(len(uv1))]) @ np.linalg.inv(tv.K1).T
    X2 = (ray * 8.0 / ray[:, 2:]) @ tv.R.T + tv.t
    err = np.linalg.norm(X2[:, :2] / X2[:, 2:] @ tv.K2[:2, :2].T + tv.K2[:2, 2] - uv2, axis=1)
    assert np.percentile(err, 99) < 0.05 and err.max() < 0.5
    # the pixels image 2 sees (the plane 8 / 7 times larger there), minus the epipole's few
    xs, ys = np.meshgrid(np.arange(320) + 0.5, np.arange(240) + 0.5)
    p = np.column_stack([xs.ravel(), ys.ravel()])
    e = tv.K1 @ (-tv.R.T @ tv.t)
    e = e[:2] / e[2]
    seen = np.all(np.abs((p - e) * 8.0 / 7.0 + e - [160, 120]) < [159.5, 119.5], axis=1)
    matched = np.zeros(len(p), bool)
    matched[np.floor(uv1[:, 1]).astype(int) * 320 + np.floor(uv1[:, 0]).astype(int)] = True
    assert matched[~seen].mean() < 0.05
    # in every direction from the epipole
    sector = (np.degrees(np.arctan2(*(p - e).T[::-1])) // 10).astype(int)
    for k in np.unique(sector[seen]):
        assert matched[seen & (sector == k)].mean() > 0.97


def test_the_outermost_pixel_rows_read_back_as_every_other_row():
    """The first and last rows of the line images lie half a row inside image 1's outermost
    pixel centres, which are as near the row beyond that does not exist: they are matched
    from the row there is, as every other row of pixels."""
    from sefm_recon.matching.sgm import pixel_matches

    tv = _two_view(np.eye(3), [-1.0, 0.0, 0.0])  # rectified: the rows are image rows
    grid = line_grid(tv, (320, 240), (320, 240))
    grid.pad = 40
    width = grid.pad + grid.columns + 1
    phi = grid.phi.copy()
    # the outermost pixel centres a hair farther than half a row from the first (last) row
    for outer, nudge in ((239, 0.02), (0, -0.02)):  # (phi runs up the image)
        grid.phi = phi + nudge * grid.reach[0]
        uv1, _, _, _ = pixel_matches(_plane_disparities(tv, grid, width, 8.0), 0.0, grid, tv, (320, 240), (320, 240))
        per_row = np.bincount(np.floor(uv1[:, 1]).astype(int), minlength=240)
        assert per_row[120] > 200 and per_row[outer] >= per_row[120] - 2  # (a corner's partner may leave image 2)


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


def test_the_nearer_surfaces_cell_at_a_depth_edge_is_dropped():
    from sefm_recon.matching.sgm import FATTENED_CELLS, drop_fattened_cells

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

    from sefm_recon.matching.sgm import _sgbm, fill_from_half_size, half_size_sgm, halve_line_images

    rng = np.random.default_rng(5)
    clouds = cv2.GaussianBlur(rng.normal(0, 1, (64, 300)), (0, 0), 3.0)
    L1, L2 = _low_contrast_pair(rng, 128 + 4 * clouds / clouds.std(), noise=3.0)
    full, _ = _sgbm(L1, L2, 0, 48, 10)
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
    1 px off, or hidden in image 2) far more often than the matches overall (measured: 87
    cells, 32 % wrong against 0.26 %)."""
    at, wrong, _, _ = _cells_a_check_drops("sgm.lr_check")
    assert 20 < at.sum() < 0.01 * len(at)
    assert wrong[at].mean() > 5 * wrong.mean()


def _one_row_collision(d_far, d_near, colour_far, colour_near, colour2):
    """A row with two valid cells, 12 (parallax ``d_far``) and 16 (``d_near``), and image 2's
    column 2, where both land when the parallaxes are 10 and 14; returns the cells dropped."""
    from sefm_recon.matching.sgm import drop_collisions

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


def test_the_cells_dropped_where_two_surfaces_reach_one_pixel_are_wrong_far_more_often():
    """On the lateral pair (the square at 30 px in front of its background at 10 px), with
    the other depth-edge step off: the cells the collision test drops are wrong (more than
    1 px off, or hidden in image 2) far more often than the matches overall (measured: 191
    cells, 95 % wrong against 0.55 %)."""
    at, wrong, _, _ = _cells_a_check_drops("sgm.collision_check", extra=["sgm.edge_check=false"])
    assert 20 < at.sum() < 0.01 * len(at)
    assert wrong[at].mean() > 5 * wrong.mean()


def _one_row_occlusion(before: float, strip_colour: int, gap_start: int = 40, holes=(), hole_parallax=30.0,
                       edge: int = 56):
    """A row: a valid cell (parallax ``before``) at ``gap_start - 1``, unmatched cells up to
    column 50, then a run at parallax 30: cells of ``strip_colour`` on 50 .. ``edge - 1``, the
    nearer surface's texture from ``edge`` on; the cells ``holes`` unmatched and the run's cells
    after them at ``hole_parallax``. The gap's colour is 100. Returns the cells dropped."""
    from sefm_recon.matching.sgm import drop_occluded_plain, plain_windows

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


def _one_row_jump(near_colour: int, edge: int = 60, ramp: bool = False, far_plain: bool = True, unmatched=()):
    """A row: a plain farther surface (colour 100, parallax 10) on columns 0 .. 39, then
    the nearer parallax 20 from column 40 on, on cells of ``near_colour`` up to ``edge - 1``
    and the nearer surface's texture from ``edge`` on (with ``ramp``, instead, grey rising
    by 1.5 levels a column from column 40: plain windows throughout); the cells
    ``unmatched`` unmatched. Returns the cells dropped."""
    from sefm_recon.matching.sgm import drop_carried_plain, plain_windows

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
    240 cells, 11 % wrong against 2.5 %; with the check alone, 468); measured without: 572
    cells, 27 % wrong against 2.7 %, the strip 29 % matched without the check, 23 % with."""
    at, wrong, kept, d = _cells_a_check_drops("sgm.occlusion_check", plain=(70, 150),
                                              extra=("sgm.half_fill=false", "sgm.half_check=false"))
    assert at.sum() > 500
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
    from sefm_recon.matching import sgm

    assert sgm.speckle_window(400, 700, 64) == 508 and sgm.speckle_window(100, 164, 64) == sgm.SPECKLE_WINDOW
    for side, kept in ((30, False), (48, True)):
        L1, L2, patch = _island(side)
        d, _ = sgm._sgbm(L1, L2, 0, 64, 10)
        assert np.mean(np.abs(d[50:120, 100:600] - 20) < 1) > 0.99  # the background stays
        found = np.mean(np.abs(d[patch] - 40) < 1)
        assert found > 0.5 if kept else found < 0.05
    monkeypatch.setattr(sgm, "SPECKLE_SHARE", 0.0)
    L1, L2, patch = _island(30)
    d, _ = sgm._sgbm(L1, L2, 0, 64, 10)
    assert np.mean(np.abs(d[patch] - 40) < 1) > 0.3


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
    tv = _two_view(np.eye(3), [-1.0, 0, 0])
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
    base = _two_view(np.eye(3), [-1.0, 0, 0])
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


def test_estimates_whose_window_reaches_into_an_area_of_one_value_are_dropped():
    # the fill left of a turned image's edge (columns 0 .. 19) beside texture: a window of
    # 5 reaches into the fill from column 21 leftwards, and column 22's no longer does
    from sefm_recon.matching.sgm import drop_flat_windows

    L1 = np.random.default_rng(1).integers(1, 255, (12, 60, 3)).astype(np.uint8)
    L1[:, :20] = 0
    disp = np.full((12, 60), 5.0, np.float32)
    disp[:, 40] = -1.0  # an estimate already dropped stays so, uncounted
    n = drop_flat_windows(disp, L1, -1.0)
    dropped = disp[6] == -1.0
    assert dropped[:22].all() and not dropped[22:40].any() and not dropped[41:].any()
    assert n == 12 * 22


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


def test_far_end_estimates_of_cells_image_2_sees_only_there_are_dropped():
    from sefm_recon.matching.sgm import BLOCK, drop_unseen_far

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
    from sefm_recon.matching.sgm import MEDIAN_SAME_SURFACE, drop_frame_end_runs

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
    from sefm_recon.matching.sgm import BLOCK, drop_unanchored_far

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
    from sefm_recon.matching.sgm import PLAIN_FIT_HALF, local_planes

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
    from sefm_recon.matching.sgm import PLAIN_LEVELS, fit_plain_surfaces, plain_windows

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
    from sefm_recon.matching.sgm import MEDIAN_SAME_SURFACE, PLAIN_FIT_HALF, PLAIN_FIT_SUPPORT, fit_plain_surfaces

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
    from sefm_recon.matching.sgm import JUMP_PENALTY, choose_jump_penalty

    opt = load_config(None, []).sgm
    h, w = 240, 400
    flat = np.full((h, w), 20.0)
    assert choose_jump_penalty(*_shifted_line_images(flat), 48, opt) == JUMP_PENALTY
    slant = np.repeat(5.0 + 30.0 * np.arange(w)[None, :] / w, h, axis=0)
    assert choose_jump_penalty(*_shifted_line_images(slant, plain=slice(100, 400), noise=1.0), 48, opt) > JUMP_PENALTY
