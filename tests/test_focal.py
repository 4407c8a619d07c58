"""The focal length from the pair (geometry/focal.py) and the checks of an estimated pose."""

import numpy as np
import pytest

from sefm_recon.geometry.focal import estimate_focal, focal_matrix
from sefm_recon.geometry.two_view import TwoView
from sefm_recon.realgt import rotation


def _F(factor, R, t, size=(640, 480)):
    K = focal_matrix(factor, size)
    return TwoView(K, K, R, np.asarray(t, float) / np.linalg.norm(t)).F


@pytest.mark.parametrize("factor", [0.6, 1.0, 1.9])
def test_the_focal_length_of_a_general_pair_is_found(factor):
    """Axes that neither are parallel nor meet fix the focal length: found to a fraction of a per cent."""
    F = _F(factor, rotation([4.0, -12.0, 3.0]), [-1.0, 0.2, 0.3])
    est = estimate_focal(F, (640, 480), (640, 480))
    assert est.determined
    assert est.factor == pytest.approx(factor, rel=2e-3)


def test_one_known_camera_stays_and_the_other_is_found():
    K1 = focal_matrix(1.4, (640, 480))
    K2 = focal_matrix(0.8, (640, 480))
    R = rotation([4.0, -12.0, 3.0])
    F = TwoView(K1, K2, R, np.array([-1.0, 0.2, 0.3]) / np.linalg.norm([-1.0, 0.2, 0.3])).F
    est = estimate_focal(F, (640, 480), (640, 480), K1=K1)
    assert est.determined and est.factor == pytest.approx(0.8, rel=2e-3)


# Both cameras turned towards each other by 7 deg: axes that meet as far from both cameras.
_R1, _R2 = rotation([0.0, -7.0, 0.0]), rotation([0.0, 7.0, 0.0])


@pytest.mark.parametrize("R, t", [(np.eye(3), [-1.0, 0.0, 0.0]),  # a rectified pair: parallel axes
                                  (_R2 @ _R1.T, _R2 @ [-1.0, 0.0, 0.0])])
def test_a_pair_that_does_not_fix_the_focal_length_says_so(R, t):
    est = estimate_focal(_F(1.2, R, t), (640, 480), (640, 480))
    assert not est.determined


def test_axes_that_meet_nearer_one_camera_fix_the_focal_length():
    """One focal length for both photos: only the symmetric meeting of the axes leaves it open."""
    est = estimate_focal(_F(1.2, rotation([0.0, 10.0, 0.0]), [-1.0, 0.0, 0.2]), (640, 480), (640, 480))
    assert est.determined and est.factor == pytest.approx(1.2, rel=2e-3)


def _cropped_pair(scene, crop):
    """Both views cropped about their centres: the focal length stays, COLMAP's guess (1.2 x the side) shrinks."""
    a, b = scene.views[0], scene.views[1]
    x0, y0, w, h = crop
    Ks = []
    for v in (a, b):
        K = v.K.copy()
        K[0, 2] -= x0
        K[1, 2] -= y0
        Ks.append(K)
    imgs = [np.ascontiguousarray(v.image[y0:y0 + h, x0:x0 + w]) for v in (a, b)]
    R = b.R @ a.R.T
    return imgs, Ks, R, b.t - R @ a.t


def test_a_pair_without_exif_whose_guessed_focal_length_is_far_off():
    """The guess is 26 % short of the true focal length: the pair's own estimate is used, the lines are right."""
    from sefm_recon.config import load_config
    from sefm_recon.geometry.two_view import epipolar_distances
    from sefm_recon.io.cameras import default_camera
    from sefm_recon.pipeline import reconstruct_pair
    from sefm_recon.synthetic import render_scene

    scene = render_scene(seed=11, width=480, height=360, style="classic")
    (im1, im2), (K1, K2), R, t = _cropped_pair(scene, (90, 67, 300, 226))
    assert 1.2 * 300 < 0.8 * K1[0, 0]
    cfg = load_config(None, ["output.mesh=false", "output.progress=false"], internal=True)
    res = reconstruct_pair(im1, im2, default_camera(300, 226, 1), default_camera(300, 226, 2), cfg)
    assert res.notes["focal"]["source"] == "estimated"
    assert res.camera1.mean_focal_length() == pytest.approx(K1[0, 0], rel=0.1)
    d = epipolar_distances(TwoView(K1, K2, R, t / np.linalg.norm(t)).F, res.uv1, res.uv2)
    assert np.median(d) < 0.5


def test_an_ambiguous_geometry_is_refused(small_scene, monkeypatch):
    """A pose that explains few of the matches an independent fundamental matrix fits is an input error."""
    from sefm_recon import pipeline
    from sefm_recon.config import load_config
    from sefm_recon.errors import InputError
    from sefm_recon.geometry import two_view

    true_estimate = two_view.estimate_two_view

    def wrong_pose(*args, **kwargs):  # a pose 60 deg off in its translation direction, as RANSAC can return
        tv = true_estimate(*args, **kwargs)
        tv.t = rotation([0.0, 0.0, 60.0]) @ tv.t
        return tv

    monkeypatch.setattr(pipeline, "estimate_two_view", wrong_pose)
    v1, v2 = small_scene.views[0], small_scene.views[1]
    cfg = load_config(None, ["output.mesh=false", "output.progress=false"], internal=True)
    cams = [v1.camera(1), v2.camera(2)]
    for cam in cams:
        cam.has_prior_focal_length = True  # the true cameras, as given with --camera
    with pytest.raises(InputError, match="geometry of the pair is ambiguous: the relative pose .* explains only 0 %"):
        pipeline.reconstruct_pair(v1.image, v2.image, *cams, cfg)
    cfg.geometry.ransac_max_error = 2.0
    monkeypatch.setattr(pipeline, "estimate_two_view", true_estimate)  # the right pose passes the same check
    res = pipeline.reconstruct_pair(v1.image, v2.image, *cams, cfg)
    assert res.notes["geometry_check"]["explained_share"] > 0.95


