"""The grid mesh (reconstruct/mesh.py): known surfaces seen by a pinhole camera at the origin."""

from __future__ import annotations

import numpy as np
import pytest

from sefm_recon.reconstruct.mesh import MAX_GRAZING_DEG, grid_mesh

F, W, H = 500.0, 200, 150  # focal length (px) and image size of the test camera


def _seen(depth: np.ndarray):
    """Points on every pixel centre of a (H, W) z-depth map: (uv, xyz) in COLMAP pixels and camera 1's frame."""
    r, c = np.nonzero(np.isfinite(depth))
    uv = np.stack([c + 0.5, r + 0.5], 1)
    z = depth[r, c]
    xyz = np.stack([(uv[:, 0] - W / 2) * z / F, (uv[:, 1] - H / 2) * z / F, z], 1)
    return uv, xyz


def _components(f: np.ndarray, n: int) -> int:
    """Connected components of a triangle mesh's vertices that have triangles."""
    parent = np.arange(n)

    def root(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a, b, c in f:
        for p, q in ((a, b), (b, c)):
            parent[root(p)] = root(q)
    return len({root(v) for v in np.unique(f)})


def test_plane_facing_the_camera():
    uv, xyz = _seen(np.full((H, W), 4.0))
    rgb = np.tile(np.array([[10, 120, 250]], np.uint8), (len(uv), 1))
    v, f, c, vn = grid_mesh(uv, xyz, rgb, (H, W), F, max_vertices=2000)
    assert 1500 <= len(v) <= 2000  # the budget, nearly filled
    np.testing.assert_allclose(v[:, 2], 4.0)
    np.testing.assert_array_equal(c, np.tile([10, 120, 250], (len(v), 1)))
    np.testing.assert_allclose(vn, np.tile([0.0, 0.0, -1.0], (len(v), 1)), atol=1e-9)  # towards the camera
    # every triangle faces the camera (its winding's normal points back along the ray)
    nrm = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert (nrm[:, 2] < 0).all()
    side = int(np.ceil(np.sqrt(W * H / 2000)))  # the cell size the budget gives
    rows, cols = -(-H // side), -(-W // side)
    assert len(f) == 2 * (rows - 1) * (cols - 1)  # one closed sheet: two triangles a cell


def test_depth_jump_left_open_and_cells_not_mixed():
    depth = np.full((H, W), 4.0)
    depth[:, 103:] = 4.5  # a wall 12 % behind, from a column that no cell boundary meets
    uv, xyz = _seen(depth)
    v, f, _, _ = grid_mesh(uv, xyz, None, (H, W), F, max_vertices=2000)
    # a cell across the jump takes the surface of its centre point, never the mean of both
    assert np.isin(np.round(v[:, 2], 9), [4.0, 4.5]).all()
    # no triangle joins the two surfaces: two sheets
    assert (np.ptp(v[f][:, :, 2], axis=1) == 0).all()
    assert _components(f, len(v)) == 2


def test_slanted_plane_stays_one_surface():
    # a floor seen at 75 degrees from the viewing direction: depth grows tan(75) x faster than across
    tilt = np.radians(75.0)
    assert 75.0 < MAX_GRAZING_DEG
    r = np.arange(H)[:, None] + 0.5
    # plane z = z0 + k * y, in camera coordinates y = (row - H/2) z / F  =>  z = z0 / (1 - k (row - H/2) / F)
    k = np.tan(tilt)
    depth = np.broadcast_to(4.0 / (1 - k * (r - H / 2) / F), (H, W)).copy()
    depth[depth <= 0] = np.inf
    depth[depth > 40] = np.inf
    uv, xyz = _seen(depth)
    v, f, _, _ = grid_mesh(uv, xyz, None, (H, W), F, max_vertices=2000)
    assert _components(f, len(v)) == 1
    # its vertices lie on the plane z - k y = 4
    np.testing.assert_allclose(v[:, 2] - k * v[:, 1], 4.0, rtol=1e-3)


def test_no_surface_raises():
    uv = np.array([[10.5, 10.5], [100.5, 80.5], [150.5, 20.5]])
    xyz = np.array([[0.0, 0.0, 4.0], [0.1, 0.1, 4.0], [0.2, 0.0, 4.0]])
    with pytest.raises(ValueError, match="no triangle"):
        grid_mesh(uv, xyz, None, (H, W), F, max_vertices=100)
