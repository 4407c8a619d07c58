"""Epipoles and epipolar line pairs on configurations with known answers."""

import cv2
import numpy as np
import pytest

from sefm_recon.geometry.epipolar import epipoles, line_pairs, ray_angles, sample_lines
from sefm_recon.geometry.triangulate import project

from .conftest import rot_y

K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
SIZE = (640, 480)

CONFIGS = {
    # name: (R, camera-2 centre in camera-1 coordinates)
    "sideways (epipole at infinity)": (np.eye(3), np.array([1.0, 0.0, 0.0])),
    "forward (epipole inside)": (np.eye(3), np.array([0.1, 0.05, 1.0])),
    "backward (epipole inside, behind)": (np.eye(3), np.array([0.05, 0.0, -1.0])),
    "converging": (rot_y(-0.2), np.array([1.0, 0.1, 0.2])),
}


def _pose(name):
    R, c2 = CONFIGS[name]
    return R, -R @ c2


def test_epipoles_are_the_other_camera_centre():
    R, t = _pose("forward (epipole inside)")
    e1, e2 = epipoles(K, K, R, t)
    # e1 is camera 2's centre seen from camera 1 (here in front: inside the image)
    np.testing.assert_allclose(e1[:2] / e1[2], project(K, np.eye(3), np.zeros(3), CONFIGS["forward (epipole inside)"][1][None])[0])
    np.testing.assert_allclose(e2[:2] / e2[2], project(K, R, t, np.zeros((1, 3)))[0])
    # F e1 = 0 and e2^T F = 0
    from sefm_recon.geometry.two_view import TwoView

    F = TwoView(K, K, R, t).F
    assert np.linalg.norm(F @ e1) < 1e-9 * np.linalg.norm(F) * np.linalg.norm(e1)
    assert np.linalg.norm(e2 @ F) < 1e-9 * np.linalg.norm(F) * np.linalg.norm(e2)
    _, e2_inf = epipoles(K, K, *_pose("sideways (epipole at infinity)"))
    assert abs(e2_inf[2]) < 1e-12


@pytest.mark.parametrize("name", list(CONFIGS))
def test_corresponding_points_lie_on_corresponding_lines(name):
    R, t = _pose(name)
    lp = line_pairs(K, K, R, t, SIZE, SIZE)
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-2, 2, 3000), rng.uniform(-1.5, 1.5, 3000), rng.uniform(4, 8, 3000)]
    p1 = project(K, np.eye(3), np.zeros(3), X)
    p2 = project(K, R, t, X)
    inside = lambda p: (p[:, 0] > 1) & (p[:, 0] < SIZE[0] - 1) & (p[:, 1] > 1) & (p[:, 1] < SIZE[1] - 1)  # noqa: E731
    ok = inside(p1) & inside(p2) & ((X @ R.T + t)[:, 2] > 0)
    p1, p2 = p1[ok], p2[ok]
    assert len(p1) > 500
    phi1, a1 = ray_angles(K, np.eye(3), lp.basis, p1)
    phi2, a2 = ray_angles(K, R.T, lp.basis, p2)
    np.testing.assert_allclose(np.angle(np.exp(1j * (phi1 - phi2))), 0, atol=1e-9)  # same epipolar plane
    assert np.all(a2 > a1)  # positive depth: camera 2 sees the point further from the baseline direction
    # Each point is within a pixel of the nearest line pair, inside its sampled segment, in both images.
    dphi = np.abs(np.angle(np.exp(1j * (phi1[:, None] - lp.phi[None, :]))))
    line = np.argmin(dphi, axis=1)
    for p, start, step, count in ((p1, lp.start1, lp.step1, lp.count1), (p2, lp.start2, lp.step2, lp.count2)):
        d = step[line] / np.linalg.norm(step[line], axis=1, keepdims=True)
        v = p - start[line]
        across = np.abs(v[:, 0] * d[:, 1] - v[:, 1] * d[:, 0])
        along = np.sum(v * d, axis=1)
        assert across.max() < 1.0
        assert np.all((along > -1.5) & (along < count[line] + 1.5))


@pytest.mark.parametrize("name", list(CONFIGS))
def test_lines_are_dense_and_ordered(name):
    R, t = _pose(name)
    lp = line_pairs(K, K, R, t, SIZE, SIZE, line_spacing=1.0)
    # samples one pixel apart
    np.testing.assert_allclose(np.linalg.norm(lp.step1, axis=1), 1.0)
    np.testing.assert_allclose(np.linalg.norm(lp.step2, axis=1), 1.0)
    # neighbouring lines at most ~1 px apart at their far ends (where they spread most)
    order = np.argsort(lp.phi)
    far1 = lp.start1 + (lp.count1 - 1)[:, None] * lp.step1
    gaps = np.linalg.norm(np.diff(far1[order], axis=0), axis=1)
    assert np.median(gaps) <= 1.05
    # alpha (angle from the baseline) increases along every line in both images
    for pts, off, Rc in ((lp.all_points1(), lp.offset1, np.eye(3)), (lp.all_points2(), lp.offset2, R.T)):
        _, a = ray_angles(K, Rc, lp.basis, pts)
        d = np.diff(a)
        starts = off[1:-1] - 1  # differences across line boundaries are not along a line
        mask = np.ones(len(d), bool)
        mask[starts] = False
        assert np.all(d[mask] > 0)


