"""The SeFM stages on sequences with known answers."""

import cv2
import numpy as np
import pytest

from sefm_recon.matching import dense, rough
from sefm_recon.matching.validity import depth_continuity


def _signal(n, seed=0):
    rng = np.random.default_rng(seed)
    x = np.cumsum(rng.normal(0, 6, n))
    x = np.convolve(x, np.ones(3) / 3, mode="same")
    return (x - x.min()) / (np.ptp(x) + 1e-9) * 200 + 20


def test_intensity_jumps_match_the_paper():
    a = np.array([0, 0, 10, 30, 30, 30], np.float32)
    np.testing.assert_allclose(rough.intensity_jumps(a), [0, 5, 15, 10, 0, 0])
    # one key point per edge (the local maximum), none on flat parts
    np.testing.assert_array_equal(rough.detect_keypoints(a, 4.0), [2])


def test_fft_descriptors_ignore_gain_and_offset_but_not_shape():
    a = _signal(200)
    kp = rough.detect_keypoints(a, 3.0)
    assert len(kp) > 10
    d = rough.fft_descriptors(a, kp)
    d_gain = rough.fft_descriptors(1.3 * a + 15, kp)
    np.testing.assert_allclose(d, d_gain, atol=1e-3)
    d_other = rough.fft_descriptors(a[::-1].copy(), kp)
    assert np.linalg.norm(d - d_other) > 1.0


def test_rough_dp_recovers_a_shift_and_skips_extra_keypoints():
    a = _signal(400, seed=1)
    shift = 17
    b = np.r_[_signal(shift, seed=9), a][:400]  # b[i + shift] = a[i]
    p = rough.detect_keypoints(a, 3.0)
    q = rough.detect_keypoints(b, 3.0)
    pairs = rough.align_keypoints(p, q, rough.fft_descriptors(a, p), rough.fft_descriptors(b, q), max_dist=0.8)
    assert len(pairs) > 0.7 * len(p[p < 400 - shift - 10])
    assert np.all(np.diff(pairs[:, 0]) > 0) and np.all(np.diff(pairs[:, 1]) > 0)  # ordered
    disp = q[pairs[:, 1]] - p[pairs[:, 0]]
    assert np.mean(disp == shift) > 0.95


def test_rough_dp_respects_the_search_band():
    a = _signal(300, seed=2)
    p = rough.detect_keypoints(a, 3.0)
    d = rough.fft_descriptors(a, p)
    lo = np.full(300, 1000)  # nothing allowed
    assert len(rough.align_keypoints(p, p, d, d, 0.8, lo=lo, hi=lo + 5)) == 0
    full = rough.align_keypoints(p, p, d, d, 0.8)
    np.testing.assert_array_equal(full[:, 0], full[:, 1])
    assert len(full) == len(p)


def test_dense_dp_aligns_a_shifted_sequence():
    x = _signal(120, seed=3)
    y = np.r_[x[5:], x[-1] * np.ones(5)]  # y[v] = x[v + 5]: partner of u is u - 5
    v, run, cost = dense.align_segment(x, y, penalty=20.0, band=20)
    u = np.arange(120)
    interior = (u >= 10) & (u < 110)
    np.testing.assert_allclose(v[interior], u[interior] - 5)
    assert np.all(np.diff(v) >= 0)
    assert cost[interior].max() < 1e-3
    assert np.all(run[interior] == 1)


def test_dense_cost_is_sampling_insensitive():
    # y samples x half-way between its samples: the paper's cost sees no mismatch
    x = _signal(100, seed=4)
    y = np.r_[0.5 * (x[:-1] + x[1:]), x[-1]]
    v, _, cost = dense.align_segment(x, y, penalty=20.0, band=10)
    assert np.abs(v[5:-5] - np.arange(5, 95)).max() <= 1
    assert np.median(cost) < 1e-3


def test_dense_dp_marks_occlusions():
    x = _signal(100, seed=5)
    y = np.r_[x[:40], x[60:], x[60:80]]  # x[40:60] is not in y
    v, run, _ = dense.align_segment(x, y, penalty=5.0, band=40)
    assert np.mean(run[42:58] > 2) > 0.8
    assert np.all(run[:35] == 1)


def test_resample_is_linear():
    np.testing.assert_allclose(dense.resample(np.array([0.0, 10.0]), 5), [0, 2.5, 5, 7.5, 10])


def test_depth_continuity_drops_spikes_but_keeps_steps():
    depth = np.r_[np.linspace(5, 5.1, 20), 9.0, np.linspace(5.1, 5.2, 20), np.linspace(3, 3.1, 20)]
    line = np.zeros(len(depth), np.int64)
    keep = depth_continuity(depth, line, jump=0.05, min_run=3)
    assert not keep[20]  # the isolated spike
    assert keep[:20].all() and keep[21:].all()  # both sides of the real step survive
    # runs do not continue across lines
    line2 = np.r_[np.zeros(2, np.int64), np.ones(5, np.int64)]
    np.testing.assert_array_equal(depth_continuity(np.ones(7), line2, 0.05, 3), [False] * 2 + [True] * 5)
    # masked-out points are skipped: the spike masked, the line is one run; a masked point is never kept
    mask = np.ones(len(depth), bool)
    mask[20] = False
    mask[5] = False
    keep = depth_continuity(depth, line, jump=0.05, min_run=3, mask=mask)
    assert not keep[20] and not keep[5]
    assert keep[:5].all() and keep[6:20].all() and keep[21:].all()
    # a run made short by the mask is dropped
    np.testing.assert_array_equal(depth_continuity(np.ones(4), np.zeros(4, np.int64), 0.05, 3,
                                                   mask=np.array([True, False, True, False])), [False] * 4)
    with pytest.raises(ValueError, match="sorted by line"):
        depth_continuity(np.ones(3), np.array([1, 0, 0]), 0.05, 3)


