import numpy as np

from sefm_recon.geometry.triangulate import project, reprojection_errors, triangulate

from .conftest import rot_y


def test_triangulation_of_known_points():
    rng = np.random.default_rng(1)
    K1 = np.array([[800.0, 0, 400], [0, 800, 300], [0, 0, 1]])
    K2 = np.array([[700.0, 0, 330], [0, 710, 260], [0, 0, 1]])
    R, t = rot_y(0.2), np.array([-1.0, 0.1, 0.2])
    X = np.c_[rng.uniform(-2, 2, 200), rng.uniform(-2, 2, 200), rng.uniform(5, 10, 200)]
    uv1, uv2 = project(K1, np.eye(3), np.zeros(3), X), project(K2, R, t, X)
    Xh, valid, angle = triangulate(K1, K2, R, t, uv1, uv2)
    assert valid.all()
    np.testing.assert_allclose(Xh, X, atol=1e-9)
    assert reprojection_errors(K1, K2, R, t, uv1, uv2, Xh).max() < 1e-9
    assert np.all(angle > 0)


def test_points_behind_a_camera_are_invalid():
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    R, t = np.eye(3), np.array([-1.0, 0, 0])
    uv1 = np.array([[320.0, 240.0]])
    uv2 = np.array([[420.0, 240.0]])  # rays diverge: intersection behind the cameras
    _, valid, _ = triangulate(K, K, R, t, uv1, uv2)
    assert not valid[0]
