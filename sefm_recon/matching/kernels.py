"""numba kernels of the SeFM matcher: the per-sample loops of §4.2-4.5.

Everything here works on flat arrays of line samples (see
:class:`sefm_recon.geometry.epipolar.LinePairs`): line ``l`` of image ``n`` is
``I_n[off_n[l]:off_n[l + 1]]``. :func:`match_lines` runs lines in parallel
(``prange``); each line writes only its own slice of the outputs.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..geometry.kernels import sample_band

# Back-pointer codes of the DP tables.
_DIAG, _UP, _LEFT = 0, 1, 2


@njit(cache=True)
def intensity_jumps(a: np.ndarray) -> np.ndarray:
    """``da_i = |a_{i-1} - a_{i+1}| / 2`` (paper §4.3), 0 at both ends. ``a``: (n,) float32."""
    n = a.shape[0]
    da = np.zeros(n, np.float32)
    for i in range(1, n - 1):
        da[i] = abs(a[i - 1] - a[i + 1]) * 0.5
    return da


@njit(cache=True)
def detect_keypoints(a: np.ndarray, threshold: float, border: int) -> np.ndarray:
    """Positions where the intensity jump exceeds ``threshold`` and is a local maximum.

    Non-maximum suppression keeps one key point per edge, where the paper's plain
    threshold would mark every sample of a blurred edge. ``border`` samples at
    both ends are skipped (their neighbourhoods are incomplete).
    """
    da = intensity_jumps(a)
    n = a.shape[0]
    out = np.empty(n, np.int64)
    k = 0
    for i in range(max(border, 1), n - max(border, 1)):
        if da[i] > threshold and da[i] >= da[i - 1] and da[i] > da[i + 1]:
            out[k] = i
            k += 1
    return out[:k]


@njit(cache=True)
def fft_descriptors(a: np.ndarray, keypoints: np.ndarray, radius: int, ncoef: int) -> np.ndarray:
    """Fourier descriptors of the neighbourhood of each key point (paper §4.3).

    The window ``a[i - radius : i + radius + 1]`` of every channel is
    Hann-tapered, made zero-mean, and described by the real and imaginary parts
    of its DFT coefficients 1..ncoef (the DC term is gone with the mean). The
    descriptor is normalised to unit energy over all channels, so a gain or
    offset between the photos does not matter. The window is centred on the key
    point, so the phase says on which side the edge rises. With neighbouring
    lines as channels, the descriptor sees a small 2-D patch.

    Args:
        a: (n, C) float32 samples.
    Returns:
        (len(keypoints), 2 * ncoef * C) float32.
    """
    n = a.shape[0]
    C = a.shape[1]
    size = 2 * radius + 1
    m = keypoints.shape[0]
    D = 2 * ncoef
    out = np.zeros((m, D * C), np.float32)
    win = np.empty(size, np.float64)
    taper = np.empty(size, np.float64)
    for s in range(size):
        taper[s] = 0.5 - 0.5 * np.cos(2.0 * np.pi * (s + 1) / (size + 1))
    cos_t = np.empty((ncoef, size), np.float64)
    sin_t = np.empty((ncoef, size), np.float64)
    for c in range(ncoef):
        for s in range(size):
            ang = 2.0 * np.pi * (c + 1) * s / size
            cos_t[c, s] = np.cos(ang)
            sin_t[c, s] = np.sin(ang)
    for k in range(m):
        i0 = keypoints[k] - radius
        energy = 0.0
        for ch in range(C):
            mean = 0.0
            for s in range(size):
                idx = min(max(i0 + s, 0), n - 1)
                win[s] = a[idx, ch]
                mean += win[s]
            mean /= size
            for s in range(size):
                win[s] = (win[s] - mean) * taper[s]
            for c in range(ncoef):
                re = 0.0
                im = 0.0
                for s in range(size):
                    re += win[s] * cos_t[c, s]
                    im -= win[s] * sin_t[c, s]
                out[k, ch * D + 2 * c] = re
                out[k, ch * D + 2 * c + 1] = im
                energy += re * re + im * im
        scale = 1.0 / np.sqrt(energy + 1e-3)
        for c in range(D * C):
            out[k, c] *= scale
    return out


@njit(cache=True)
def align_keypoints(p, q, desc1, desc2, lo, hi, max_dist):
    """Ordered alignment of two key point sequences by DP (LCS-like, paper §4.2).

    Maximises the summed similarity ``max_dist - |d1 - d2|`` over strictly
    increasing pairs; a key point may stay unmatched at no cost (seen in one
    view only). A pair is allowed only when ``q[j]`` lies in the search band
    ``[lo[p[i]], hi[p[i]]]`` of line-2 positions.

    The DP table ``S[i, j]`` (best score of ``p[:i]`` against ``q[:j]``) is
    kept as one row, updated in place: outside the band a row only repeats
    the row above until its first in-band cell, and after the last one only
    until the row above catches up, so a narrow band costs a few cells per
    key point instead of a full row (measured: README, speed). Each cell
    also keeps the last pair of its optimal path (``owner``), so the pairs
    are read back without the full table. Ties are broken as in the full
    table: the row above, then the cell to the left, then the pair.

    Args:
        p, q: (m,), (n,) increasing key point positions on line 1 and line 2.
        desc1, desc2: (m, D), (n, D) descriptors.
        lo, hi: (len(line 1),) band of line-2 positions for every line-1 sample.
    Returns:
        (k, 2) int64 indices into ``p`` and ``q`` of the matched pairs, increasing.
    """
    m = p.shape[0]
    n = q.shape[0]
    D = desc1.shape[1]
    max_d2 = max_dist * max_dist
    # In-band columns of every row: q[j0[i] : j1[i]].
    j0 = np.searchsorted(q, lo[p], "left")
    j1 = np.searchsorted(q, hi[p], "right")
    total = 0
    for i in range(m):
        total += max(0, j1[i] - j0[i])
    pair_i = np.empty(total, np.int64)
    pair_j = np.empty(total, np.int64)
    pred = np.empty(total, np.int64)
    S = np.zeros(n + 1, np.float32)  # S[j]: column j of the current row (0: no key point of q)
    owner = np.full(n + 1, -1, np.int64)
    k = 0
    for i in range(m):
        a = j0[i]
        b = j1[i]
        if b <= a:
            continue
        # Row i-1's values at columns a .. b (cell j + 1 is q[:j + 1]).
        diag_s = S[a]
        diag_o = owner[a]
        left_s = S[a]
        left_o = owner[a]
        for j in range(a, b):
            up_s = S[j + 1]
            up_o = owner[j + 1]
            best = up_s
            bo = up_o
            if left_s > best:
                best = left_s
                bo = left_o
            # Squared distance, abandoned once past max_dist: most pairs in
            # the band are far apart, and the descriptors are long.
            d2 = 0.0
            for c in range(D):
                diff = desc1[i, c] - desc2[j, c]
                d2 += diff * diff
                if d2 >= max_d2:
                    break
            if d2 < max_d2:
                cand = diag_s + (max_dist - np.sqrt(d2))
                if cand > best:
                    best = cand
                    pair_i[k] = i
                    pair_j[k] = j
                    pred[k] = diag_o
                    bo = k
                    k += 1
            diag_s = up_s
            diag_o = up_o
            S[j + 1] = best
            owner[j + 1] = bo
            left_s = S[j + 1]
            left_o = bo
        # Past the band, the row takes the left cell until the row above is as good.
        for j in range(b + 1, n + 1):
            if not left_s > S[j]:
                break
            S[j] = left_s
            owner[j] = left_o
    count = 0
    c = owner[n]
    while c >= 0:
        count += 1
        c = pred[c]
    out = np.empty((count, 2), np.int64)
    c = owner[n]
    for r in range(count - 1, -1, -1):
        out[r, 0] = pair_i[c]
        out[r, 1] = pair_j[c]
        c = pred[c]
    return out


@njit(cache=True)
def resample(seq: np.ndarray, start: int, stop: int, length: int) -> np.ndarray:
    """Linear interpolation of ``seq[start..stop]`` (inclusive, (n, C)) to ``length`` samples."""
    C = seq.shape[1]
    out = np.empty((length, C), np.float32)
    span = stop - start
    for u in range(length):
        pos = start + u * span / (length - 1)
        i0 = int(np.floor(pos))
        if i0 >= stop:
            i0 = stop - 1
        f = pos - i0
        for c in range(C):
            out[u, c] = (1.0 - f) * seq[i0, c] + f * seq[i0 + 1, c]
    return out


@njit(cache=True)
def _bt_bounds(x: np.ndarray):
    """I_min, I_max of each sample over its half-way neighbours (paper §4.4)."""
    L, C = x.shape
    lo = np.empty((L, C), np.float32)
    hi = np.empty((L, C), np.float32)
    for u in range(L):
        for c in range(C):
            v = x[u, c]
            vm = 0.5 * (v + x[u - 1, c]) if u > 0 else v
            vp = 0.5 * (v + x[u + 1, c]) if u < L - 1 else v
            lo[u, c] = min(v, min(vm, vp))
            hi[u, c] = max(v, max(vm, vp))
    return lo, hi


@njit(cache=True)
def align_path(x: np.ndarray, y: np.ndarray, penalty: float, band: int, free_end: bool):
    """Align two sequences sample by sample with DP (paper §4.4).

    Cost of matching ``x_u`` with ``y_v``: the sampling-insensitive
    ``max(0, y_v - I_max(x_u), I_min(x_u) - y_v)``, taken both ways (the smaller),
    summed over channels. Moves: diagonal (match), or advancing one sequence
    only at ``penalty`` (a sample without partner: occlusion or stretch). The
    path starts at (0, 0) and stays within ``|u - v| <= band``. It ends at
    (L1-1, L2-1), or with ``free_end`` at the cheapest cell of the last row or
    column (samples of x beyond a last-column end cost ``penalty`` each and stay
    unmatched): used at the open ends of a line, past the last rough match.

    Args:
        x, y: (L1, C), (L2, C) float32; L1 == L2 unless ``free_end``.
    Returns:
        v_of_u (L1,) float64: mean partner position of each ``u`` (NaN: none);
        run (L1,) int64: how many ``u`` share that partner (1 = one-to-one);
        cost (L1,) float32: matching cost on the path.
    """
    L1, C = x.shape
    L2 = y.shape[0]
    xlo, xhi = _bt_bounds(x)
    ylo, yhi = _bt_bounds(y)
    W = 2 * band + 1
    inf = np.float32(1e30)
    D = np.full((L1, W), inf, np.float32)
    B = np.zeros((L1, W), np.int8)
    Cm = np.zeros((L1, W), np.float32)
    for u in range(L1):
        v0 = max(0, u - band)
        v1 = min(L2 - 1, u + band)
        for v in range(v0, v1 + 1):
            c = 0.0
            for ch in range(C):
                yv = y[v, ch]
                xu = x[u, ch]
                c1 = max(0.0, max(yv - xhi[u, ch], xlo[u, ch] - yv))
                c2 = max(0.0, max(xu - yhi[v, ch], ylo[v, ch] - xu))
                c += min(c1, c2)
            k = v - u + band
            Cm[u, k] = c
            if u == 0 and v == 0:
                D[u, k] = c
                continue
            best = inf
            b = _DIAG
            if u > 0 and v > 0:
                d = D[u - 1, k]  # (u-1, v-1) has the same diagonal offset
                if d < best:
                    best = d
                    b = _DIAG
            if u > 0 and k + 1 < W:
                d = D[u - 1, k + 1] + penalty  # (u-1, v)
                if d < best:
                    best = d
                    b = _UP
            if v > 0 and k - 1 >= 0:
                d = D[u, k - 1] + penalty  # (u, v-1)
                if d < best:
                    best = d
                    b = _LEFT
            D[u, k] = best + c
            B[u, k] = b
    # Terminal cell.
    ue = L1 - 1
    ve = L2 - 1
    if free_end:
        best = inf
        for v in range(max(0, L1 - 1 - band), min(L2 - 1, L1 - 1 + band) + 1):
            d = D[L1 - 1, v - (L1 - 1) + band]
            if d < best:
                best = d
                ue = L1 - 1
                ve = v
        for u in range(max(0, L2 - 1 - band), min(L1 - 1, L2 - 1 + band) + 1):
            d = D[u, (L2 - 1) - u + band] + penalty * (L1 - 1 - u)
            if d < best:
                best = d
                ue = u
                ve = L2 - 1
    vsum = np.zeros(L1, np.float64)
    vcnt = np.zeros(L1, np.int64)
    cost = np.full(L1, np.nan, np.float32)
    partner = np.full(L1, -1, np.int64)
    u = ue
    v = ve
    if D[u, v - u + band] >= inf:
        v_of_u = np.full(L1, np.nan)
        return v_of_u, np.ones(L1, np.int64), cost
    while True:
        k = v - u + band
        vsum[u] += v
        vcnt[u] += 1
        cost[u] = Cm[u, k]
        partner[u] = v
        if u == 0 and v == 0:
            break
        b = B[u, k]
        if b == _DIAG:
            u -= 1
            v -= 1
        elif b == _UP:
            u -= 1
        else:
            v -= 1
    v_of_u = np.full(L1, np.nan)
    for u in range(L1):
        if vcnt[u] > 0:
            v_of_u[u] = vsum[u] / vcnt[u]
    # Length of the run of u's that share one partner v (a horizontal run).
    run = np.ones(L1, np.int64)
    s = 0
    while s <= ue:
        e = s
        while e + 1 <= ue and partner[e + 1] == partner[s] and vcnt[e + 1] == 1 and vcnt[s] == 1:
            e += 1
        for r in range(s, e + 1):
            run[r] = e - s + 1
        s = e + 1
    return v_of_u, run, cost


@njit(cache=True)
def align_segment(x: np.ndarray, y: np.ndarray, penalty: float, band: int):
    """Align two equal-length sequences between two rough matches; see :func:`align_path`."""
    return align_path(x, y, penalty, band, False)


@njit(cache=True)
def _open_end(a, b, i_anchor, j_anchor, forward, scale, lo, hi, penalty, band_fraction, band_min, band_max,
              occlusion_run, out_j, out_cost):
    """Match the open end of a line beyond its first (``forward=False``) or last rough match.

    The sequences run away from the anchor; line 2 is resampled by ``scale``
    (line-2 samples per line-1 sample, from the neighbouring segment) so the
    path is near the diagonal. The end is free: the line may leave either view.
    """
    n1 = a.shape[0]
    n2 = b.shape[0]
    C = a.shape[1]
    if forward:
        L1 = n1 - i_anchor
        jmax = min(n2 - 1, hi[n1 - 1])
        span2 = jmax - j_anchor
    else:
        L1 = i_anchor + 1
        jmin = max(0, lo[0])
        span2 = j_anchor - jmin
    if L1 < 2 or span2 < 1:
        return 0
    L2 = int(span2 / scale) + 1
    if L2 < 2:
        return 0
    x = np.empty((L1, C), np.float32)
    for u in range(L1):
        i = i_anchor + u if forward else i_anchor - u
        for c in range(C):
            x[u, c] = a[i, c]
    y = np.empty((L2, C), np.float32)
    for v in range(L2):
        pos = j_anchor + v * scale if forward else j_anchor - v * scale
        if pos < 0.0:
            pos = 0.0
        if pos > n2 - 1:
            pos = n2 - 1.0
        j0 = int(np.floor(pos))
        if j0 >= n2 - 1:
            j0 = n2 - 2
        f = pos - j0
        for c in range(C):
            y[v, c] = (1.0 - f) * b[j0, c] + f * b[j0 + 1, c]
    band = min(band_max, max(band_min, int(band_fraction * L1)))
    v_of_u, run, cost = align_path(x, y, penalty, band, True)
    n = 0
    for u in range(1, L1):
        if np.isnan(v_of_u[u]) or run[u] > occlusion_run:
            continue
        i = i_anchor + u if forward else i_anchor - u
        out_j[i] = j_anchor + v_of_u[u] * scale if forward else j_anchor - v_of_u[u] * scale
        out_cost[i] = cost[u]
        n += 1
    return n


@njit(cache=True)
def _count_strong(da, kps, first, last, strong):
    """Key points with index in (first, last) whose jump is at least ``strong``."""
    c = 0
    for k in range(first + 1, last):
        if da[kps[k]] >= strong:
            c += 1
    return c


@njit(cache=True)
def match_one_line(a, b, lo, hi, threshold, radius, ncoef, max_dist,
                   sv_max_unmatched, sv_strength, penalty, band_fraction, band_min, band_max,
                   occlusion_run, open_ends, out_j, out_cost, out_anchor):
    """Rough + dense matching of one line pair; writes ``out_*`` of line 1's samples.

    Returns (key points on line 1, on line 2, rough matches, valid segments, segments).
    """
    n1 = a.shape[0]
    n2 = b.shape[0]
    lum1 = np.empty(n1, np.float32)
    lum2 = np.empty(n2, np.float32)
    C = a.shape[1]
    for i in range(n1):
        s = 0.0
        for c in range(C):
            s += a[i, c]
        lum1[i] = s / C
    for i in range(n2):
        s = 0.0
        for c in range(C):
            s += b[i, c]
        lum2[i] = s / C
    kp1 = detect_keypoints(lum1, threshold, 1)
    kp2 = detect_keypoints(lum2, threshold, 1)
    if kp1.shape[0] < 2 or kp2.shape[0] < 2:
        return kp1.shape[0], kp2.shape[0], 0, 0, 0
    d1 = fft_descriptors(a, kp1, radius, ncoef)
    d2 = fft_descriptors(b, kp2, radius, ncoef)
    pairs = align_keypoints(kp1, kp2, d1, d2, lo, hi, max_dist)
    npairs = pairs.shape[0]
    da1 = intensity_jumps(lum1)
    da2 = intensity_jumps(lum2)
    strong = sv_strength * threshold
    nvalid = 0
    for k in range(npairs):
        out_anchor[kp1[pairs[k, 0]]] = True
    for k in range(npairs - 1):
        ka1 = pairs[k, 0]
        kb1 = pairs[k + 1, 0]
        ka2 = pairs[k, 1]
        kb2 = pairs[k + 1, 1]
        # S_v (paper §4.5): the segment is valid only if no (strong) key point
        # lies between its ends in either view; one there means an occlusion.
        unmatched = _count_strong(da1, kp1, ka1, kb1, strong) + _count_strong(da2, kp2, ka2, kb2, strong)
        if unmatched > sv_max_unmatched:
            continue
        ia = kp1[ka1]
        ib = kp1[kb1]
        ja = kp2[ka2]
        jb = kp2[kb2]
        len1 = ib - ia + 1
        len2 = jb - ja + 1
        L = max(len1, len2)
        x = resample(a, ia, ib, L)
        y = resample(b, ja, jb, L)
        band = min(band_max, max(band_min, int(band_fraction * L)))
        v_of_u, run, cost = align_segment(x, y, penalty, band)
        nvalid += 1
        scale1 = (L - 1) / (len1 - 1)
        scale2 = (len2 - 1) / (L - 1)
        for i in range(ia, ib + 1):
            uf = (i - ia) * scale1
            u0 = int(np.floor(uf))
            if u0 >= L - 1:
                u0 = L - 2
            f = uf - u0
            v = (1.0 - f) * v_of_u[u0] + f * v_of_u[u0 + 1]
            ur = u0 if f < 0.5 else u0 + 1
            if run[ur] > occlusion_run:
                continue  # part of a horizontal run: x has no partner (occluded in view 2)
            out_j[i] = ja + v * scale2
            out_cost[i] = cost[ur]
    if open_ends and npairs >= 2:
        # Beyond the first and last rough match, at the scale of the nearest segment.
        s0 = (kp2[pairs[1, 1]] - kp2[pairs[0, 1]]) / (kp1[pairs[1, 0]] - kp1[pairs[0, 0]])
        s1 = (kp2[pairs[npairs - 1, 1]] - kp2[pairs[npairs - 2, 1]]) / (
            kp1[pairs[npairs - 1, 0]] - kp1[pairs[npairs - 2, 0]])
        s0 = min(2.0, max(0.5, s0))
        s1 = min(2.0, max(0.5, s1))
        _open_end(a, b, kp1[pairs[0, 0]], kp2[pairs[0, 1]], False, s0, lo, hi, penalty, band_fraction,
                  band_min, band_max, occlusion_run, out_j, out_cost)
        _open_end(a, b, kp1[pairs[npairs - 1, 0]], kp2[pairs[npairs - 1, 1]], True, s1, lo, hi, penalty,
                  band_fraction, band_min, band_max, occlusion_run, out_j, out_cost)
    return kp1.shape[0], kp2.shape[0], npairs, nvalid, max(npairs - 1, 0)


@njit(parallel=True, cache=True)
def match_lines(I1, off1, I2, off2, lo, hi, threshold, radius, ncoef, max_dist,
                sv_max_unmatched, sv_strength, penalty, band_fraction, band_min, band_max,
                occlusion_run, open_ends):
    """Match every line pair; returns per line-1 sample partner position on line 2.

    Args:
        I1, I2: (N1, C), (N2, C) float32 flat samples of both images.
        off1, off2: (L + 1,) int64 line offsets.
        lo, hi: (N1,) int64 band of line-2 positions (relative to the line start)
            that may hold the partner of each line-1 sample.
    Returns:
        j (N1,) float64: partner position on line 2 (relative), NaN when none;
        cost (N1,) float32; anchor (N1,) bool: sample is a rough match;
        stats (L, 5) int64: key points 1, key points 2, rough matches, valid
        segments, segments.
    """
    L = off1.shape[0] - 1
    N1 = I1.shape[0]
    out_j = np.full(N1, np.nan)
    out_cost = np.full(N1, np.nan, np.float32)
    out_anchor = np.zeros(N1, np.bool_)
    stats = np.zeros((L, 5), np.int64)
    for l in prange(L):
        s1 = off1[l]
        e1 = off1[l + 1]
        s2 = off2[l]
        e2 = off2[l + 1]
        if e1 - s1 < 3 or e2 - s2 < 3:
            continue
        r = match_one_line(
            I1[s1:e1], I2[s2:e2], lo[s1:e1], hi[s1:e1], threshold, radius, ncoef, max_dist,
            sv_max_unmatched, sv_strength, penalty, band_fraction, band_min, band_max,
            occlusion_run, open_ends, out_j[s1:e1], out_cost[s1:e1], out_anchor[s1:e1],
        )
        stats[l, 0] = r[0]
        stats[l, 1] = r[1]
        stats[l, 2] = r[2]
        stats[l, 3] = r[3]
        stats[l, 4] = r[4]
    return out_j, out_cost, out_anchor, stats


@njit(parallel=True, cache=True)
def depth_runs_filter(depth, line_of, jump, min_run, mask):
    """S_p (paper §4.5): keep points whose depth continues their neighbours'.

    Points are in line order (``line_of`` non-decreasing, samples increasing
    along each line); only those with ``mask`` set take part (the others are
    skipped, as if absent, and not kept). A relative depth change above
    ``jump`` between consecutive points starts a new run; runs shorter than
    ``min_run`` points are isolated depth spikes (mismatches) and are dropped.
    Returns a keep mask.
    """
    n = depth.shape[0]
    keep = np.zeros(n, np.bool_)
    # Line boundaries.
    starts = np.empty(n + 1, np.int64)
    ns = 0
    for i in range(n):
        if i == 0 or line_of[i] != line_of[i - 1]:
            if i > 0 and line_of[i] < line_of[i - 1]:
                raise ValueError("points must be sorted by line")
            starts[ns] = i
            ns += 1
    starts[ns] = n
    for s in prange(ns):
        a = starts[s]
        e = starts[s + 1]
        first = a  # first point of the current run
        prev = -1  # last point taken part
        count = 0  # points of the current run
        for i in range(a, e + 1):
            if i < e and not mask[i]:
                continue
            brk = i == e
            if not brk and prev >= 0:
                d0 = depth[prev]
                d1 = depth[i]
                brk = abs(d1 - d0) > jump * min(d0, d1)
            if brk:
                if count >= min_run:
                    for k in range(first, i):
                        if mask[k]:
                            keep[k] = True
                first = i
                count = 0
            prev = i
            count += 1
    return keep


@njit(cache=True)
def _rasterise(uv, value, mask, height, width):
    """(height, width) float32 grid of ``value`` at ``floor(uv)`` of the masked points.

    The first point of a cell wins; cells without one hold NaN.
    """
    grid = np.full((height, width), np.nan, np.float32)
    for k in range(uv.shape[0]):
        if not mask[k]:
            continue
        r = int(np.floor(uv[k, 1]))
        c = int(np.floor(uv[k, 0]))
        if 0 <= r < height and 0 <= c < width and np.isnan(grid[r, c]):
            grid[r, c] = value[k]
    return grid


@njit(inline="always")
def _neighbours(grid, r, c, radius, buf):
    """Copy the values of the other cells of the ``(2 radius + 1)^2`` window at (r, c) into ``buf``.

    Returns their count (cells holding NaN are skipped).
    """
    m = 0
    for rr in range(max(r - radius, 0), min(r + radius + 1, grid.shape[0])):
        for cc in range(max(c - radius, 0), min(c + radius + 1, grid.shape[1])):
            v = grid[rr, cc]
            if not np.isnan(v) and not (rr == r and cc == c):
                buf[m] = v
                m += 1
    return m


@njit(parallel=True, cache=True)
def grid_median_check(uv, value, mask, height, width, radius, tol, min_support, drop_isolated=False, bins=0):
    """2-D consistency: compare each point's value with the median of its neighbours.

    Points with ``mask`` set are rasterised into a (height, width) grid at
    ``floor(uv)`` (the first point of a cell wins); such a point is kept when
    at least ``min_support`` other cells of its ``(2 radius + 1)^2`` window
    hold a value and the point is within ``tol`` of their median; a point with
    too few neighbours to judge is kept, unless ``drop_isolated``. The median
    test is done by counting, without sorting: the median lies more than
    ``tol`` above the point exactly when more than half of the neighbours do
    (with an even count: when the lower middle value does). Points without
    ``mask`` are not kept.

    With ``bins`` > 0 the median itself is estimated for the kept, judged
    points, without sorting either: the neighbours within ``tol`` of the point
    go into ``bins`` bins of width ``2 tol / bins``, and the middle rank's
    value is the mean of its bin (exact where it falls outside the range),
    so within one bin width of the exact median.

    Args:
        uv: (N, 2) positions (x, y), COLMAP pixels; value, mask: (N,).
    Returns (keep (N,) bool, support (N,) int32, median (N,): the
    estimate, or the point's own value where not estimated; with ``bins``
    = 0, ``value`` itself).
    """
    n = uv.shape[0]
    grid = _rasterise(uv, value, mask, height, width)
    keep = np.zeros(n, np.bool_)
    support = np.zeros(n, np.int32)
    # The check alone returns the values themselves: a copy costs 24 MB of fresh pages at 2000 px.
    median = value.astype(np.float64) if bins > 0 else value
    nchunk = min(n, 256)
    width_bin = 2.0 * tol / max(bins, 1)
    for ch in prange(nchunk):
        buf = np.empty((2 * radius + 1) ** 2, np.float32)  # one per chunk, not per point
        count = np.zeros(max(bins, 1), np.int64)
        total = np.zeros(max(bins, 1))
        for k in range(ch * n // nchunk, (ch + 1) * n // nchunk):
            if not mask[k]:
                continue
            r = int(np.floor(uv[k, 1]))
            c = int(np.floor(uv[k, 0]))
            x = value[k]
            m = _neighbours(grid, r, c, radius, buf)
            above = 0
            below = 0
            for q in range(m):
                above += buf[q] > x + tol
                below += buf[q] < x - tol
            support[k] = m
            if m < min_support:
                keep[k] = not drop_isolated
                continue
            keep[k] = not (2 * above > m or 2 * below > m)
            if bins == 0 or not keep[k]:
                continue
            count[:] = 0
            total[:] = 0.0
            max_below = -np.inf
            min_above = np.inf
            for q in range(m):
                v = buf[q]
                if v < x - tol:
                    max_below = max(max_below, v)
                elif v > x + tol:
                    min_above = min(min_above, v)
                else:
                    bq = min(int((v - (x - tol)) / width_bin), bins - 1)
                    count[bq] += 1
                    total[bq] += v
            est = 0.0
            # The two middles (the same one for an odd count). A kept point has
            # at most half its neighbours below (above) the range, so a middle
            # outside it is the largest value below (smallest above) it.
            for rank in ((m - 1) // 2, m // 2):
                if rank < below:
                    est += max_below
                elif rank >= m - above:
                    est += min_above
                else:
                    cum = below
                    for bq in range(bins):
                        cum += count[bq]
                        if rank < cum:
                            est += total[bq] / count[bq]
                            break
            median[k] = 0.5 * est
    return keep, support, median


