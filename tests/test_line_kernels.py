"""The geometry's line kernels (ray angles, line sampling, band search, points) against plain numpy references."""

import numpy as np

from sefm_recon.geometry.epipolar import line_alphas, ray_angles, sample_line_channels
from sefm_recon.geometry.triangulate import points_at_distance, project
from sefm_recon.matching.band import _first_above, _first_at_least, _gallop

from .conftest import LINE_K as K
from .conftest import LINE_SIZE as SIZE
from .conftest import tilted_lines


def test_line_alphas_match_ray_angles():
    R, t, lp = tilted_lines()
    for which, Rc, pts in ((1, np.eye(3), lp.all_points1()), (2, R.T, lp.all_points2())):
        _, ref = ray_angles(K, Rc, lp.basis, pts)
        np.testing.assert_allclose(line_alphas(lp, K, Rc, which), ref, atol=1e-12)


def test_neighbour_channels_sample_the_neighbour_lines_at_the_same_ray_angle():
    R, t, lp = tilted_lines()
    # A linear image: sampled value = a known function of the position, so the
    # samples tell where the kernel looked.
    yy, xx = np.mgrid[0:SIZE[1], 0:SIZE[0]].astype(np.float32)
    img = np.stack([xx + 0.5, yy + 0.5], axis=2)  # value = COLMAP position of the pixel centre
    I = sample_line_channels(img, lp, K, np.eye(3), 1, neighbours=1, neighbour_step=1.0)
    assert I.shape == (lp.offset1[-1], 6)
    centre = lp.all_points1()
    inside = (centre[:, 0] > 3) & (centre[:, 0] < SIZE[0] - 3) & (centre[:, 1] > 3) & (centre[:, 1] < SIZE[1] - 3)
    np.testing.assert_allclose(I[inside, 2:4], centre[inside], atol=1e-3)
    phi_c, a_c = ray_angles(K, np.eye(3), lp.basis, centre[inside])
    for o, cols in ((-1, slice(0, 2)), (1, slice(4, 6))):
        phi, a = ray_angles(K, np.eye(3), lp.basis, I[inside, cols].astype(np.float64))
        d = (phi - phi_c - o * lp.phi_step + np.pi) % (2 * np.pi) - np.pi
        assert np.abs(d).max() < 1e-3 * lp.phi_step + 1e-6  # the neighbour half-plane...
        np.testing.assert_allclose(a, a_c, atol=1e-5)  # ...at the same angle from the baseline
        # ...about one line step away
        step = np.linalg.norm(I[inside, cols] - centre[inside], axis=1)
        assert 0.2 < np.median(step) < 1.5


def test_points_at_distance_lie_on_the_ray_and_project_to_the_epipolar_line():
    K1 = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    K2 = np.array([[520.0, 0, 300], [0, 520, 250], [0, 0, 1]])
    a = 0.1
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    t = np.array([-1.0, 0.05, 0.1])
    rng = np.random.default_rng(0)
    uv1 = rng.uniform([0, 0], [640, 480], (50, 2))
    dist = rng.uniform(2, 10, 50)
    X, uv2 = points_at_distance(np.linalg.inv(K1), K2, R, t, uv1, dist)
    np.testing.assert_allclose(np.linalg.norm(X, axis=1), dist)
    np.testing.assert_allclose(project(K1, np.eye(3), np.zeros(3), X), uv1, atol=1e-9)
    np.testing.assert_allclose(project(K2, R, t, X), uv2, atol=1e-9)


def test_galloping_search_equals_bisection_from_any_guess():
    rng = np.random.default_rng(0)
    for _ in range(3000):
        n = int(rng.integers(1, 40))
        a = np.sort(rng.integers(0, 20, n)).astype(float)  # ties included
        s = int(rng.integers(0, n))
        e = int(rng.integers(s, n + 1))
        v = float(rng.integers(-2, 22)) + float(rng.choice([0.0, 0.5]))
        guess = int(rng.integers(-3, n + 4))  # also outside [s, e]
        assert _gallop(a, s, e, v, guess, False) == _first_at_least(a, s, e, v)
        assert _gallop(a, s, e, v, guess, True) == _first_above(a, s, e, v)
