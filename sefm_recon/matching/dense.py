"""Dense matching (paper §4.4): between consecutive rough matches, resample both
segments to equal length and align every sample by DP with the
sampling-insensitive cost ``C = max(0, I(y) - I_max, I_min - I(y))``.

:func:`match_lines` runs the whole per-line matcher (rough matches, S_v,
segment DP) over every line pair; :func:`match_direction` drives it, and
:func:`reverse_check` matches line 2 back to line 1 and keeps the matches both
directions agree on. :func:`resample` and :func:`align_segment` are the DP steps
on single sequences, for tests and notebooks.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from ..config import Config
from .band import invert_band
from .rough import RoughOptions, match_keypoints
from .validity import SegmentValidity, segment_valid

# Back-pointer codes of the DP tables.
_DIAG, _UP, _LEFT = 0, 1, 2


class DenseOptions(NamedTuple):
    """Settings of the segment DP."""

    penalty: float  #: DP cost of a sample without partner
    band_fraction: float  #: DP band half width, as a share of the segment length...
    band_min: int  #: ...at least this many samples
    band_max: int  #: ...and at most this many
    occlusion_run: int  #: samples sharing one partner beyond this are occluded
    open_ends: bool  #: also match beyond the first and last rough match of a line


class LineOptions(NamedTuple):
    """Settings of the per-line matcher (:func:`match_lines`)."""

    rough: RoughOptions
    sv: SegmentValidity
    dense: DenseOptions


def line_options(cfg: Config, jump: float) -> LineOptions:
    """The per-line matcher's settings from ``cfg``, with key points at intensity jumps over ``jump``."""
    r, v, d = cfg.rough, cfg.validity, cfg.dense
    return LineOptions(
        RoughOptions(float(jump), int(r.descriptor_radius), int(r.descriptor_coefficients),
                     float(r.max_descriptor_distance)),
        SegmentValidity(int(v.sv_max_unmatched), float(v.sv_strength)),
        DenseOptions(float(d.occlusion_penalty), float(d.band_fraction), int(d.band_min), int(d.band_max),
                     int(d.occlusion_run), bool(d.open_ends)),
    )


@njit(inline="always")
def _band(opts, length):
    """DP band half width for a segment ``length`` samples long (:class:`DenseOptions`)."""
    return min(opts.band_max, max(opts.band_min, int(opts.band_fraction * length)))


