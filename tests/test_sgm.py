"""Polar line images (matching/lines.py) and semi-global matching over them (matching/sgm.py)."""

import numpy as np
import pytest

from sefm_recon.config import load_config
from sefm_recon.evaluate import covisibility_mask, evaluate_matches
from sefm_recon.geometry.epipolar import ray_angles
from sefm_recon.geometry.two_view import TwoView
from sefm_recon.matching.lines import line_grid, line_images, project, rays
from sefm_recon.matching.sgm import parallax_columns
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


def test_rows_are_at_most_the_row_spacing_apart():
    tv = _two_view(rot_y(0.2), [-1.0, 0.1, 0.2])
    grid = line_grid(tv, (320, 240), (320, 240))
    grid.pad = 0
    alpha = grid.alpha(np.arange(grid.columns))
    for K, Rc in ((tv.K1, np.eye(3)), (tv.K2, tv.R.T)):
        u, v, _ = project(K, Rc, rays(grid.basis, grid.phi[:, None], alpha[None, :]))
        inside = (u >= 0) & (u < 320) & (v >= 0) & (v < 240)
        du, dv = np.diff(u, axis=0)[:, :-1], np.diff(v, axis=0)[:, :-1]  # to the next row
        tu, tv_ = np.diff(u, axis=1)[:-1], np.diff(v, axis=1)[:-1]  # along the row
        gap = np.abs(du * tv_ - dv * tu) / np.hypot(tu, tv_)  # distance between the lines
        both = (inside[1:] & inside[:-1])[:, :-1] & inside[:-1, 1:]
        assert gap[both].max() <= 0.8 + 1e-3 and gap[both].max() > 0.4


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
    assert 0.7 < abs(un - u1) < 0.9  # about 0.8 px a column
    _, a2 = ray_angles(tv.K2, np.eye(3), grid.basis, np.array([[u1 - 10, v1]]))
    c2 = float(grid.column(a2)[0])
    assert abs((c - c2) * abs(un - u1) - 10) < 0.2  # 10 px in columns of that width
    # the same texture: interpolate row r of L2 at c2
    left = int(np.floor(c2))
    value2 = L2[r, left] * (left + 1 - c2) + L2[r, left + 1] * (c2 - left)
    assert abs(value2 - float(L1[r, c])) < 3
    assert abs(float(L2[r, left - 3]) - float(L1[r, c])) > abs(value2 - float(L1[r, c]))


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


def test_one_match_per_pixel_keeps_the_consensus_of_its_samples():
    from sefm_recon.matching.sgm import one_per_pixel

    uv1 = np.array([[10.2, 5.5], [10.5, 5.5], [10.8, 5.4], [3.5, 3.5], [12.5, 5.5]])
    uv2 = uv1 + np.array([[-4.0, 0], [-4.1, 0], [-9.0, 0], [-2.0, 0], [-4.0, 0]])  # the third one is an outlier
    keep = one_per_pixel(uv1, uv2, (20, 10))
    assert keep.tolist() == [1, 3, 4]  # pixel (10, 5): the sample nearest the mean displacement


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
