"""Property-based tests (hypothesis) of the matcher's kernels, line sampling and triangulation.

Random inputs of every shape the stages can meet, including the degenerate ones
(empty sequences, flat signals, zero bands, parallel rays): the kernels never
crash, their outputs keep their contracts, and no non-finite point can reach a PLY.
Example counts are modest so the file runs in well under a minute.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from sefm_recon.geometry.epipolar import line_pairs, sample_lines
from sefm_recon.geometry.triangulate import triangulate
from sefm_recon.matching import dense, rough

SETTINGS = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True)

finite = st.floats(0.0, 255.0, allow_nan=False, allow_infinity=False, width=32)


@st.composite
def increasing(draw, max_len=30, max_pos=200):
    """Strictly increasing int64 positions (possibly empty)."""
    pos = draw(st.lists(st.integers(0, max_pos), max_size=max_len, unique=True))
    return np.array(sorted(pos), np.int64)


def _reference_score(p, q, d1, d2, lo, hi, max_dist):
    """Plain-Python LCS-like DP: best total similarity of an ordered matching."""
    m, n = len(p), len(q)
    S = np.zeros((m + 1, n + 1))
    for i in range(1, m + 1):
        for j in range(1, n + 1):
            best = max(S[i - 1, j], S[i, j - 1])
            if lo[p[i - 1]] <= q[j - 1] <= hi[p[i - 1]]:
                dist = float(np.linalg.norm(d1[i - 1].astype(np.float64) - d2[j - 1]))
                if dist < max_dist:
                    best = max(best, S[i - 1, j - 1] + max_dist - dist)
            S[i, j] = best
    return S[m, n]


# ------------------------------------------------------------------ rough DP


def _reference_pairs(p, q, d1, d2, lo, hi, max_dist):
    """The full-table DP with its back-pointers (row above, then left, then the pair, each on a strict gain)."""
    m, n = len(p), len(q)
    S = np.zeros((m + 1, n + 1), np.float32)
    B = np.zeros((m + 1, n + 1), np.int8)
    for i in range(1, m + 1):
        for j in range(1, n + 1):
            best, b = float(S[i - 1, j]), 1
            if S[i, j - 1] > best:
                best, b = float(S[i, j - 1]), 2
            if lo[p[i - 1]] <= q[j - 1] <= hi[p[i - 1]]:
                diff = d1[i - 1] - d2[j - 1]  # float32, as the kernel
                d2sum = 0.0
                for c in range(len(diff)):
                    d2sum += float(diff[c]) * float(diff[c])
                    if d2sum >= max_dist * max_dist:
                        break
                if d2sum < max_dist * max_dist:
                    cand = float(S[i - 1, j - 1]) + (max_dist - np.sqrt(d2sum))
                    if cand > best:
                        best, b = cand, 0
            S[i, j], B[i, j] = best, b
    out, i, j = [], m, n
    while i > 0 and j > 0:
        if B[i, j] == 0:
            out.append((i - 1, j - 1))
            i, j = i - 1, j - 1
        elif B[i, j] == 1:
            i -= 1
        else:
            j -= 1
    return np.array(out[::-1], np.int64).reshape(-1, 2)




@settings(max_examples=150, **SETTINGS)
@given(p=increasing(), q=increasing(), dim=st.integers(1, 8), max_dist=st.floats(0.0, 3.0),
       seed=st.integers(0, 2**32 - 1), banded=st.booleans())
def test_rough_alignment_is_ordered_in_range_and_optimal(p, q, dim, max_dist, seed, banded):
    rng = np.random.default_rng(seed)
    d1 = rng.normal(size=(len(p), dim)).astype(np.float32) * 0.5
    d2 = rng.normal(size=(len(q), dim)).astype(np.float32) * 0.5
    if len(q) and len(p) and rng.random() < 0.5:  # some exact partners
        k = min(len(p), len(q))
        d2[:k] = d1[:k]
    lo = hi = None
    if banded:
        n1 = int(p.max()) + 1 if len(p) else 1
        lo = rng.integers(-5, 200, n1)
        hi = lo + rng.integers(-10, 120, n1)  # hi < lo: an empty band
    pairs = rough.align_keypoints(p, q, d1, d2, max_dist, lo=lo, hi=hi)
    pairs = np.asarray(pairs)
    assert pairs.ndim == 2 and pairs.shape[1] == 2
    assert len(pairs) <= min(len(p), len(q))
    if len(pairs) == 0:
        return
    i, j = pairs[:, 0], pairs[:, 1]
    assert i.min() >= 0 and i.max() < len(p) and j.min() >= 0 and j.max() < len(q)
    assert np.all(np.diff(i) > 0) and np.all(np.diff(j) > 0)  # ordered, one-to-one
    dist = np.linalg.norm(d1[i].astype(np.float64) - d2[j], axis=1)
    assert np.all(dist < max_dist + 1e-5)
    if banded:
        assert np.all((q[j] >= lo[p[i]]) & (q[j] <= hi[p[i]]))
    # The DP is optimal: its matching scores as much as the reference DP's best.
    if len(p) <= 15 and len(q) <= 15:
        lo_r = lo if banded else np.zeros(int(p.max()) + 1, np.int64)
        hi_r = hi if banded else np.full(int(p.max()) + 1, 10**9, np.int64)
        score = float(np.sum(max_dist - dist))
        assert score == pytest.approx(_reference_score(p, q, d1, d2, lo_r, hi_r, max_dist), rel=1e-4, abs=1e-4)


@settings(max_examples=150, **SETTINGS)
@given(p=increasing(), q=increasing(), dim=st.integers(1, 4), seed=st.integers(0, 2**32 - 1),
       banded=st.booleans())
def test_rough_alignment_row_update_equals_the_full_table(p, q, dim, seed, banded):
    # The kernel keeps one row of the table; its pairs are the full table's,
    # ties included (repeated descriptors make many equal scores).
    rng = np.random.default_rng(seed)
    d1 = rng.integers(0, 3, size=(len(p), dim)).astype(np.float32) * 0.25
    d2 = rng.integers(0, 3, size=(len(q), dim)).astype(np.float32) * 0.25
    n1 = int(p.max()) + 1 if len(p) else 1
    if banded:
        lo = rng.integers(-5, 200, n1)
        hi = lo + rng.integers(-10, 120, n1)
    else:
        lo, hi = np.zeros(n1, np.int64), np.full(n1, 10**9, np.int64)
    pairs = np.asarray(rough.align_keypoints(p, q, d1, d2, 0.6, lo=lo, hi=hi)).reshape(-1, 2)
    np.testing.assert_array_equal(pairs, _reference_pairs(p, q, d1, d2, lo, hi, 0.6))


@settings(max_examples=100, **SETTINGS)
@given(a=arrays(np.float32, st.integers(0, 120), elements=finite), threshold=st.floats(0.0, 50.0),
       radius=st.integers(1, 12), ncoef=st.integers(1, 8))
def test_keypoints_and_descriptors_on_any_sequence(a, threshold, radius, ncoef):
    kp = np.asarray(rough.detect_keypoints(a, threshold))
    assert kp.ndim == 1 and np.all(np.diff(kp) > 0)
    if len(kp):
        assert kp.min() >= 1 and kp.max() <= len(a) - 2
        da = np.asarray(rough.intensity_jumps(a))
        assert np.all(da[kp] > threshold)
    desc = np.asarray(rough.fft_descriptors(a, kp, radius, ncoef))
    assert desc.shape[0] == len(kp) and desc.shape[1] % (2 * ncoef) == 0
    assert np.all(np.isfinite(desc))
    if len(kp):
        assert np.all(np.linalg.norm(desc, axis=1) <= 1.0 + 1e-4)  # unit energy at most


# ------------------------------------------------------------------ dense DP


@settings(max_examples=150, **SETTINGS)
@given(L=st.integers(1, 60), C=st.integers(1, 3), penalty=st.floats(0.0, 100.0), band_frac=st.floats(0.0, 1.2),
       seed=st.integers(0, 2**32 - 1), related=st.booleans())
def test_dense_alignment_is_a_monotone_path_in_the_band(L, C, penalty, band_frac, seed, related):
    rng = np.random.default_rng(seed)
    x = rng.uniform(0, 255, (L, C)).astype(np.float32)
    if related:  # y: a shifted, noisy copy of x (what the matcher usually sees)
        y = np.roll(x, int(rng.integers(-3, 4)), axis=0) + rng.normal(0, 2, (L, C)).astype(np.float32)
    else:
        y = rng.uniform(0, 255, (L, C)).astype(np.float32)
    if rng.random() < 0.2:
        x[:] = x[0]  # a flat segment
    band = int(band_frac * L)
    v, run, cost = dense.align_segment(x, y, penalty=penalty, band=band)
    v, run, cost = np.asarray(v), np.asarray(run), np.asarray(cost)
    assert v.shape == run.shape == cost.shape == (L,)
    assert np.all(np.isfinite(v)) and np.all(np.isfinite(cost))  # equal lengths: every sample is on the path
    # v is the mean partner of each u on a monotone path from (0, 0) to (L-1, L-1)
    assert np.all((v >= 0) & (v <= L - 1))
    assert np.all(np.diff(v) >= -1e-9)
    assert np.all(np.abs(v - np.arange(L)) <= band + 1e-9)  # and stays in the band
    assert np.all(run >= 1) and np.all(cost >= 0)


@settings(max_examples=100, **SETTINGS)
@given(seq=arrays(np.float32, st.integers(2, 50), elements=finite), length=st.integers(2, 120))
def test_resample_keeps_ends_and_range(seq, length):
    out = np.asarray(dense.resample(seq, length))
    assert out.shape == (length,)
    assert out[0] == pytest.approx(seq[0], abs=1e-3) and out[-1] == pytest.approx(seq[-1], abs=1e-3)
    assert np.all(out >= seq.min() - 1e-3) and np.all(out <= seq.max() + 1e-3)


# ---------------------------------------------------------- line-pair sampling


def _rotation(axis, angle):
    import cv2

    axis = np.asarray(axis, float)
    axis /= np.linalg.norm(axis)
    return cv2.Rodrigues(axis * angle)[0]


@st.composite
def two_cameras(draw):
    """Random cameras (focal length, principal point, size) and a relative pose with a baseline."""
    cams = []
    for _ in range(2):
        w = draw(st.integers(64, 240))
        h = draw(st.integers(64, 240))
        f = draw(st.floats(0.4, 3.0)) * max(w, h)
        cx = draw(st.floats(0.3, 0.7)) * w
        cy = draw(st.floats(0.3, 0.7)) * h
        cams.append((np.array([[f, 0, cx], [0, f * draw(st.floats(0.9, 1.1)), cy], [0, 0, 1.0]]), (w, h)))
    axis = draw(st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda a: np.linalg.norm(a) > 0.1))
    R = _rotation(axis, draw(st.floats(0.0, 0.8)))
    c2 = np.array(draw(st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda a: np.linalg.norm(a) > 0.05)))
    return cams, R, -R @ c2


def _bilinear(img, pts):
    """Reference bilinear sampling at COLMAP positions (clamped at the borders)."""
    h, w = img.shape
    x = np.clip(pts[:, 0] - 0.5, 0, w - 1)
    y = np.clip(pts[:, 1] - 0.5, 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(int), w - 2)
    y0 = np.minimum(np.floor(y).astype(int), h - 2)
    fx, fy = x - x0, y - y0
    return ((1 - fy) * ((1 - fx) * img[y0, x0] + fx * img[y0, x0 + 1])
            + fy * ((1 - fx) * img[y0 + 1, x0] + fx * img[y0 + 1, x0 + 1]))


@settings(max_examples=60, **SETTINGS)
@given(cfg=two_cameras(), spacing=st.sampled_from([1.0, 2.0]), seed=st.integers(0, 1000))
def test_line_samples_never_leave_the_images(cfg, spacing, seed):
    (K1, size1), (K2, size2) = cfg[0]
    R, t = cfg[1], cfg[2]
    lp = line_pairs(K1, K2, R, t, size1, size2, line_spacing=spacing, sample_spacing=spacing, max_lines=4000)
    assert len(lp.count1) == len(lp.count2) == len(lp)
    rng = np.random.default_rng(seed)
    for which, (w, h), K in ((1, size1, K1), (2, size2, K2)):
        count = lp.count1 if which == 1 else lp.count2
        assert np.all(count >= 1)
        pts = lp.all_points1() if which == 1 else lp.all_points2()
        assert len(pts) == count.sum()
        if len(pts) == 0:
            continue
        assert np.all(np.isfinite(pts))
        eps = 1e-6 * max(w, h)
        assert pts[:, 0].min() >= 0.5 - eps and pts[:, 0].max() <= w - 0.5 + eps, "sample left the image (x)"
        assert pts[:, 1].min() >= 0.5 - eps and pts[:, 1].max() <= h - 0.5 + eps, "sample left the image (y)"
        img = rng.uniform(0, 255, (h, w)).astype(np.float32)
        start = lp.start1 if which == 1 else lp.start2
        step = lp.step1 if which == 1 else lp.step2
        vals = np.asarray(sample_lines(img, start, step, count))[:, 0]
        np.testing.assert_allclose(vals, _bilinear(img.astype(np.float64), pts), atol=0.05)


# -------------------------------------------------------------- triangulation


@st.composite
def triangulation_inputs(draw):
    n = draw(st.integers(0, 40))
    f1, f2 = draw(st.floats(10, 5000)), draw(st.floats(10, 5000))
    K1 = np.array([[f1, 0, draw(st.floats(0, 2000))], [0, f1, draw(st.floats(0, 2000))], [0, 0, 1.0]])
    K2 = np.array([[f2, 0, draw(st.floats(0, 2000))], [0, f2, draw(st.floats(0, 2000))], [0, 0, 1.0]])
    axis = draw(st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda a: np.linalg.norm(a) > 0.1))
    R = _rotation(axis, draw(st.floats(0.0, np.pi)))
    t = np.array(draw(st.tuples(*[st.floats(-10, 10)] * 3)))  # includes t = 0: no baseline
    kind = draw(st.sampled_from(["random", "same", "huge"]))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    uv1 = rng.uniform(-100, 2100, (n, 2))
    uv2 = uv1.copy() if kind == "same" else rng.uniform(-100, 2100, (n, 2))
    if kind == "huge":
        uv2[: n // 2] = rng.uniform(-1e12, 1e12, (n // 2, 2))
    return K1, K2, R, t, uv1, uv2


@settings(max_examples=200, **SETTINGS)
@given(inp=triangulation_inputs(), min_angle=st.floats(0.0, 2.0))
def test_triangulation_never_lets_a_non_finite_point_through(inp, min_angle):
    K1, K2, R, t, uv1, uv2 = inp
    with np.errstate(all="ignore"):
        X, valid, angle = triangulate(K1, K2, R, t, uv1, uv2)
    assert X.shape == (len(uv1), 3) and valid.shape == angle.shape == (len(uv1),)
    # The pipeline keeps valid points above the angle threshold (matching/sefm.py), then writes them.
    keep = valid & (angle >= np.radians(min_angle))
    assert np.all(np.isfinite(X[keep]))
    assert np.all(np.isfinite(angle[keep]))


@settings(max_examples=30, **SETTINGS)
@given(n=st.integers(1, 300), seed=st.integers(0, 10_000), spread=st.sampled_from([1e-6, 1.0, 1e6]))
def test_points_written_to_ply_are_finite(tmp_path_factory, n, seed, spread):
    """The writer's path: clean, normals, PLY; the cloud read back is finite and complete."""
    from sefm_recon.io.ply import read_point_cloud, write_point_cloud
    from sefm_recon.reconstruct.points import clean_points, estimate_normals

    rng = np.random.default_rng(seed)
    xyz = rng.normal(size=(n, 3)) * spread + [0, 0, 5 * spread]
    keep = clean_points(xyz) if n > 32 else np.ones(n, bool)
    xyz = xyz[keep]
    assume(len(xyz) > 0)
    normals = estimate_normals(xyz, np.array([[0, 0, 0], [spread, 0, 0]], float)) if len(xyz) >= 3 else None
    if normals is not None:
        assert np.all(np.isfinite(normals))
    path = tmp_path_factory.mktemp("ply") / "points.ply"
    write_point_cloud(path, xyz, np.zeros((len(xyz), 3), np.uint8), normals)
    back, _, nrm = read_point_cloud(path)
    assert len(back) == len(xyz) and np.all(np.isfinite(back))


def test_zero_line_pairs_expand_to_no_samples():
    """Found by test_line_samples_never_leave_the_images: cameras whose images share no epipolar line
    (``epipolar._expand`` used to raise a broadcasting ValueError on zero line pairs)."""
    K1 = np.array([[192.0, 0, 32], [0, 192, 32], [0, 0, 1]])
    K2 = np.array([[64.0, 0, 32], [0, 64, 20], [0, 0, 1]])
    R = _rotation([1, 0, 0], 0.5)
    lp = line_pairs(K1, K2, R, np.array([-1.0, 0, 0]), (64, 64), (64, 64))
    assert len(lp) == 0
    assert lp.all_points1().shape == (0, 2)
    assert sample_lines(np.zeros((64, 64), np.float32), lp.start1, lp.step1, lp.count1).shape[0] == 0
