"""Tests of the synthetic scene generator (small renders, fast)."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from sefm_recon.synthetic import SyntheticScene, read_workspace, render_scene, write_workspace

W, H = 160, 120


@pytest.fixture(scope="module")
def scene() -> SyntheticScene:
    return render_scene(seed=7, width=W, height=H)


@pytest.fixture(scope="module")
def scene320() -> SyntheticScene:
    return render_scene(seed=3, width=320, height=240)


def _backproject(view, step: int = 1):
    h, w = view.depth.shape
    ii, jj = np.mgrid[0:h:step, 0:w:step]
    d = view.depth[ii, jj].astype(np.float64)
    ok = np.isfinite(d)
    pix = np.stack([jj[ok] + 0.5, ii[ok] + 0.5, np.ones(ok.sum())])
    Xc = (np.linalg.inv(view.K) @ pix) * d[ok]
    Xw = (view.R.T @ (Xc - view.t[:, None])).T
    return Xw, ii[ok], jj[ok]


def _sdf(prim: dict, X: np.ndarray) -> np.ndarray:
    kind = prim["type"]
    if kind in ("floor", "back_wall", "left_wall", "right_wall"):
        return X @ np.asarray(prim["normal"]) + prim["offset"]
    if kind == "sphere":
        return np.linalg.norm(X - np.asarray(prim["center"]), axis=1) - prim["radius"]
    if kind == "box":
        c, s = math.cos(prim["yaw"]), math.sin(prim["yaw"])
        Ry = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        q = np.abs((X - np.asarray(prim["center"])) @ Ry) - np.asarray(prim["half_size"])
        return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
    if kind == "cylinder":
        cx, cz = prim["center_xz"]
        y0, y1 = prim["y_range"]
        dr = np.hypot(X[:, 0] - cx, X[:, 2] - cz) - prim["radius"]
        dy = np.maximum(y0 - X[:, 1], X[:, 1] - y1)
        q = np.stack([dr, dy], axis=1)
        return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
    raise AssertionError(kind)


def test_basic_shapes_and_types(scene):
    assert len(scene.views) == 2
    for k, v in enumerate(scene.views):
        assert v.name == f"view_{k:03d}.png"
        assert v.image.shape == (H, W, 3) and v.image.dtype == np.uint8
        assert v.depth.shape == (H, W) and v.depth.dtype == np.float32
        assert v.K.shape == (3, 3) and v.R.shape == (3, 3) and v.t.shape == (3,)
        np.testing.assert_allclose(v.R @ v.R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(v.R) == pytest.approx(1.0)
        assert v.K[0, 0] == v.K[1, 1]
        assert 0.9 * W <= v.K[0, 0] <= 1.2 * W
        assert (v.K[0, 2], v.K[1, 2]) == (W / 2, H / 2)
        # enclosed scene: every pixel hits a surface
        assert np.isfinite(v.depth).all()
        assert (v.depth > 0).all()
        # textured, not flat
        assert v.image.std() > 15
    m = scene.meta
    assert m["seed"] == 7 and m["width"] == W and m["height"] == H
    assert m["scene_size"] > 1.0
    json.dumps(m)  # serialisable


def test_cameras_upright_converging(scene):
    v1, v2 = scene.views
    C1, C2 = v1.center, v2.center
    target = np.asarray(scene.meta["target"])
    b = np.linalg.norm(C2 - C1)
    dist = np.linalg.norm((C1 + C2) / 2 - target)
    assert 0.08 < b / dist < 0.22
    for v in scene.views:
        # camera "down" axis close to world -y (upright), optical axis towards the target
        assert v.R[1] @ np.array([0.0, -1.0, 0.0]) > 0.9
        ray = (target - v.center) / np.linalg.norm(target - v.center)
        assert v.R[2] @ ray > math.cos(math.radians(5))
    # view 2 lies to the right of view 1 (camera x axis)
    assert v1.R[0] @ (C2 - C1) > 0


def test_depth_lies_on_scene_surfaces(scene):
    prims = scene.meta["primitives"]
    for v in scene.views:
        X, _, _ = _backproject(v)
        d = np.min(np.abs(np.stack([_sdf(p, X) for p in prims])), axis=0)
        assert np.max(d) < 1e-4, np.max(d)
        # nothing below the floor; the floor is y = 0
        assert X[:, 1].min() > -1e-4
        on_floor = np.abs(X[:, 1]) < 1e-5
        assert on_floor.mean() > 0.1


def test_depth_consistent_across_views(scene):
    v1, v2 = scene.views
    X, ii, jj = _backproject(v1)
    Xc2 = X @ v2.R.T + v2.t
    p = Xc2 @ v2.K.T
    uv = p[:, :2] / p[:, 2:3]
    inside = (uv[:, 0] >= 0.5) & (uv[:, 0] < W - 0.5) & (uv[:, 1] >= 0.5) & (uv[:, 1] < H - 0.5)
    x = uv[inside, 0] - 0.5
    y = uv[inside, 1] - 0.5
    j0, i0 = np.floor(x).astype(int), np.floor(y).astype(int)
    j1, i1 = np.minimum(j0 + 1, W - 1), np.minimum(i0 + 1, H - 1)
    D = v2.depth.astype(np.float64)
    nb = np.stack([D[i0, j0], D[i0, j1], D[i1, j0], D[i1, j1]])
    z = Xc2[inside, 2]
    smooth = (nb.max(0) - nb.min(0)) < 0.01 * nb.min(0)
    fx, fy = x - j0, y - i0
    bil = (nb[0] * (1 - fx) + nb[1] * fx) * (1 - fy) + (nb[2] * (1 - fx) + nb[3] * fx) * fy
    visible = smooth & (z < bil * 1.01)
    assert smooth.mean() > 0.5
    assert visible.sum() > 0.8 * smooth.sum()  # most of view 1 is co-visible
    # where visible, view 2's depth agrees with the transferred z
    rel = np.abs(z[visible] - bil[visible]) / z[visible]
    assert np.median(rel) < 1e-4
    assert np.quantile(rel, 0.99) < 2e-3
    # and some pixels are occluded in view 2 (real occlusions exist)
    occluded = smooth & (z > bil * 1.05)
    assert occluded.sum() > 0


def test_photometric_consistency_pixel_convention(scene320):
    """Warping view 2 into view 1 with the true geometry reproduces view 1 best at
    zero offset: images and depth maps share the COLMAP pixel convention."""
    from sefm_recon.evaluate import true_correspondences

    v1, v2 = scene320.views
    h, w = v1.depth.shape
    ii, jj = np.mgrid[0:h, 0:w]
    uv1 = np.column_stack([jj.ravel() + 0.5, ii.ravel() + 0.5])
    uv2, cov = true_correspondences(v1, v2, uv1)
    # stay away from depth edges, where a warp is ill-defined
    D = v1.depth
    edge = np.zeros_like(D, bool)
    g = np.maximum(np.abs(np.diff(D, axis=0, prepend=D[:1])), np.abs(np.diff(D, axis=1, prepend=D[:, :1])))
    edge |= g > 0.01 * D
    edge = cv2.dilate(edge.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    sel = cov & ~edge.ravel()
    img1 = v1.image.reshape(-1, 3).astype(np.float64)
    img2 = v2.image.astype(np.float32)

    def err(dx, dy):
        mx = (uv2[:, 0] - 0.5 + dx).reshape(h, w).astype(np.float32)
        my = (uv2[:, 1] - 0.5 + dy).reshape(h, w).astype(np.float32)
        warped = cv2.remap(img2, np.nan_to_num(mx), np.nan_to_num(my), cv2.INTER_LINEAR).reshape(-1, 3)
        return np.abs(warped[sel] - img1[sel]).mean()

    e0 = err(0, 0)
    assert e0 < 6.0
    for dx, dy in ((0.5, 0), (-0.5, 0), (0, 0.5), (0, -0.5)):
        assert err(dx, dy) > 1.3 * e0


def test_deterministic_and_seed_dependent():
    a = render_scene(seed=11, width=W, height=H)
    b = render_scene(seed=11, width=W, height=H)
    c = render_scene(seed=12, width=W, height=H)
    for va, vb in zip(a.views, b.views):
        np.testing.assert_array_equal(va.image, vb.image)
        np.testing.assert_array_equal(va.depth, vb.depth)
        np.testing.assert_array_equal(va.R, vb.R)
        np.testing.assert_array_equal(va.t, vb.t)
    assert a.meta == b.meta
    assert not np.array_equal(a.views[0].image, c.views[0].image)
    assert not np.allclose(a.views[0].t, c.views[0].t)
    assert a.meta["primitives"] != c.meta["primitives"]


def test_noise_and_gain():
    clean = render_scene(seed=5, width=W, height=H)
    noisy = render_scene(seed=5, width=W, height=H, noise_sigma=3.0, gain=(1.0, 1.2))
    n1 = noisy.views[0].image.astype(float) - clean.views[0].image.astype(float)
    assert 2.0 < n1.std() < 4.0
    assert abs(n1.mean()) < 0.5
    ratio = noisy.views[1].image.mean() / clean.views[1].image.mean()
    assert 1.1 < ratio < 1.25
    np.testing.assert_array_equal(noisy.views[1].depth, clean.views[1].depth)
    with pytest.raises(ValueError):
        render_scene(seed=5, width=W, height=H, gain=(1.0,))


def test_n_views_on_arc():
    sc = render_scene(seed=2, width=96, height=72, n_views=4)
    assert [v.name for v in sc.views] == [f"view_{k:03d}.png" for k in range(4)]
    C = np.stack([v.center for v in sc.views])
    steps = np.linalg.norm(np.diff(C, axis=0), axis=1)
    assert steps.max() < 1.6 * steps.min()
    for k in range(3):  # left to right
        assert sc.views[k].R[0] @ (C[k + 1] - C[k]) > 0
    assert all(np.isfinite(v.depth).all() for v in sc.views)


def test_workspace_round_trip(scene, tmp_path):
    out = write_workspace(scene, tmp_path / "ws")
    assert (out / "images" / "view_000.png").exists()
    assert (out / "sparse" / "cameras.txt").exists()
    assert (out / "sparse" / "images.txt").exists()
    assert (out / "sparse" / "points3D.txt").exists()
    assert (out / "gt" / "view_001.depth.npy").exists()
    assert "PINHOLE" in (out / "sparse" / "cameras.txt").read_text()
    back = read_workspace(out)
    assert len(back.views) == len(scene.views)
    for a, b in zip(scene.views, back.views):
        assert a.name == b.name
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_allclose(a.K, b.K, rtol=0, atol=1e-9)
        np.testing.assert_allclose(a.R, b.R, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.t, b.t, rtol=0, atol=1e-12)
    assert back.meta["seed"] == scene.meta["seed"]
    assert back.meta["scene_size"] == pytest.approx(scene.meta["scene_size"])


def test_cli(tmp_path, capsys):
    from sefm_recon.synthetic import main

    assert main([str(tmp_path / "cli"), "--seed", "4", "--width", "64", "--height", "48", "--noise", "1", "--gain", "1", "1.1"]) == 0
    assert str(tmp_path / "cli") in capsys.readouterr().out
    sc = read_workspace(tmp_path / "cli")
    assert sc.views[0].image.shape == (48, 64, 3)
    assert sc.meta["gain"] == [1.0, 1.1]