def test_sampling_stays_inside_the_image():
    R, t = _pose("converging")
    lp = line_pairs(K, K, R, t, SIZE, SIZE)
    for pts in (lp.all_points1(), lp.all_points2()):
        assert pts[:, 0].min() >= 0.5 - 1e-6 and pts[:, 0].max() <= SIZE[0] - 0.5 + 1e-6
        assert pts[:, 1].min() >= 0.5 - 1e-6 and pts[:, 1].max() <= SIZE[1] - 0.5 + 1e-6
    # bilinear sampling reads the pixel value at pixel centres (COLMAP convention)
    img = np.arange(SIZE[0] * SIZE[1], dtype=np.float32).reshape(SIZE[1], SIZE[0])
    vals = sample_lines(img, np.array([[10.5, 20.5]]), np.array([[1.0, 0.0]]), np.array([3]))[:, 0]
    np.testing.assert_allclose(vals, img[20, 10:13], rtol=1e-6)


@pytest.mark.parametrize("model,params", [("PINHOLE", [900.0, 880.0, 401.0, 299.0]),
                                          ("SIMPLE_RADIAL", [900.0, 401.0, 299.0, 0.05])])
def test_working_view_maps_back_to_the_original_pixels(model, params):
    import pycolmap

    from sefm_recon.geometry.undistort import make_working_view

    cam = pycolmap.Camera(model=model, width=800, height=600, params=params)
    image = np.zeros((600, 800, 3), np.uint8)
    view = make_working_view(image, cam, max_size=400)  # half size
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [400, 300], size=(50, 2))
    orig = view.to_original(uv)
    # the working pixel's ray, projected by the original camera (with its distortion)
    rays = np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(view.K).T
    np.testing.assert_allclose(orig, cam.img_from_cam(rays), atol=1e-9)
    if model == "PINHOLE":  # pixel edges scale exactly: the image corner maps to the corner
        np.testing.assert_allclose(view.to_original(np.array([[400.0, 300.0]])), [[800.0, 600.0]], atol=1e-9)


def test_sift_upsamples_small_photos_only():
    """COLMAP's octave -1 on a small photo finds the fine features octave 0 misses; large ones are not upsampled."""
    from sefm_recon.geometry.two_view import extract_sift
    from sefm_recon.synthetic import render_scene

    img = render_scene(seed=5, width=320, height=240, style="classic").views[0].image
    gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    at0, _ = extract_sift(gray, 8192, 0, upsample_max_size=0)
    up, _ = extract_sift(gray, 8192, 0, upsample_max_size=320)
    assert len(up) > 1.5 * len(at0), (len(up), len(at0))
    same, _ = extract_sift(gray, 8192, 0, upsample_max_size=319)  # longer than the limit: octave 0
    assert len(same) == len(at0)


@pytest.mark.parametrize("fork", ["child", "fork fails", "child fails"])
def test_sift_of_a_pair_side_by_side_is_each_image_s_own(monkeypatch, fork):
    """Image 2's SIFT in a child process gives its own features exactly; where no child can run
    or the child gives nothing, image 2 is done in this process with the same result."""
    import os

    import sefm_recon.forked as forked
    import sefm_recon.geometry.two_view as two_view
    from sefm_recon.synthetic import render_scene

    views = render_scene(seed=5, width=480, height=360, style="classic").views
    g1, g2 = (cv2.cvtColor(v.image, cv2.COLOR_RGB2GRAY) for v in views[:2])
    expected = [two_view.extract_sift(g, 8192, 400, 0) for g in (g1, g2)]
    monkeypatch.setattr(forked, "can_fork", lambda: True)
    if fork == "fork fails":
        def no_fork():
            raise OSError("no process")
        monkeypatch.setattr(os, "fork", no_fork)
    if fork == "child fails":  # the child dies before it writes (here: its SIFT raises)
        real = two_view._colmap_sift
        parent = os.getpid()

        def failing(*args):
            if os.getpid() != parent:
                raise RuntimeError("child")
            return real(*args)
        monkeypatch.setattr(two_view, "_colmap_sift", failing)
    got = two_view.extract_sift_pair(g1, g2, 8192, 400, 0)
    for (xy, desc), (xy_e, desc_e) in zip(got, expected):
        np.testing.assert_array_equal(xy, xy_e)
        np.testing.assert_array_equal(desc, desc_e)