def _matches(rng, K, R, t, n, size=(640, 480)):
    """``n`` correspondences of random scene points seen by camera 1 at the origin and camera 2 at (R, t)."""
    xy1 = rng.uniform([20, 20], [size[0] - 20, size[1] - 20], (n, 2))
    X = np.c_[xy1, np.ones(n)] @ np.linalg.inv(K).T * rng.uniform(3.0, 8.0, (n, 1))
    x2 = (X @ R.T + t) @ K.T
    return xy1, x2[:, :2] / x2[:, 2:]


def _poses():
    return [(rotation(r), np.asarray(t, float) / np.linalg.norm(t))
            for r, t in (([2.0, -8.0, 1.0], [-1.0, 0.1, 0.2]), ([-6.0, 3.0, 4.0], [0.3, -1.0, 0.1]),
                         ([5.0, 9.0, -3.0], [0.2, 0.4, -1.0]), ([-3.0, -5.0, 8.0], [1.0, 0.6, 0.3]))]


def test_a_pose_the_matches_determine_survives_their_resampling():
    """150 matches of one pose among 50 random ones: the pose found again from any 80 % keeps its inliers."""
    from sefm_recon.geometry.two_view import estimate_two_view, resampled_consensus

    rng = np.random.default_rng(1)
    K = focal_matrix(1.2, (640, 480))
    (R, t), = _poses()[:1]
    a, b = _matches(rng, K, R, t, 150)
    a = np.r_[a, rng.uniform(0, 640, (50, 2))]
    b = np.r_[b, rng.uniform(0, 480, (50, 2))]
    tv = estimate_two_view(a, b, K, K, (640, 480), (640, 480))
    assert len(tv.kp1) >= 140
    assert resampled_consensus(a, b, tv, (640, 480), (640, 480)) > 0.95


def test_a_chance_consensus_is_refused():
    """Four groups of 30 matches, each of another pose: the pose RANSAC picks is one of four, and
    the poses found again from resampled matches explain other groups: refused, whichever it picks."""
    from sefm_recon import pipeline
    from sefm_recon.errors import InputError
    from sefm_recon.geometry.two_view import estimate_two_view, resampled_consensus

    rng = np.random.default_rng(2)
    K = focal_matrix(1.2, (640, 480))
    groups = [_matches(rng, K, R, t, 30) for R, t in _poses()]
    a, b = np.concatenate([g[0] for g in groups]), np.concatenate([g[1] for g in groups])
    tv = estimate_two_view(a, b, K, K, (640, 480), (640, 480), min_inliers=20)
    assert 25 <= len(tv.kp1) <= 40  # one group's (and a few of the others' by chance)
    assert resampled_consensus(a, b, tv, (640, 480), (640, 480)) < pipeline.CONSENSUS_MIN_SHARE
    with pytest.raises(InputError, match="geometry of the pair is ambiguous: .* is not determined by the matches"):
        pipeline._check_consensus(tv, a, b, (640, 480), (640, 480), 2.0, True)
    with pytest.raises(InputError, match="focal length could not be found: .* give the camera with --camera"):
        pipeline._check_consensus(tv, a, b, (640, 480), (640, 480), 2.0, False)


def test_the_command_line_refuses_a_chance_consensus(small_scene, tmp_path, monkeypatch, capsys):
    """`sefm-recon pair` on SIFT matches of four poses: exit 2, one line that says so, no output."""
    import cv2

    from sefm_recon import cli, pipeline

    v1, v2 = small_scene.views[0], small_scene.views[1]
    paths = []
    for name, v in (("a.png", v1), ("b.png", v2)):
        assert cv2.imwrite(str(tmp_path / name), cv2.cvtColor(v.image, cv2.COLOR_RGB2BGR))
        paths.append(str(tmp_path / name))
    h, w = v1.image.shape[:2]
    K = v1.K
    rng = np.random.default_rng(3)
    groups = [_matches(rng, K, R, t, 30, (w, h)) for R, t in _poses()]
    chance = np.concatenate([g[0] for g in groups]), np.concatenate([g[1] for g in groups])
    monkeypatch.setattr(pipeline, "sift_correspondences", lambda *args, **kwargs: chance)
    cam = f"PINHOLE {w} {h} {K[0, 0]:.9g} {K[1, 1]:.9g} {K[0, 2]:.9g} {K[1, 2]:.9g}"
    out = tmp_path / "out"
    code = cli.main(["pair", *paths, "-o", str(out), "--camera", cam, "-q", "--set", "geometry.min_inliers=20"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and "geometry of the pair is ambiguous" in err[0] and "not determined by the matches" in err[0]
    assert not out.exists()
