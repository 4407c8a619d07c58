import cv2
import numpy as np
import pytest

from sefm_recon.geometry.triangulate import project, reprojection_errors, triangulate
from sefm_recon.geometry.two_view import match_descriptors

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


def test_points_appended_into_the_room_left_after_them():
    """``append_rows`` fills the unwritten rows after a leading slice (as the SGM
    read-back returns its points) without copying it, and concatenates where there is
    no room (a plain array, or more rows than the room)."""
    from sefm_recon.arrays import append_rows

    rng = np.random.default_rng(2)
    X = np.c_[rng.uniform(-2, 2, (50, 2)), rng.uniform(5, 10, 50)]
    Xh = np.empty((60, 3))[:50]
    Xh[:] = X
    more = rng.normal(size=(10, 3))
    both = append_rows(Xh, more)
    assert np.shares_memory(both, Xh) and both.shape == (60, 3)
    np.testing.assert_allclose(both[:50], X, atol=1e-9)
    np.testing.assert_array_equal(both[50:], more)
    over = append_rows(Xh, rng.normal(size=(11, 3)))  # beyond the room: a fresh array
    assert not np.shares_memory(over, Xh) and over.shape == (61, 3)
    np.testing.assert_array_equal(over[:50], Xh)
    plain = np.arange(6.0).reshape(3, 2)
    assert not np.shares_memory(append_rows(plain, plain), plain)
    np.testing.assert_array_equal(append_rows(plain, plain[:1]), np.r_[plain, plain[:1]])


def test_kept_rows_move_to_the_front_in_place_and_still_take_appended_rows():
    """``keep_rows`` keeps the rows in order at the front of the arrays it is given (the
    read-back's leading slices), so that ``append_rows`` still writes after them."""
    from sefm_recon.arrays import append_rows, keep_rows

    rng = np.random.default_rng(3)
    X = rng.normal(size=(50, 3))
    Xh, rows = np.empty((60, 3))[:50], np.empty(60, np.int64)[:50]
    Xh[:], rows[:] = X, np.arange(50)
    keep = rng.random(50) < 0.6
    kh, kr = keep_rows(keep, Xh, rows)
    np.testing.assert_array_equal(kh, X[keep])
    np.testing.assert_array_equal(kr, np.flatnonzero(keep))
    assert np.shares_memory(kh, Xh) and kh.ctypes.data == Xh.ctypes.data
    assert np.shares_memory(append_rows(kh, X[:5]), Xh)


def test_points_behind_a_camera_are_invalid():
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    R, t = np.eye(3), np.array([-1.0, 0, 0])
    uv1 = np.array([[320.0, 240.0]])
    uv2 = np.array([[420.0, 240.0]])  # rays diverge: intersection behind the cameras
    _, valid, _ = triangulate(K, K, R, t, uv1, uv2)
    assert not valid[0]


def _two_view_points(t, seed=0, n=400):
    """Exact correspondences of points 1-20 m ahead, in view, seen by K = f 500 at 640x480 from the origin and
    from ``t`` after a 3 deg turn."""
    rng = np.random.default_rng(seed)
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    X = np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(1, 20, n)]
    X[:, :2] *= 0.5 * X[:, 2:]
    R = cv2.Rodrigues(np.radians([0.0, 3.0, 0.0]))[0]

    def proj(P):
        p = P @ K.T
        return p[:, :2] / p[:, 2:]

    return K, proj(X), proj(X @ R.T + np.asarray(t, float))


def test_a_narrow_baseline_is_a_warning_a_pure_rotation_is_refused(caplog):
    """Median triangulation angle 0.38 deg (below the comfortable 0.5): noisy depth, not wrong; t = 0: no depth."""
    from sefm_recon.errors import InputError
    from sefm_recon.geometry.two_view import estimate_two_view, rotation_parallax, triangulation_angles

    K, a, b = _two_view_points([0.08, 0.0, 0.0])
    with caplog.at_level("WARNING"):
        tv = estimate_two_view(a, b, K, K, (640, 480), (640, 480), min_tri_angle_deg=0.5)
    angle = np.degrees(np.median(triangulation_angles(tv)))
    assert 0.3 < angle < 0.5 and rotation_parallax(tv)[1] > 3.0
    assert "narrow baseline" in caplog.text and "depth will be noisy" in caplog.text
    assert np.degrees(np.arccos(np.clip(tv.t @ [1, 0, 0], -1, 1))) < 1.0  # the right direction
    K, a, b = _two_view_points([0.0, 0.0, 0.0])
    b = b + np.random.default_rng(1).normal(0, 0.3, b.shape)  # SIFT's localisation noise
    with pytest.raises(InputError, match=r"no baseline.*pure rotation of the camera \(by 3\.0 deg\)"):
        estimate_two_view(a, b, K, K, (640, 480), (640, 480))


def test_sift_matching_does_not_depend_on_what_ran_before():
    """FLANN's randomised trees draw from OpenCV's RNG: the matches of one pair of descriptor
    sets must be the same whatever else used that RNG in between."""
    rng = np.random.default_rng(0)
    d1 = rng.random((2000, 128), np.float32)
    d2 = np.clip(d1 + rng.normal(0, 0.35, d1.shape), 0, 1).astype(np.float32)  # ambiguous enough to vary
    first = match_descriptors(d1, d2)
    cv2.randu(np.zeros((100, 100), np.float32), 0, 1)  # another user of OpenCV's RNG
    again = match_descriptors(d1, d2)
    assert len(first) > 500 and np.array_equal(first, again)
