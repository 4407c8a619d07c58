"""Camera files read into COLMAP's conventions (io/cameras.py)."""

import numpy as np

from sefm_recon.io.cameras import read_strecha_camera


def test_a_strecha_camera_file_projects_as_colmap_does(tmp_path):
    """x ~ K R^T (X - C) with integer pixel centres in the file; COLMAP's x = K (R X + t) with centres at .5."""
    K = np.array([[800.0, 0, 319.5], [0, 810.0, 239.5], [0, 0, 1]])
    a = np.radians(20.0)
    R_c2w = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    C = np.array([1.0, -2.0, 0.5])
    rows = [*K, [0, 0, 0], *R_c2w, C, [640, 480]]
    path = tmp_path / "0000.jpg.camera"
    path.write_text("\n".join(" ".join(f"{x:.12g}" for x in r) for r in rows))
    Kc, R, t, size = read_strecha_camera(path)
    X = np.array([0.3, 0.2, 6.0])
    x_file = K @ R_c2w.T @ (X - C)
    x_colmap = Kc @ (R @ X + t)
    np.testing.assert_allclose(x_colmap[:2] / x_colmap[2], x_file[:2] / x_file[2] + 0.5)
    assert size == (640, 480)
