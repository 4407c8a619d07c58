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


@pytest.fixture(scope="session")
def small_scene():
    """A 320x240 generated pair with ground truth (rendered once per session)."""
    from sefm_recon.synthetic import render_scene

    return render_scene(seed=11, width=320, height=240, style="classic")
