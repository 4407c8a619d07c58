"""Line matches to pixel pairs and points (matching/points.py)."""

import numpy as np

from sefm_recon.matching.points import PairGeometry, line_matches_to_points, sample_points

from .conftest import LINE_K as K
from .conftest import tilted_lines


def test_sample_points_are_those_of_the_line_matches():
    R, t, lp = tilted_lines()
    rng = np.random.default_rng(3)
    n = int(lp.offset1[-1])
    j = np.where(rng.random(n) < 0.3, rng.uniform(0, 50, n), np.nan)
    start1, step1, off1 = lp.side(1)
    start2, step2, _ = lp.side(2)
    Kinv = np.linalg.inv(K)
    Rt = np.ascontiguousarray(R.T)
    c2 = -Rt @ np.asarray(t, np.float64)
    geo = PairGeometry(start1, step1, off1, start2, step2, Kinv, Kinv, Rt, c2)
    idx, line, uv1, _, _, dist, valid = line_matches_to_points(j, np.zeros(n), 1.0, geo, 0.0, False)
    pick = np.sort(rng.choice(len(idx), 500, replace=False))
    got = sample_points(idx[pick], line[pick], j, geo, 0.0)
    np.testing.assert_array_equal(got[0], uv1[pick])
    np.testing.assert_array_equal(got[1], dist[pick])
    np.testing.assert_array_equal(got[2], valid[pick])