@njit(cache=True)
def _resample(seq: np.ndarray, start: int, stop: int, length: int) -> np.ndarray:
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
def _open_end(a, b, i_anchor, j_anchor, forward, scale, lo, hi, opts, out_j, out_cost):
    """Match the open end of a line beyond its first (``forward=False``) or last rough match.

    The sequences run away from the anchor; line 2 is resampled by ``scale``
    (line-2 samples per line-1 sample, from the neighbouring segment) so the
    path is near the diagonal. The end is free: the line may leave either view.
    ``opts`` is the :class:`DenseOptions`; returns the number of samples matched.
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
    v_of_u, run, cost = align_path(x, y, opts.penalty, _band(opts, L1), True)
    n = 0
    for u in range(1, L1):
        if np.isnan(v_of_u[u]) or run[u] > opts.occlusion_run:
            continue
        i = i_anchor + u if forward else i_anchor - u
        out_j[i] = j_anchor + v_of_u[u] * scale if forward else j_anchor - v_of_u[u] * scale
        out_cost[i] = cost[u]
        n += 1
    return n


@njit(cache=True)
def _match_line(a, b, lo, hi, rough, sv, d, out_j, out_cost, out_anchor, out_stats):
    """Rough + dense matching of one line pair; writes ``out_*`` of line 1's samples and the line's counts.

    Rough matches (:func:`.rough.match_keypoints`) cut the lines into
    segments; each segment valid by S_v (:func:`.validity.segment_valid`) is
    resampled to equal lengths and aligned by DP (:func:`align_path`), and
    with ``open_ends`` the parts beyond the first and last rough match too.
    ``rough``, ``sv``, ``d`` are the fields of a :class:`LineOptions`.
    ``out_stats`` (5,) int64 gets the counts: key points on line 1, on line
    2, rough matches, valid segments, segments.
    """
    r = match_keypoints(a, b, lo, hi, rough)
    kp1 = r.kp1
    kp2 = r.kp2
    pairs = r.pairs
    npairs = pairs.shape[0]
    strong = sv.strength * rough.threshold
    nvalid = 0
    for k in range(npairs):
        out_anchor[kp1[pairs[k, 0]]] = True
    for k in range(npairs - 1):
        # S_v (paper §4.5): a segment with (strong) unmatched key points between its ends is an occlusion.
        if not segment_valid(r.jump1, r.jump2, pairs, k, strong, sv.max_unmatched):
            continue
        ia = kp1[pairs[k, 0]]
        ib = kp1[pairs[k + 1, 0]]
        ja = kp2[pairs[k, 1]]
        jb = kp2[pairs[k + 1, 1]]
        len1 = ib - ia + 1
        len2 = jb - ja + 1
        L = max(len1, len2)
        x = _resample(a, ia, ib, L)
        y = _resample(b, ja, jb, L)
        v_of_u, run, cost = align_path(x, y, d.penalty, _band(d, L), False)
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
            if run[ur] > d.occlusion_run:
                continue  # part of a horizontal run: x has no partner (occluded in view 2)
            out_j[i] = ja + v * scale2
            out_cost[i] = cost[ur]
    if d.open_ends and npairs >= 2:
        # Beyond the first and last rough match, at the scale of the nearest segment.
        s0 = (kp2[pairs[1, 1]] - kp2[pairs[0, 1]]) / (kp1[pairs[1, 0]] - kp1[pairs[0, 0]])
        s1 = (kp2[pairs[npairs - 1, 1]] - kp2[pairs[npairs - 2, 1]]) / (
            kp1[pairs[npairs - 1, 0]] - kp1[pairs[npairs - 2, 0]])
        s0 = min(2.0, max(0.5, s0))
        s1 = min(2.0, max(0.5, s1))
        _open_end(a, b, kp1[pairs[0, 0]], kp2[pairs[0, 1]], False, s0, lo, hi, d, out_j, out_cost)
        _open_end(a, b, kp1[pairs[npairs - 1, 0]], kp2[pairs[npairs - 1, 1]], True, s1, lo, hi, d, out_j, out_cost)
    out_stats[0] = kp1.shape[0]
    out_stats[1] = kp2.shape[0]
    out_stats[2] = npairs
    out_stats[3] = nvalid
    out_stats[4] = max(npairs - 1, 0)


@njit(parallel=True, cache=True)
def match_lines(I1, off1, I2, off2, lo, hi, rough, sv, dense):
    """Match every line pair (:func:`_match_line`); returns per line-1 sample partner position on line 2.

    Args:
        I1, I2: (N1, C), (N2, C) float32 flat samples of both images.
        off1, off2: (L + 1,) int64 line offsets.
        lo, hi: (N1,) int64 band of line-2 positions (relative to the line start)
            that may hold the partner of each line-1 sample.
        rough, sv, dense: the fields of a :class:`LineOptions` (numba's parallel
            loops take flat named tuples only).
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
        _match_line(I1[s1:e1], I2[s2:e2], lo[s1:e1], hi[s1:e1], rough, sv, dense, out_j[s1:e1], out_cost[s1:e1],
                    out_anchor[s1:e1], stats[l])
    return out_j, out_cost, out_anchor, stats


@dataclass
class LineMatches:
    """One direction's matches of every line pair (:func:`match_direction`)."""

    j: np.ndarray  #: (N1,) float64 partner position on line 2, samples from its start (NaN: none)
    cost: np.ndarray  #: (N1,) float32 DP cost of the match
    anchor: np.ndarray  #: (N1,) bool: the sample is a rough match
    stats: np.ndarray  #: (L, 5) int64 key points 1, key points 2, rough matches, valid segments, segments


