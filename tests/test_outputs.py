"""Tests of the output writers: PLY, Poisson mesh, normals, COLMAP model, pictures."""

from __future__ import annotations

import numpy as np
import pytest

from sefm_recon.io.colmap_model import read_model, write_two_view_model
from sefm_recon.io.matches import _WRITE_BLOCK as _MATCH_BLOCK
from sefm_recon.io.matches import write_matches
from sefm_recon.io.ply import (
    _WRITE_BLOCK,
    read_mesh,
    read_ply_header,
    read_point_cloud,
    write_mesh,
    write_point_cloud,
)
from sefm_recon.io.visualize import draw_matches, render_points, write_image
from sefm_recon.reconstruct.mesh import poisson_mesh
from sefm_recon.reconstruct.points import clean_points, estimate_normals, sample_colors

RNG = np.random.default_rng(1234)


def _rot(rvec) -> np.ndarray:
    import cv2

    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))
    return R


def _project(K, R, t, X):
    x = (X @ R.T + t) @ K.T
    return x[:, :2] / x[:, 2:]


def _sphere(n, radius=1.0, center=(0.0, 0.0, 0.0)):
    d = RNG.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(center) + radius * d, d


# --------------------------------------------------------------------- PLY


@pytest.mark.parametrize("n", [500, 2 * _WRITE_BLOCK + 7])  # (the second: written in three blocks, the last short)
def test_ply_point_cloud_round_trip(tmp_path, n):
    xyz = RNG.normal(size=(n, 3))
    rgb = RNG.integers(0, 256, (n, 3), dtype=np.uint8)
    rgb[:3] = [[0, 0, 0], [255, 255, 255], [1, 128, 254]]
    nrm = RNG.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    path = tmp_path / "sub" / "cloud.ply"
    write_point_cloud(path, xyz, rgb, nrm)

    hdr = read_ply_header(path)
    assert hdr["format"] == "binary_little_endian"
    vert = hdr["elements"]["vertex"]
    assert vert["count"] == n
    assert [p for _, p in vert["properties"]] == ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"]
    types = dict((p, ty) for ty, p in vert["properties"])
    assert all(types[c] == "uchar" for c in ("red", "green", "blue"))
    assert all(types[c] == "float" for c in ("x", "y", "z", "nx", "ny", "nz"))  # COLMAP fused.ply layout

    xyz2, rgb2, nrm2 = read_point_cloud(path)
    np.testing.assert_allclose(xyz2, xyz, atol=1e-6)
    np.testing.assert_allclose(nrm2, nrm, atol=1e-6)
    assert rgb2.dtype == np.uint8
    np.testing.assert_array_equal(rgb2, rgb)
    # atomic writer leaves no temporary files behind
    assert [p.name for p in path.parent.iterdir()] == ["cloud.ply"]
    data = path.read_bytes()  # the header, then 27 bytes a point and nothing more
    assert len(data) == data.index(b"end_header\n") + len(b"end_header\n") + n * 27


@pytest.mark.parametrize("n", [0, 5, 2 * _MATCH_BLOCK + 3])
def test_matches_npz_is_numpys_savez_of_float32_copies(tmp_path, n):
    uv1, uv2 = RNG.normal(size=(n, 2)) * 1e3, RNG.normal(size=(n, 2)) * 1e3
    score = RNG.random(n)
    write_matches(tmp_path / "m.npz", uv1=uv1, uv2=uv2, score=score)
    np.savez(tmp_path / "s.npz", uv1=uv1.astype(np.float32), uv2=uv2.astype(np.float32),
             score=score.astype(np.float32))
    with np.load(tmp_path / "m.npz") as m, np.load(tmp_path / "s.npz") as s:
        assert m.files == s.files == ["uv1", "uv2", "score"]
        for k in m.files:
            assert m[k].dtype == np.float32 and m[k].shape == s[k].shape
            np.testing.assert_array_equal(m[k], s[k])
    assert (tmp_path / "m.npz").stat().st_size == (tmp_path / "s.npz").stat().st_size


