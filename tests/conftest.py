import os
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("GLOG_minloglevel", "2")

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "data_samples" / "scene"
REAL = ROOT.parent / "shared" / "data" / "real"


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def two_view(R, t, f=300.0, w=320, h=240):
    """The geometry of two cameras with the same K (focal ``f``, principal point at the centre
    of a ``w`` x ``h`` image), camera 2 at ``R``, ``t`` (x_cam2 = R x_cam1 + t), no SIFT points."""
    from sefm_recon.geometry.two_view import TwoView

    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    return TwoView(K, K, np.asarray(R, float), np.asarray(t, float), np.zeros((0, 2)), np.zeros((0, 2)), 0)


#: Camera and image size of the line-pair tests' pair (:func:`tilted_lines`).
LINE_K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
LINE_SIZE = (640, 480)


def tilted_lines():
    """``R, t`` and the epipolar line pairs of two LINE_K cameras, the second turned 0.15 rad and moved sideways."""
    from sefm_recon.geometry.epipolar import line_pairs

    R = rot_y(-0.15)
    t = -R @ np.array([1.0, 0.1, 0.2])
    return R, t, line_pairs(LINE_K, LINE_K, R, t, LINE_SIZE, LINE_SIZE)


def grid_bounds(lp, gmin, gmax, scale, depths):
    """Reference: each line-1 sample's distance range from the grid cell under it, else ``depths`` (numpy)."""
    pts = lp.all_points1()
    H, W = gmin.shape
    c = np.clip(np.floor(pts[:, 0] * scale[0]).astype(int), 0, W - 1)
    r = np.clip(np.floor(pts[:, 1] * scale[1]).astype(int), 0, H - 1)
    known = np.isfinite(gmin[r, c])
    return (np.where(known, gmin[r, c], depths[0]).astype(np.float64),
            np.where(known, gmax[r, c], depths[1]).astype(np.float64))


@pytest.fixture(scope="session")
def small_scene():
    """A 320x240 generated pair with ground truth (rendered once per session)."""
    from sefm_recon.synthetic import render_scene

    return render_scene(seed=11, width=320, height=240, style="classic")