def match_direction(Ia: np.ndarray, offa: np.ndarray, Ib: np.ndarray, offb: np.ndarray, lo: np.ndarray,
                    hi: np.ndarray, opts: LineOptions, bar=None) -> LineMatches:
    """:func:`match_lines` from the lines of image a to those of image b, in chunks (for the progress bar)."""
    n = len(offa) - 1
    j = np.full(len(Ia), np.nan)
    cost = np.full(len(Ia), np.nan, np.float32)
    anchor = np.zeros(len(Ia), bool)
    stats = np.zeros((n, 5), np.int64)
    chunks = np.array_split(np.arange(n), max(1, min(50, n // 64)))
    for chunk in chunks:
        if len(chunk) == 0:
            continue
        a, b = chunk[0], chunk[-1] + 1
        s1, e1, s2, e2 = offa[a], offa[b], offb[a], offb[b]
        rj, rc, ra, rs = match_lines(Ia[s1:e1], offa[a:b + 1] - s1, Ib[s2:e2], offb[a:b + 1] - s2, lo[s1:e1],
                                     hi[s1:e1], *opts)
        j[s1:e1], cost[s1:e1], anchor[s1:e1], stats[a:b] = rj, rc, ra, rs
        if bar is not None:
            bar.update(len(chunk))
    return LineMatches(j, cost, anchor, stats)


def consistent(j12: np.ndarray, i21: np.ndarray, off1, off2, count2, tol: float) -> np.ndarray:
    """Left-right check: keep j12[i] only where matching back from round(j12[i]) returns to i."""
    L = len(off1) - 1
    line1 = np.repeat(np.arange(L), np.diff(off1))
    k1 = np.arange(len(j12)) - off1[line1]
    out = np.full_like(j12, np.nan)
    ok = np.isfinite(j12)
    jr = np.clip(np.rint(np.where(ok, j12, 0)).astype(np.int64), 0, count2[line1] - 1)
    back = i21[off2[line1] + jr]
    ok &= np.isfinite(back) & (np.abs(back - k1) <= tol)
    out[ok] = j12[ok]
    return out


def reverse_check(j: np.ndarray, I1: np.ndarray, off1: np.ndarray, I2: np.ndarray, off2: np.ndarray,
                  lo: np.ndarray, hi: np.ndarray, count2: np.ndarray, opts: LineOptions, tol: float,
                  bar=None) -> np.ndarray:
    """Match line 2 back to line 1 and keep the matches ``j`` (N1,) that return to their sample.

    The reverse pass searches the inverse of the band ``lo``, ``hi`` (N1,)
    (:func:`.band.invert_band`); a match is kept where the partner of its
    rounded partner lies within ``tol`` samples of it (:func:`consistent`).
    """
    lo21, hi21 = invert_band(lo, hi, off1, off2)
    i21 = match_direction(I2, off2, I1, off1, lo21, hi21, opts, bar).j
    del lo21, hi21
    return consistent(j, i21, off1, off2, count2, tol)


def _as2d(x):
    """A (n,) or (n, C) sequence as (n, C) contiguous float32."""
    x = np.ascontiguousarray(x, np.float32)
    return x[:, None] if x.ndim == 1 else x


def resample(seq: np.ndarray, length: int) -> np.ndarray:
    """Linear interpolation of a (n,) or (n, C) sequence to ``length`` samples."""
    s = _as2d(seq)
    out = _resample(s, 0, len(s) - 1, int(length))
    return out[:, 0] if np.ndim(seq) == 1 else out


def align_segment(x: np.ndarray, y: np.ndarray, penalty: float = 20.0, band: int | None = None):
    """Align equal-length sequences x, y ((L,) or (L, C)); see :func:`align_path`.

    Returns ``(v_of_u, run, cost)``: partner position in y of each sample of x,
    length of the one-to-many run it belongs to, and the matching cost.
    """
    x2, y2 = _as2d(x), _as2d(y)
    if x2.shape != y2.shape:
        raise ValueError(f"sequences must have equal shapes, got {x2.shape} and {y2.shape}")
    if band is None:
        band = len(x2)
    return align_path(x2, y2, float(penalty), int(band), False)