def test_ply_without_normals_and_empty(tmp_path):
    xyz = RNG.normal(size=(10, 3))
    rgb = np.zeros((10, 3), np.uint8)
    write_point_cloud(tmp_path / "a.ply", xyz, rgb, None)
    _, rgb2, nrm2 = read_point_cloud(tmp_path / "a.ply")
    assert nrm2 is None and rgb2.shape == (10, 3)
    with pytest.raises(ValueError, match="empty"):
        write_point_cloud(tmp_path / "e.ply", np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
    assert not (tmp_path / "e.ply").exists()
    with pytest.raises(ValueError):
        write_point_cloud(tmp_path / "f.ply", xyz, rgb.astype(np.float32))


def test_mesh_round_trip(tmp_path):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    c = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [9, 99, 199]], np.uint8)
    path = tmp_path / "m.ply"
    write_mesh(path, v, f, c, None)
    hdr = read_ply_header(path)
    assert hdr["format"] == "binary_little_endian"
    assert hdr["elements"]["face"]["count"] == 4
    v2, f2, c2, _ = read_mesh(path)
    np.testing.assert_allclose(v2, v)
    np.testing.assert_array_equal(f2, f)
    np.testing.assert_array_equal(c2, c)
    # with normals and without colours; open3d's layout: double vertices, a uchar count and uint indices
    nrm = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)
    write_mesh(path, v + 0.125, f, None, nrm)
    vert, face = (read_ply_header(path)["elements"][k] for k in ("vertex", "face"))
    assert vert["properties"] == [("double", a) for a in ("x", "y", "z", "nx", "ny", "nz")]
    assert face["count"] == 4 and face["properties"] == [("list uchar uint", "vertex_indices")]
    v2, f2, c2, n2 = read_mesh(path)
    np.testing.assert_array_equal(v2, v + 0.125)
    np.testing.assert_array_equal(n2, nrm)
    np.testing.assert_array_equal(f2, f)
    assert c2 is None


# ------------------------------------------------------------ points/mesh


def test_normals_of_plane_face_camera_and_clean_points():
    n = 2000
    xy = RNG.uniform(-1, 1, (n, 2))
    xyz = np.c_[xy, np.full(n, 5.0)]  # plane z = 5, camera at the origin
    nrm = estimate_normals(xyz, np.zeros((1, 3)), k=12)
    np.testing.assert_allclose(nrm, np.tile([0, 0, -1.0], (n, 1)), atol=1e-6)
    # camera on the other side -> normals flip
    nrm = estimate_normals(xyz, np.array([[0, 0, 10.0], [0, 0, 0]]), k=12)
    assert np.all(nrm[:, 2] > 0.999)

    xyz_out = np.r_[xyz, [[0, 0, 50.0], [30, -20, 5]]]
    keep = clean_points(xyz_out, nb_neighbors=16, std_ratio=2.5)
    assert keep.shape == (n + 2,)
    assert not keep[-1] and not keep[-2]
    assert keep[:n].mean() > 0.95


def test_sample_colors_bilinear_colmap_convention():
    img = np.zeros((4, 5, 3), np.uint8)
    img[1, 2] = [100, 200, 50]
    img[1, 3] = [200, 0, 150]
    uv = np.array([[2.5, 1.5], [3.0, 1.5], [3.5, 1.5], [-10, -10], [100, 100]])
    c = sample_colors(img, uv)
    assert c.dtype == np.uint8
    np.testing.assert_array_equal(c[0], [100, 200, 50])  # pixel centre
    np.testing.assert_array_equal(c[1], [150, 100, 100])  # half way
    np.testing.assert_array_equal(c[2], [200, 0, 150])
    np.testing.assert_array_equal(c[3], img[0, 0])  # clamped
    np.testing.assert_array_equal(c[4], img[-1, -1])
    # a non-finite position gives 0; a grey image gives (N,); a float image keeps its dtype
    np.testing.assert_array_equal(sample_colors(img, [[np.nan, 1.0]])[0], [0, 0, 0])
    grey = sample_colors(img[:, :, 0], uv)
    assert grey.shape == (len(uv),) and grey.dtype == np.uint8
    np.testing.assert_array_equal(grey, c[:, 0])
    f = sample_colors(img.astype(np.float32) / 255, uv)
    assert f.dtype == np.float32
    np.testing.assert_allclose(f, c / 255, atol=0.5 / 255)


def test_poisson_mesh_sphere():
    xyz, nrm = _sphere(6000, radius=2.0, center=(1.0, -1.0, 3.0))
    rgb = np.tile(np.array([[200, 50, 10]], np.uint8), (len(xyz), 1))
    v, f, c, vn = poisson_mesh(xyz, nrm, rgb, depth=6, density_quantile=0.02)
    assert len(f) > 500 and f.max() < len(v)
    r = np.linalg.norm(v - [1.0, -1.0, 3.0], axis=1)
    assert np.abs(r - 2.0).max() < 0.1
    assert c.dtype == np.uint8 and c.shape == v.shape
    assert np.abs(c.astype(int) - [200, 50, 10]).max() <= 3
    # vertex normals point outwards
    assert (np.einsum("ij,ij->i", vn, v - [1.0, -1.0, 3.0]) > 0).mean() > 0.99
    with pytest.raises(ValueError, match="at least"):
        poisson_mesh(xyz[:50], nrm[:50], rgb[:50])


