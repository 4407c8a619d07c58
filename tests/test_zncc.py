"""Window correlation along a line pair (matching/zncc.py) against plain numpy references."""

import numpy as np
import pytest

from sefm_recon.matching.zncc import zncc, zncc3, zncc_search


@pytest.mark.parametrize("jpos", [20.0, 20.3, 35.75])
def test_three_zncc_in_one_pass_equal_three_single_ones(jpos):
    rng = np.random.default_rng(1)
    a = rng.normal(size=(60, 3)).astype(np.float32)
    b = rng.normal(size=(60, 3)).astype(np.float32)
    got = zncc3(a, 25, b, jpos, 5)
    want = [zncc(a, 25, b, jpos + d, 5) for d in (-1.0, 0.0, 1.0)]
    np.testing.assert_allclose(got, want, atol=1e-9)


def _zncc_ref(a, i, b, jpos, s_lo, s_hi):
    """ZNCC over window offsets s_lo..s_hi, b linearly interpolated at jpos + s (numpy reference)."""
    s = np.arange(s_lo, s_hi + 1)
    x = a[i + s].ravel().astype(float)
    j0 = int(np.floor(jpos))
    f = jpos - j0
    y = ((1 - f) * b[j0 + s] + f * b[np.minimum(j0 + s + 1, len(b) - 1)]).ravel().astype(float)
    x -= x.mean()
    y -= y.mean()
    return float(x @ y / np.sqrt((x @ x) * (y @ y)))


@pytest.mark.parametrize("i, jpos, s_lo, s_hi", [
    (2, 20.3, -2, 5),    # window cut at the start of line 1
    (25, 1.4, 0, 5),     # at the start of line 2 (jpos - 1 + s >= 0)
    (25, 55.6, -5, 2),   # at the end of line 2 (jpos + 1 + s < 59)
])
def test_zncc_near_line_ends_uses_the_cut_window(i, jpos, s_lo, s_hi):
    rng = np.random.default_rng(3)
    a = rng.normal(size=(60, 3)).astype(np.float32)
    b = rng.normal(size=(60, 3)).astype(np.float32)
    got = zncc3(a, i, b, jpos, 5)
    want = [_zncc_ref(a, i, b, jpos + d, s_lo, s_hi) for d in (-1.0, 0.0, 1.0)]
    np.testing.assert_allclose(got, want, atol=1e-6)


def test_zncc_window_too_short_near_a_line_end_is_rejected():
    rng = np.random.default_rng(4)
    a = rng.normal(size=(60, 2)).astype(np.float32)
    b = rng.normal(size=(60, 2)).astype(np.float32)
    # fewer than half + 1 = 6 samples fit: i = 59 leaves offsets -5..0, but line 2 ends at jpos + 0
    assert zncc3(a, 59, b, 59.0, 5)[1] == -2.0
    assert zncc(a, 59, b, 59.0, 5) == -2.0  # single ZNCC (search, fill) needs the whole window
    assert zncc(a, 0, b, 30.0, 5) == -2.0
    assert zncc(a, 30, b, 30.0, 5) > -2.0


def test_shifted_window_matches_a_sample_next_to_a_depth_edge():
    # line 1: foreground texture up to sample 49, background from 50; in line 2
    # the foreground moved by 2 samples and the background by 6 (4 occluded)
    rng = np.random.default_rng(7)
    fg = rng.normal(size=(80, 3))
    bg = rng.normal(size=(120, 3))
    a = np.concatenate([fg[:50], bg[50:110]]).astype(np.float32)
    b = np.empty((116, 3), np.float32)
    b[2:52] = fg[:50]  # b[k] = fg[k - 2]
    b[:2] = rng.normal(size=(2, 3))
    b[52:56] = rng.normal(size=(4, 3))  # background seen only in view 2
    b[56:116] = bg[50:110]  # b[k] = bg[k - 6]
    i = 51  # background, one sample from the edge: its partner is 57
    centred, _ = zncc_search(a, i, b, 54.0, 7, 3, 0.98, 0)
    shifted, pos = zncc_search(a, i, b, 54.0, 7, 3, 0.98, 3)
    assert centred < 0.98 < shifted and pos == pytest.approx(57.0, abs=0.5)
    # inside the background, the centred window already does it (and is kept)
    z, pos = zncc_search(a, 80, b, 83.0, 7, 3, 0.98, 3)
    assert z > 0.99 and pos == pytest.approx(86.0, abs=0.5)


def test_shifted_window_does_not_cross_an_intensity_step():
    # line 1: background up to sample 49, a bright foreground from 50; in line 2
    # the foreground moved by -6 samples and the background by -2, so background
    # samples 46-49 are hidden behind the foreground in view 2
    rng = np.random.default_rng(3)
    bg = rng.normal(size=(60, 3))
    fg = rng.normal(size=(120, 3)) + 6.0  # a step of 6 on a texture of 1
    a = np.concatenate([bg[:50], fg[50:110]]).astype(np.float32)
    b = np.concatenate([bg[2:46], fg[50:110]]).astype(np.float32)  # b[k] = bg[k + 2] (k < 44), fg[k + 6]
    i = 49  # occluded in view 2
    # moved 3 samples into the foreground (windows of 5), the window finds the
    # foreground's partner: the hidden sample would take the foreground's depth
    centred, _ = zncc_search(a, i, b, 40.0, 7, 2, 0.98, 0)
    z, pos = zncc_search(a, i, b, 40.0, 7, 2, 0.98, 3)
    assert centred < 0.98 < z and pos == pytest.approx(43.0, abs=0.5)
    # with the step limit it is not moved across the edge, and stays unmatched
    z, _ = zncc_search(a, i, b, 40.0, 7, 2, 0.98, 3, 4.0)
    assert z < 0.98
    # a foreground sample next to the edge still moves its window into the foreground
    z, pos = zncc_search(a, 50, b, 40.0, 7, 2, 0.98, 3, 4.0)
    assert z > 0.98 and pos == pytest.approx(44.0, abs=0.5)
