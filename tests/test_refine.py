import numpy as np

from sefm_recon.geometry.refine import GRID_CELLS, grid_subset


def test_grid_subset_keeps_the_most_confident_match_of_each_cell():
    rng = np.random.default_rng(3)
    w, h = 400, 300
    cell = np.sqrt(w * h / GRID_CELLS)  # 7.75 px, under MIN_CELL_PX: cells of 8 px
    uv = rng.uniform([0, 0], [w, h], (20000, 2))
    score = rng.integers(0, 5, len(uv)).astype(np.float32)  # many ties: the first of them is kept
    idx = grid_subset(uv, score, (w, h))
    key = np.floor(uv / max(cell, 8.0)).astype(int)
    cells = {}
    for i, k in enumerate(map(tuple, key)):
        if k not in cells or score[i] > score[cells[k]]:
            cells[k] = i
    assert sorted(idx.tolist()) == sorted(cells.values())
    # x-major cell order, as the tracks are handed to RANSAC
    assert [tuple(key[i]) for i in idx] == sorted(cells)


def test_grid_subset_of_no_match_is_empty():
    assert len(grid_subset(np.zeros((0, 2)), np.zeros(0), (100, 100))) == 0


def test_the_pose_from_the_tracks_is_refined_over_their_inliers(monkeypatch):
    """RANSAC's pose from the tracks is refined over its inliers as the SIFT pose is
    (``two_view.refine_on_inliers``): a RANSAC pose 1 deg off comes back to the pose RANSAC's
    own refines to (within 0.02 deg; both 0.15-0.2 deg from the truth, what the tracks'
    0.3 px of noise allows)."""
    import cv2
    import pycolmap

    from sefm_recon.geometry.refine import DenseTracks, pose_change_deg, refine_pose
    from sefm_recon.geometry.two_view import TwoView

    rng = np.random.default_rng(0)
    K = np.array([[400.0, 0, 160], [0, 400, 120], [0, 0, 1]])
    R = cv2.Rodrigues(np.radians([1.0, -6.0, 0.5]))[0]
    t = np.array([0.5, 0.02, 0.05])
    X = np.c_[rng.uniform(-2, 2, 500), rng.uniform(-1.5, 1.5, 500), rng.uniform(4, 10, 500)]

    def project(P):
        x = P @ K.T
        return x[:, :2] / x[:, 2:] + rng.normal(0, 0.3, (len(P), 2))

    xy1, xy2 = project(X), project(X @ R.T + t)
    real = pycolmap.estimate_calibrated_two_view_geometry

    def off(*args, **kwargs):  # RANSAC's answer, its pose turned 1 deg
        tvg = real(*args, **kwargs)
        pose = tvg.cam2_from_cam1
        tvg.cam2_from_cam1 = pycolmap.Rigid3d(
            pycolmap.Rotation3d(cv2.Rodrigues(np.radians([1.0, 0, 0]))[0] @ pose.rotation.matrix()), pose.translation)
        return tvg

    tracks, tv = DenseTracks(xy1, xy2, len(xy1)), TwoView(K, K, R, t)
    best = refine_pose(tv, tracks, (320, 240), (320, 240))
    monkeypatch.setattr(pycolmap, "estimate_calibrated_two_view_geometry", off)
    new = refine_pose(tv, tracks, (320, 240), (320, 240))
    err = pose_change_deg(best, new)
    assert err[0] < 0.02 and err[1] < 0.02, err
    assert max(pose_change_deg(tv, new)) < 0.3
