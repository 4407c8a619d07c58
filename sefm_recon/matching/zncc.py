"""Zero-mean normalised cross-correlation (ZNCC) of windows along a line pair.

The windows run along the line samples (:class:`sefm_recon.geometry.epipolar.LinePairs`)
over all channels: with neighbour lines as channels, a window is a small 2-D
patch. Line 2 is read at fractional positions, linearly interpolated. Gap
filling (:mod:`.fill`), propagation (:mod:`.propagate`) and sub-pixel
refinement (:mod:`.subpixel`) judge a partner by these correlations.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _window(i, n1, j0, n2, half, pad_lo, pad_hi, min_len):
    """Window offsets ``s`` in [lo, hi] with ``i + s`` on line 1 and ``j0 + s - pad_lo .. j0 + s + pad_hi`` on line 2.

    The window is cut where it would leave either line, so samples near the
    image border keep a (one-sided) window; fewer than ``min_len`` samples
    left gives an empty range (``hi < lo``).
    """
    lo = max(-half, -i, pad_lo - j0)
    hi = min(half, n1 - 1 - i, n2 - 1 - pad_hi - j0)
    if hi - lo + 1 < min_len:
        return 1, 0
    return lo, hi


@njit(cache=True)
def zncc(a, i, b, jpos, half):
    """ZNCC of the window a[i-half..i+half, :] with b sampled at jpos-half..jpos+half (linear).

    -2 where the window (cut at the line ends, :func:`_window`) is too short or flat.
    """
    n1 = a.shape[0]
    n2 = b.shape[0]
    C = a.shape[1]
    if not (jpos >= 0.0 and jpos <= n2 - 1):
        return -2.0
    j0 = int(np.floor(jpos))
    f = jpos - j0
    lo, hi = _window(i, n1, j0, n2, half, 0, 0, 2 * half + 1)
    if hi < lo:
        return -2.0
    sx = 0.0
    sy = 0.0
    sxx = 0.0
    syy = 0.0
    sxy = 0.0
    m = 0
    for s in range(lo, hi + 1):
        jj = j0 + s
        for c in range(C):
            x = a[i + s, c]
            if jj + 1 <= n2 - 1:
                y = (1.0 - f) * b[jj, c] + f * b[jj + 1, c]
            else:
                y = b[jj, c]
            sx += x
            sy += y
            sxx += x * x
            syy += y * y
            sxy += x * y
            m += 1
    vx = sxx - sx * sx / m
    vy = syy - sy * sy / m
    if vx <= 1e-6 * m or vy <= 1e-6 * m:
        return -2.0
    return (sxy - sx * sy / m) / np.sqrt(vx * vy)


#: Window sums of :func:`_add3`: x, x², y₋, y₀, y₊, y₋², y₀², y₊², xy₋, xy₀, xy₊.
_SUMS3 = (0.0,) * 11


@njit(inline="always")
def _add3(t, x, yl, yc, yr):
    """Add one sample pair (x, and y at three shifts) to the window sums ``t``."""
    return (t[0] + x, t[1] + x * x, t[2] + yl, t[3] + yc, t[4] + yr, t[5] + yl * yl, t[6] + yc * yc,
            t[7] + yr * yr, t[8] + x * yl, t[9] + x * yc, t[10] + x * yr)


@njit(inline="always")
def _ncc3(t, m):
    """The three ZNCCs from the window sums of ``m`` sample pairs (-2 where a window is flat)."""
    vx = t[1] - t[0] * t[0] / m
    if vx <= 1e-6 * m:
        return -2.0, -2.0, -2.0
    return (_ncc(t[8], t[0], t[2], t[5], vx, m), _ncc(t[9], t[0], t[3], t[6], vx, m),
            _ncc(t[10], t[0], t[4], t[7], vx, m))


@njit(cache=True)
def _ncc(sxy, sx, sy, syy, vx, m):
    """ZNCC from the window sums of ``m`` sample pairs, x's variance sum ``vx`` given (-2 where y is flat)."""
    vy = syy - sy * sy / m
    if vy <= 1e-6 * m:
        return -2.0
    return (sxy - sx * sy / m) / np.sqrt(vx * vy)


@njit(cache=True)
def zncc3(a, i, b, jpos, half):
    """:func:`zncc` at ``jpos - 1``, ``jpos`` and ``jpos + 1`` in one pass (shared window sums)."""
    n1 = a.shape[0]
    n2 = b.shape[0]
    C = a.shape[1]
    if not (jpos >= 1.0 and jpos < n2 - 2):
        return -2.0, zncc(a, i, b, jpos, half), -2.0
    j0 = int(np.floor(jpos))
    # Cut windows: samples near the image border keep a match and a sub-pixel
    # position, which adds coverage along the border.
    lo, hi = _window(i, n1, j0, n2, half, 1, 2, half + 1)
    if hi < lo:
        return -2.0, zncc(a, i, b, jpos, half), -2.0
    f = jpos - j0
    g = 1.0 - f
    m = (hi - lo + 1) * C
    t = _SUMS3
    for s in range(lo, hi + 1):
        jj = j0 + s
        for c in range(C):
            t = _add3(t, a[i + s, c], g * b[jj - 1, c] + f * b[jj, c], g * b[jj, c] + f * b[jj + 1, c],
                      g * b[jj + 1, c] + f * b[jj + 2, c])
    return _ncc3(t, m)


