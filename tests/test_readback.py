"""The disparities read back at every pixel of image 1 (:mod:`sefm_recon.matching.readback`)."""

import numpy as np

from sefm_recon.matching.lines import line_grid, project, rays

from .conftest import rot_y, two_view


def _plane_disparities(tv, grid, width, depth):
    """Disparity map (rows, width) of the line images for a fronto-parallel plane at ``depth``."""
    alpha = grid.alpha(np.arange(width))
    r1 = rays(grid.basis, grid.phi[:, None], alpha[None, :])
    X = r1 * (depth / r1[..., 2])[..., None]  # camera-1 axes
    d2 = X - (-tv.R.T @ tv.t)  # from camera 2's centre, camera-1 axes
    a2 = np.arccos(np.clip((d2 @ grid.basis[0]) / np.linalg.norm(d2, axis=-1), -1, 1))
    return (np.arange(width)[None, :] - grid.column(a2)).astype(np.float32)


def test_disparities_read_back_at_every_pixel_lie_on_its_epipolar_line(monkeypatch):
    from sefm_recon.matching.readback import pixel_matches

    tv = two_view(rot_y(0.1), [-1.0, 0.05, 0.1])
    grid = line_grid(tv, (320, 240), (320, 240))
    grid.pad = 40
    width = grid.pad + grid.columns + 1
    near, far = _plane_disparities(tv, grid, width, 8.0), _plane_disparities(tv, grid, width, 20.0)
    # two surfaces side by side in the line images, and a hole the matcher left
    disp = np.where(np.arange(width)[None, :] < grid.pad + grid.columns // 2, near, far)
    disp[100:120, :] = -1.0
    uv1, uv2, X, cells = pixel_matches(disp, 0.0, grid, tv, (320, 240), (320, 240))
    rows = cells // width
    assert np.all(disp.ravel()[cells] >= 0)  # each match's nearest cell: a valid one
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
    import sefm_recon.matching.readback as readback

    monkeypatch.setattr(readback, "_CHUNK_PIXELS", 7 * 320 + 5)
    chunked = pixel_matches(disp, 0.0, grid, tv, (320, 240), (320, 240))
    for a, b in zip(chunked, (uv1, uv2, X, cells)):
        assert np.array_equal(a, b)


def test_disparities_read_back_all_round_an_epipole_inside_the_image():
    """Forward motion: the rows go all round the epipole, spaced by what each direction
    needs; a plane's disparities read back at every pixel that image 2 sees, in every
    direction from the epipole (across the rows' first and last), onto the plane's points."""
    from sefm_recon.matching.readback import pixel_matches

    tv = two_view(np.eye(3), [0.1, 0.0, -1.0])  # camera 2 1 unit nearer the plane at 8
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
    from sefm_recon.matching.readback import pixel_matches

    tv = two_view(np.eye(3), [-1.0, 0.0, 0.0])  # rectified: the rows are image rows
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


def test_the_matches_read_back_from_one_disparity_have_that_parallax():
    from sefm_recon.matching.lines import match_parallax
    from sefm_recon.matching.readback import pixel_matches

    tv = two_view(rot_y(0.1), [-1.0, 0.05, 0.1])
    grid = line_grid(tv, (320, 240), (320, 240))
    grid.pad = 40
    disp = np.full((len(grid.phi), grid.pad + grid.columns + 1), 17.25, np.float32)
    uv1, uv2, _, _ = pixel_matches(disp, 0.0, grid, tv, (320, 240), (320, 240))
    assert len(uv1) > 1000
    np.testing.assert_allclose(match_parallax(grid, tv, uv1, uv2), 17.25, atol=1e-6)