def test_propagation_step_limit_and_window_shift_scale_with_the_photo_size():
    import dataclasses

    from sefm_recon.config import load_config
    from sefm_recon.matching import sefm

    cfg = load_config(None, [])
    step = cfg.dense.propagate_shift_max_step
    assert step > 0
    # an edge spreads over twice the samples at twice the size: half the step between them
    assert sefm.shift_max_step(cfg, 800) == sefm.shift_max_step(cfg, 1000) == step
    assert sefm.shift_max_step(cfg, 2000) == step / 2
    off = dataclasses.replace(cfg, dense=dataclasses.replace(cfg.dense, propagate_shift_max_step=0.0))
    assert sefm.shift_max_step(off, 2000) == np.inf
    # the window is moved farther on larger photos, with the square root of the size
    shift = cfg.dense.propagate_window_shift
    assert shift == 4
    assert sefm.window_shift(cfg, 800) == sefm.window_shift(cfg, 1000) == sefm.window_shift(cfg, 2000) == 4
    assert sefm.window_shift(cfg, 4000) == 6 and sefm.window_shift(cfg, 6000) == 7
    fixed = dataclasses.replace(cfg, rough=dataclasses.replace(cfg.rough, jump_reference_size=0))
    assert sefm.window_shift(fixed, 4000) == 4

def test_jump_threshold_shrinks_with_the_photo_size_and_coarse_levels_keep_it(monkeypatch):
    import dataclasses

    from sefm_recon.config import load_config
    from sefm_recon.geometry.two_view import TwoView
    from sefm_recon.matching import sefm

    cfg = load_config(None, [])
    assert cfg.rough.jump_reference_size == 1000
    assert sefm.jump_threshold(cfg, 800) == sefm.jump_threshold(cfg, 1000) == cfg.rough.jump_threshold
    assert sefm.jump_threshold(cfg, 2000) == cfg.rough.jump_threshold / 2
    off = dataclasses.replace(cfg, rough=dataclasses.replace(cfg.rough, jump_reference_size=0))
    assert sefm.jump_threshold(off, 4000) == cfg.rough.jump_threshold

    seen = []
    monkeypatch.setattr(sefm, "match_pair", lambda c1, c2, tv, ccfg: seen.append((c1.shape, ccfg.rough, ccfg.dense)) or None)
    K = np.array([[1500.0, 0, 1000], [0, 1500, 750], [0, 0, 1]])
    tv = TwoView(K, K, np.eye(3), np.array([-1.0, 0, 0]))
    img = np.zeros((1500, 2000, 3), np.uint8)
    sefm.coarse_level(img, img, tv, cfg)
    (shape, rough_cfg, dense_cfg), = seen
    assert shape[:2] == (375, 500)
    # the 500 px level matches with the 2000 px photo's threshold, not its own
    assert rough_cfg.jump_threshold == cfg.rough.jump_threshold / 2 and rough_cfg.jump_reference_size == 0
    # it only bounds the fine level's search: one direction, whole samples
    assert not dense_cfg.both_directions and not dense_cfg.subpixel and dense_cfg.propagate_passes == 0


def test_refinement_window_keeps_the_centre_line_and_its_nearest_neighbours():
    from sefm_recon.matching.subpixel import inner_channels

    # two neighbours on each side, two colour channels: columns are (line offset, channel)
    I = np.array([[10 * o + c for o in range(-2, 3) for c in range(2)]], np.float32)
    c0, c1 = inner_channels(I, 2, 1)
    np.testing.assert_array_equal(I[:, c0:c1], [[-10, -9, 0, 1, 10, 11]])
    c0, c1 = inner_channels(I, 2, 0)
    np.testing.assert_array_equal(I[:, c0:c1], [[0, 1]])
    assert inner_channels(I, 2, 2) == inner_channels(I, 2, 5) == (0, 10)


def test_prepared_image_equals_the_whole_image_conversion():
    from sefm_recon.matching.sefm import _prepare

    # converted in blocks of rows, blurred in place: the same values as in one go
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (600, 410, 3), dtype=np.uint8)
    want = cv2.GaussianBlur(cv2.cvtColor(img.astype(np.float32), cv2.COLOR_RGB2GRAY), (0, 0), 0.7)
    np.testing.assert_array_equal(_prepare(img, 0.7, False), want)
    np.testing.assert_array_equal(_prepare(img, 0.0, True), img.astype(np.float32))