# ------------------------------------------------------------------ COLMAP


def test_colmap_two_view_round_trip(tmp_path):
    import pycolmap

    W, H = 640, 480
    K1 = np.array([[500.0, 0, 320], [0, 510, 240], [0, 0, 1]])
    K2 = np.array([[480.0, 0, 330], [0, 480, 235], [0, 0, 1]])
    cam1 = pycolmap.Camera(model="PINHOLE", width=W, height=H, params=[500, 510, 320, 240])
    cam2 = pycolmap.Camera(model="PINHOLE", width=W, height=H, params=[480, 480, 330, 235])
    R = _rot([0.02, -0.15, 0.01])
    t = np.array([-0.8, 0.05, 0.1])
    n = 3000
    X = np.c_[RNG.uniform(-2, 2, (n, 2)), RNG.uniform(4, 8, n)]
    uv1 = _project(K1, np.eye(3), np.zeros(3), X)
    uv2 = _project(K2, R, t, X)
    rgb = RNG.integers(0, 256, (n, 3), dtype=np.uint8)

    out = tmp_path / "sparse" / "0"
    rec = write_two_view_model(out, cam1, cam2, "a.png", "b.png", R, t, uv1, uv2, X, rgb,
                               max_points=1000, seed=3)
    assert rec.num_points3D() == 1000
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        assert (out / name).is_file()
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]

    rec2 = read_model(out)
    assert rec2.num_images() == 2 and rec2.num_points3D() == 1000
    assert rec2.num_reg_images() == 2
    im1 = rec2.find_image_with_name("a.png")
    im2 = rec2.find_image_with_name("b.png")
    np.testing.assert_allclose(im1.cam_from_world().matrix(), np.c_[np.eye(3), np.zeros(3)], atol=1e-12)
    np.testing.assert_allclose(im2.cam_from_world().matrix(), np.c_[R, t], atol=1e-9)
    np.testing.assert_allclose(rec2.camera(im1.camera_id).calibration_matrix(), K1)
    np.testing.assert_allclose(rec2.camera(im2.camera_id).calibration_matrix(), K2)

    # every point's track: one observation per image, xy = the match's uv
    uv_of = {tuple(np.round(x, 9)): k for k, x in enumerate(X)}
    for pid, p in rec2.points3D.items():
        k = uv_of[tuple(np.round(p.xyz, 9))]
        els = {e.image_id: e.point2D_idx for e in p.track.elements}
        assert set(els) == {im1.image_id, im2.image_id}
        np.testing.assert_allclose(im1.points2D[els[im1.image_id]].xy, uv1[k], atol=1e-9)
        np.testing.assert_allclose(im2.points2D[els[im2.image_id]].xy, uv2[k], atol=1e-9)
        np.testing.assert_array_equal(p.color, rgb[k])
    rec2.update_point_3d_errors()
    assert rec2.compute_mean_reprojection_error() < 1e-6

    # rewriting replaces the model; a folder with foreign files is refused
    write_two_view_model(out, cam1, cam2, "a.png", "b.png", R, t, uv1, uv2, X, rgb, max_points=10)
    assert read_model(out).num_points3D() == 10
    (out / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError):
        write_two_view_model(out, cam1, cam2, "a.png", "b.png", R, t, uv1, uv2, X, rgb)
    with pytest.raises(FileNotFoundError):
        read_model(tmp_path / "nothing")


# ---------------------------------------------------------------- pictures


def test_draw_matches_shape_and_scaling(tmp_path):
    img1 = RNG.integers(0, 256, (300, 400, 3), dtype=np.uint8)
    img2 = RNG.integers(0, 256, (250, 350, 3), dtype=np.uint8)
    uv1 = RNG.uniform(0, 1, (1000, 2)) * [400, 300]
    uv2 = RNG.uniform(0, 1, (1000, 2)) * [350, 250]
    pic = draw_matches(img1, img2, uv1, uv2, max_lines=50)
    assert pic.shape == (300, 750, 3) and pic.dtype == np.uint8
    big1 = np.zeros((3000, 4000, 3), np.uint8)
    big2 = np.zeros((3000, 4000), np.uint8)
    pic = draw_matches(big1, big2, uv1 * 10, uv2 * 10, max_lines=20)
    assert pic.shape == (750, 2000, 3)
    assert pic.any()  # lines and tint were drawn
    path = write_image(tmp_path / "m.png", pic)
    import cv2

    back = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(back, pic)