@njit(cache=True)
def zncc3_sheared(a, i, b, jpos, half, g, h, o_first, cc):
    """:func:`zncc3` with line 2's window stretched by ``g`` and each neighbour line's moved by its shear.

    On a slanted surface the partner of ``i + s`` is near ``jpos + g s``, not
    ``jpos + s``; the stretched window correlates there without bias. The columns of ``a`` and ``b`` are
    neighbour lines ``o_first, o_first + 1, ...`` (``cc`` channels each). On
    a surface whose depth changes across lines, neighbour ``o``'s partner is
    ``o h`` samples along line 2 from the centre line's (:func:`.subpixel.line_shear`);
    correlating there keeps the 2-D window on the surface.
    """
    n1 = a.shape[0]
    n2 = b.shape[0]
    C = a.shape[1]
    reach = abs(h) * max(abs(o_first), abs(o_first + C // cc - 1))
    lo = max(-half, -i, int(np.ceil((1.0 + reach - jpos) / g)))
    hi = min(half, n1 - 1 - i, int(np.floor((n2 - 2.0 - reach - jpos) / g)))
    if hi - lo + 1 < half + 1:
        return zncc3(a, i, b, jpos, half)  # near a line end: the plain (cut) window
    m = (hi - lo + 1) * C
    t = _SUMS3
    for c in range(C):  # column by column: faster than sample by sample
        sh = jpos + (o_first + c // cc) * h
        for s in range(lo, hi + 1):
            p = sh + g * s
            q = int(p)  # p >= 1 inside the bounds: truncation is the floor
            f = p - q
            e = 1.0 - f
            q2 = min(q + 2, n2 - 1)
            t = _add3(t, a[i + s, c], e * b[q - 1, c] + f * b[q, c], e * b[q, c] + f * b[q + 1, c],
                      e * b[q + 1, c] + f * b[q2, c])
    return _ncc3(t, m)


@njit(cache=True)
def _max_step(a, i, sh):
    """Largest change of the channel mean between consecutive samples from ``i`` to ``i + sh``."""
    C = a.shape[1]
    lo = min(i, i + sh)
    hi = max(i, i + sh)
    prev = 0.0
    for c in range(C):
        prev += a[lo, c]
    out = 0.0
    for k in range(lo + 1, hi + 1):
        m = 0.0
        for c in range(C):
            m += a[k, c]
        out = max(out, abs(m - prev) / C)
        prev = m
    return out


@njit(cache=True)
def zncc_search(a, i, b, first, n, half, min_zncc, shift=0, max_step=np.inf):
    """Best ZNCC of ``a[i]``'s window over line-2 positions ``first + d``, d = 0..n-1.

    With ``shift`` > 0 the window may also be moved ``shift`` samples to
    either side (the same move on both lines; the best of the three counts),
    so a sample next to a depth edge is judged on the side of the edge it
    belongs to. A window is moved only where the samples between ``i`` and
    its new centre change by at most ``max_step`` from one to the next: a
    window moved across an intensity edge judges the other side's surface,
    whose depth a sample of this side (occluded in view 2) would take. A
    best position reaching ``min_zncc`` is refined by a parabola through its
    neighbours (by at most half a sample). Returns (best ZNCC, position).
    """
    best = -2.0
    bj = first
    bs = 0
    for d in range(n):
        z = zncc(a, i, b, first + d, half)
        if z > best:
            best = z
            bj = first + d
    if best < min_zncc and shift > 0:  # the centred window failed: try the shifted ones
        for sh in (-shift, shift):
            if not 0 <= i + sh < a.shape[0]:
                continue
            if max_step < np.inf and _max_step(a, i, sh) > max_step:
                continue
            for d in range(n):
                z = zncc(a, i + sh, b, first + d + sh, half)
                if z > best:
                    best = z
                    bj = first + d
                    bs = sh
    if best < min_zncc:
        return best, bj
    zl = zncc(a, i + bs, b, bj - 1.0 + bs, half)
    zr = zncc(a, i + bs, b, bj + 1.0 + bs, half)
    den = zl - 2.0 * best + zr
    off = 0.0
    if zl > -2.0 and zr > -2.0 and den < 0.0:
        off = min(0.5, max(-0.5, 0.5 * (zl - zr) / den))
    return best, bj + off