def test_render_points_projection_and_zbuffer():
    K = np.array([[100.0, 0, 32], [0, 100, 24], [0, 0, 1]])
    R = _rot([0.0, 0.1, 0.0])
    t = np.array([0.1, -0.2, 0.5])
    uv_target = np.array([[10.3, 7.8], [40.5, 30.5]])
    depth = np.array([3.0, 5.0])
    # back-project the target pixels to world points
    rays = np.c_[uv_target, np.ones(2)] @ np.linalg.inv(K).T
    Xc = rays * depth[:, None]
    X = (Xc - t) @ R  # R.T @ (Xc - t)
    far = (rays[0] * 9.0 - t) @ R  # same pixel as point 0, further away
    xyz = np.r_[X, far[None]]
    rgb = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], np.uint8)
    img = render_points(xyz, rgb, K, R, t, 64, 48)
    assert img.shape == (48, 64, 3)
    np.testing.assert_array_equal(img[7, 10], [255, 0, 0])  # nearest wins
    np.testing.assert_array_equal(img[30, 40], [0, 255, 0])
    assert (img.reshape(-1, 3).any(1)).sum() == 2
    # near-first order reversed must give the same result
    img_rev = render_points(xyz[::-1], rgb[::-1], K, R, t, 64, 48)
    np.testing.assert_array_equal(img_rev, img)
    big = render_points(xyz, rgb, K, R, t, 64, 48, point_size=3)
    assert (big.reshape(-1, 3).any(1)).sum() == 18
    np.testing.assert_array_equal(big[6:9, 9:12].reshape(-1, 3), np.tile([255, 0, 0], (9, 1)))


def test_grid_normals_of_a_tilted_plane_face_the_camera():
    from sefm_recon.reconstruct.points import grid_normals

    K = np.array([[200.0, 0, 50], [0, 200, 40], [0, 0, 1]])
    jj, ii = np.meshgrid(np.arange(100) + 0.5, np.arange(80) + 0.5)
    uv = np.c_[jj.ravel(), ii.ravel()]
    rays = np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(K).T
    n_true = np.array([0.3, -0.2, -1.0])
    n_true /= np.linalg.norm(n_true)
    # plane n . X = d with the camera on the side n points to (d < 0)
    d = -5.0
    X = rays * (d / (rays @ n_true))[:, None]
    n = grid_normals(uv, X, (80, 100))
    assert np.all(np.abs(n @ n_true - 1) < 1e-6)
    assert np.all(np.sum(n * -X, axis=1) > 0)


def test_finite_rows_flags_any_non_finite_entry():
    from sefm_recon.arrays import finite_rows

    a = np.ones((6, 3))
    b = np.ones((6, 2))
    a[1, 2] = np.nan
    a[2, 0] = np.inf
    b[3, 1] = -np.inf
    a[4] = [np.inf, -np.inf, 0.0]  # opposite infinities must not cancel
    np.testing.assert_array_equal(finite_rows(a, b), [True, False, False, False, False, True])
    np.testing.assert_array_equal(finite_rows(b), [True, True, True, False, True, True])
    c = np.ones((4, 2), np.float32)  # every entry finite: every row, however they are summed
    np.testing.assert_array_equal(finite_rows(c, np.zeros((4, 3))), [True] * 4)
    c[2, 0] = np.nan
    np.testing.assert_array_equal(finite_rows(c, np.zeros((4, 3))), [True, True, False, True])


def test_sample_colors_equal_the_corner_weights_everywhere():
    from sefm_recon.reconstruct.points import bilinear_corners

    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, size=(7, 9, 3)).astype(np.uint8)
    uv = rng.uniform([-3, -3], [12, 10], size=(500, 2))  # inside, on the border and outside
    y0, y1, x0, x1, fx, fy = bilinear_corners(7, 9, uv)
    f = img.astype(np.float64)
    fx, fy = fx[:, None], fy[:, None]
    want = (f[y0, x0] * (1 - fx) + f[y0, x1] * fx) * (1 - fy) + (f[y1, x0] * (1 - fx) + f[y1, x1] * fx) * fy
    np.testing.assert_allclose(sample_colors(img.astype(np.float32), uv), want, atol=1e-4)
