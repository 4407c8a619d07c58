"""A plane of the scene aligned between the two images by their intensities, an addition beyond the paper.

On a weakly textured surface SGM's estimates follow the sensor noise: each is the minimum of
a cost whose true minimum is barely deeper than its neighbours', so that a plain floor's
matches scatter 1-3 px about it (generated seed 68: 46 % within 1 px) and a plane fitted to
them inherits their errors. The faint texture still fixes the surface when the evidence of
every pixel is summed: the plane's 3 parameters (the inverse depth ``1 / z = a u + b v + c``,
:func:`.planes._inverse_depth_plane`) are refined by Gauss-Newton on the intensity
differences between image 1 and image 2 warped by the homography the plane induces
(:func:`align_plane`), coarse to fine (:data:`SIGMAS`). The images are compared after a
local normalisation (:func:`normalised`), which takes out the shading and exposure that
differ between the views; its window (:data:`NORM_RADIUS`) keeps the blotches of a floor's
texture, which carry its signal. Image 2 is warped into image 1's frame before it is
blurred and normalised, so that both are filtered over the same part of the plane. The
floors of generated seeds 29 and 68, started from the planes RANSAC fits to SGM's matches
(98.9 % and 73 % of their pixels within 1 px of the truth), came within 1 px on 99.9 % and
99.4 %.

Whether the plane is a surface at all is judged by the plane alone (:func:`halves_agree`):
the same alignment on each half of the pixels, split across the rows and across the columns,
gives the same plane where the pixels lie on one, and two planes where they hold several
surfaces or a curved one. Comparing the plane's cost with SGM's pixel by pixel cannot judge
it: SGM's estimates are the minima of that cost, noise included (the floor of seed 68: the
plane's 5 x 5 windows cost more than SGM's at 68 % of the matches where they disagree, and
SGM's were right at 23 % of them, the plane's at 73 %).

An aligned plane is known beyond the matches it was aligned among: the region's other
unmatched pixels take it where image 2 warped by it matches image 1 over the normalisation's
window (:func:`agreement`, :data:`FILL_ZNCC`), and not where image 2 shows another surface
there (an occluder, a face seen in view 2 alone, a box the plain region runs into without
an edge).
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np
from numba import njit

__all__ = ["AlignImages", "agreement", "align_images", "align_plane", "halves_agree", "masked_zncc", "median_apart",
           "normalised", "normalised_region", "partners_apart"]

#: Gaussian blurs (px) of the levels the plane is aligned on, coarse to fine: at 4 px the
#: warp's linearisation holds over the 1-3 px the fitted plane is off; below 2 px the sensor
#: noise dominates a plain surface's signal (seed 68's floor: 0.20 px median error after the
#: 2 px level, 0.29 px after one more at 1 px).
SIGMAS = (4.0, 2.0)
#: Gauss-Newton steps per level: the floors of seeds 29 and 68 settled (to 0.01 px) within 3.
ITERATIONS = 4
#: The local normalisation's window: 2 x this + 1 px square. Over 15 x 15 px the blotches of
#: seed 68's floor averaged away and its alignment stalled (0.75 of its pixels within 1 px
#: after ten steps at 1 px blur); over 31 x 31 it converged.
NORM_RADIUS = 15
#: Added to the local variance (grey levels squared) before the normalisation divides by its
#: root: about an 8-bit sensor's noise, so that a window of noise alone is not blown up to
#: the contrast of a textured one.
NOISE_VARIANCE = 1.0
#: Residuals beyond this many robust standard deviations (1.4826 x the median absolute
#: residual) weigh less (Huber): pixels of another surface among the plane's.
HUBER = 1.5
#: Two planes agree where the partners they give the pixels lie a median of at most this
#: many px apart: the precision the matches are judged at.
AGREE_PX = 1.0
#: A pixel set too small to split (per half) says nothing of its planarity.
MIN_HALF_PIXELS = 500
#: An aligned plane explains image 2 about a pixel where, over the normalisation's window, image
#: 1 and image 2 warped by the plane correlate at least this much (:func:`agreement`). At the
#: finer blur a window holds about ten independent samples (961 px over a blur's 4 pi sigma^2),
#: so that a window of another surface, or one hidden in view 2, correlates at 0.5-0.7 by chance
#: in places (Wood1 conv's half-occluded strips beside its frame, Bowling1 unrect's left edge);
#: 0.8 is about three of chance's standard deviations there. The floors of generated seeds 29,
#: 68 and 88 beyond their matches: 60,000-156,000 pixels from 0.8 up, 0.992-1.000 of them
#: within 1 px of the truth.
FILL_ZNCC = 0.8
#: An aligned plane is a surface of the scene only where image 1 and image 2 warped by it
#: correlate at least this much over the pixels it was aligned on (the median of
#: :func:`agreement`): at 0.5 the signal the plane aligns is as strong as the noise, in a
#: window holding both. The halves test alone passes a plane that image 2 shows nothing of
#: (the alignment has no gradient to follow, so both halves stay where they started). The
#: aligned planes of the generated floors reach 0.84-0.96. Of the real pairs', Wood2 rect's
#: reaches 0.98 and Lampshade2's 0.68-0.82 (right: its fill 0.96-0.97 within 1 px), while
#: Bowling1 unrect's at the image's left edge has -0.51 (13 % of its pixels within 1 px) and
#: Plastic rect's box face 0.46 (its fill 0.957 within 1 px, against 0.973 from the plane
#: fitted to the matches).
ALIGNED_ZNCC = 0.5


#: The crop of image 1 that it is normalised on, and image 2 warped into, reaches this many
#: px beyond the pixels: the filters' reach (the normalisation's window, the coarser blur's
#: 4 sigma that OpenCV's kernel spans, the derivative's and the bilinear sample's pixel), so
#: that at the pixels each value is the whole image's.
MARGIN = NORM_RADIUS + 4 * int(max(SIGMAS)) + 2


class AlignImages(NamedTuple):
    """Image 1 at each of :data:`SIGMAS`, normalised (:func:`normalised`) over a crop, and image 2's
    grey values, which each step of :func:`align_plane` warps into that crop's frame before it
    blurs and normalises them."""

    image1: tuple  #: (h1, w1) float32 per level
    image2: np.ndarray  #: (H2, W2) float32: image 2's grey values
    origin1: np.ndarray  #: (2,) the crop's top-left pixel (x, y) in image 1


def normalised(gray: np.ndarray, sigma: float) -> np.ndarray:
    """``gray`` (H, W) blurred by ``sigma`` px, less its local mean, over its local standard
    deviation (:data:`NORM_RADIUS`, :data:`NOISE_VARIANCE`): (H, W) float32."""
    g = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), sigma)
    win = (2 * NORM_RADIUS + 1, 2 * NORM_RADIUS + 1)
    mean = cv2.boxFilter(g, -1, win)
    var = cv2.boxFilter(g * g, -1, win) - mean * mean
    return (g - mean) / np.sqrt(np.maximum(var, 0.0) + NOISE_VARIANCE)


def _crop(gray: np.ndarray, xy: np.ndarray, margin: int) -> tuple[np.ndarray, np.ndarray]:
    """The part of ``gray`` (H, W) around the COLMAP positions ``xy`` (N, 2), ``margin`` px
    beyond them, and its top-left pixel (x, y)."""
    h, w = gray.shape
    lo = np.clip(np.floor(xy.min(axis=0)).astype(np.int64) - margin, 0, [w - 1, h - 1])
    hi = np.clip(np.ceil(xy.max(axis=0)).astype(np.int64) + margin + 1, lo + 1, [w, h])
    return gray[lo[1]:hi[1], lo[0]:hi[0]], lo


def align_images(gray1: np.ndarray, gray2: np.ndarray, uv1: np.ndarray) -> AlignImages:
    """:class:`AlignImages` of two (H, W) grey images (image 1 uint8, image 2 uint8 or float32)
    about the pixels ``uv1`` (N, 2) of image 1, COLMAP positions."""
    crop1, origin1 = _crop(gray1, uv1, MARGIN)
    one = tuple(normalised(crop1, sigma) for sigma in SIGMAS)
    # image 2 whole: the crop of image 1 warped by a plane reaches wherever the plane puts it
    return AlignImages(one, np.asarray(gray2, np.float32), origin1.astype(np.float64))


def _sample(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``image`` bilinearly at ``xy`` (N, 2) COLMAP positions (the border replicated): (N,) float32."""
    n = len(xy)
    cols = 1024  # (OpenCV's remap takes maps under 32767 a side)
    rows = max(1, -(-n // cols))
    maps = np.zeros((2, rows * cols), np.float32)
    maps[:, :n] = (xy - 0.5).T
    out = cv2.remap(image, maps[0].reshape(rows, cols), maps[1].reshape(rows, cols), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.ravel()[:n]


def _moved(x: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The derivatives (N, 2) of the points ``x[:, :2] / x[:, 2]`` as the homogeneous points
    ``x`` (N, 3) move along ``d`` (3,)."""
    z = x[:, 2:3]
    return (d[None, :2] * z - x[:, :2] * d[2]) / (z * z)


@njit(cache=True)
def _gradient_along_depth(x, hu, hv, e, gx, gy):
    """Image 2's gradient at the partners ``x`` (N, 3) homogeneous (``H p``) along their move by
    the inverse depth ``p . abc``: the warped image's gradient ``gx``, ``gy`` (N,) float64 (image 1's
    frame) through the inverse of the warp's Jacobian (``d image1 = J^T d image2``; the
    partner's derivatives by u and v along ``hu``, ``hv``, the first two columns of ``H``),
    dotted with the partner's derivative along ``e`` (:func:`_moved`, each). (N,) float64, and
    whether every value is finite (a singular warp, a partner at infinity: not)."""
    n = x.shape[0]
    out = np.empty(n)
    for i in range(n):
        z = x[i, 2]
        zz = z * z
        ju0, ju1 = (hu[0] * z - x[i, 0] * hu[2]) / zz, (hu[1] * z - x[i, 1] * hu[2]) / zz
        jv0, jv1 = (hv[0] * z - x[i, 0] * hv[2]) / zz, (hv[1] * z - x[i, 1] * hv[2]) / zz
        dq0, dq1 = (e[0] * z - x[i, 0] * e[2]) / zz, (e[1] * z - x[i, 1] * e[2]) / zz
        det = ju0 * jv1 - jv0 * ju1
        g2x = (jv1 * gx[i] - ju1 * gy[i]) / det if det != 0.0 else np.inf
        g2y = (-jv0 * gx[i] + ju0 * gy[i]) / det if det != 0.0 else np.inf
        if not (np.isfinite(g2x) and np.isfinite(g2y)):
            return out, False
        out[i] = g2x * dq0 + g2y * dq1
    return out, True


def _partners(A: np.ndarray, e: np.ndarray, p: np.ndarray, abc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The partners (N, 2) the plane ``abc`` gives the pixels ``p`` (N, 3) homogeneous, and
    their derivatives (N, 2) by the inverse depth ``p . abc``; ``q ~ A p + e (p . abc)``."""
    x = p @ A.T + np.outer(p @ abc, e)
    return x[:, :2] / x[:, 2:3], _moved(x, e)


def _warped(image2: np.ndarray, homography: np.ndarray, origin: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``image2`` (H2, W2) float32 warped by ``homography`` (3, 3: COLMAP positions of image 1 to
    image 2's) into the box of image 1 whose top-left pixel is ``origin`` (x, y) and whose size
    is ``size`` (w, h): (h, w) float32."""
    to1 = np.array([[1.0, 0.0, origin[0] + 0.5], [0.0, 1.0, origin[1] + 0.5], [0.0, 0.0, 1.0]])
    from2 = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])
    return cv2.warpPerspective(image2, from2 @ homography @ to1, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_REPLICATE)


def align_plane(images: AlignImages, A: np.ndarray, e: np.ndarray, uv1: np.ndarray, abc: np.ndarray) -> np.ndarray:
    """The plane ``abc`` (3,) (``1 / z = a u + b v + c``, camera 1) refined so that the pixels
    ``uv1`` (N, 2) COLMAP positions of image 1 match their partners in image 2 (``images``),
    coarse to fine; ``A = K2 R K1^-1`` (3, 3) and ``e = K2 t`` (3,) give a pixel's partner
    ``q ~ A p + e (p . abc)``. Returns the refined (3,) float64 (``abc`` where a step fails).

    Each step warps image 2 by the plane into image 1's frame and then blurs and normalises
    it as image 1: blurred and normalised in its own frame, a slanted floor's image 2 is
    compared under another blur and window than image 1's (the plane's homography stretches
    them), which shifts the minimum (generated seed 224's floor: 0.31-0.46 px median off the
    truth, 0.06-0.07 px warped first)."""
    p = np.column_stack([uv1, np.ones(len(uv1))])
    # the parameters scaled to the pixels' spread, for a well-conditioned normal matrix
    scale = np.array([1.0 / max(np.ptp(uv1[:, 0]), 1.0), 1.0 / max(np.ptp(uv1[:, 1]), 1.0), 1.0])
    cur = np.asarray(abc, np.float64).copy()
    at1 = uv1 - images.origin1
    # image 2 is warped over the pixels' own box in image 1's crop (a half of them: half the work)
    shape = np.array(images.image1[0].shape[::-1])
    lo = np.clip(np.floor(at1.min(axis=0)).astype(np.int64) - MARGIN, 0, shape - 1)
    hi = np.clip(np.ceil(at1.max(axis=0)).astype(np.int64) + MARGIN + 1, lo + 1, shape)
    box = (int(hi[0] - lo[0]), int(hi[1] - lo[1]))
    at_box = at1 - lo
    for one, sigma in zip(images.image1, SIGMAS):
        i1 = _sample(one, at1)
        for _ in range(ITERATIONS):
            H = A + np.outer(e, cur)
            two = normalised(_warped(images.image2, H, images.origin1 + lo, box), sigma)
            i2 = _sample(two, at_box)
            # image 2's gradient at the partners: the warped image's, through the inverse of
            # the warp's Jacobian (d image1 = J^T d image2)
            gx = _sample(cv2.Sobel(two, cv2.CV_32F, 1, 0, ksize=1, scale=0.5), at_box).astype(np.float64)
            gy = _sample(cv2.Sobel(two, cv2.CV_32F, 0, 1, ksize=1, scale=0.5), at_box).astype(np.float64)
            along, ok = _gradient_along_depth(p @ H.T, H[:, 0].copy(), H[:, 1].copy(), e, gx, gy)
            if not ok:
                return cur
            # with a gain and offset of image 2's normalised values (least squares): its
            # contrast differs by the views' blur and sampling (0.8-1.0 on the generated floors)
            gain, offset = np.linalg.lstsq(np.column_stack([i2, np.ones_like(i2)]), i1, rcond=None)[0]
            r = (gain * i2 + offset - i1).astype(np.float64)
            J = (gain * along)[:, None] * (p / scale)
            k = HUBER * 1.4826 * max(float(np.median(np.abs(r))), 1e-6)
            w = np.minimum(1.0, k / np.maximum(np.abs(r), 1e-12))
            JW = J * w[:, None]
            try:
                step = np.linalg.solve(JW.T @ J, -(JW.T @ r))
            except np.linalg.LinAlgError:
                return cur
            cur = cur + step / scale
    return cur


def partners_apart(A: np.ndarray, e: np.ndarray, p: np.ndarray, one: np.ndarray, two: np.ndarray) -> np.ndarray:
    """The distance (px) between the partners the planes ``one`` and ``two`` give each of the
    pixels ``p`` (N, 3) homogeneous: (N,)."""
    return np.linalg.norm(_partners(A, e, p, one)[0] - _partners(A, e, p, two)[0], axis=1)


def median_apart(A: np.ndarray, e: np.ndarray, p: np.ndarray, one: np.ndarray, two: np.ndarray) -> float:
    """The median of :func:`partners_apart` over the pixels ``p`` (N, 3) homogeneous."""
    return float(np.median(partners_apart(A, e, p, one, two)))


def halves_agree(images: AlignImages, A: np.ndarray, e: np.ndarray, uv1: np.ndarray, abc: np.ndarray, *,
                 each_own: bool = False) -> bool:
    """Whether the plane ``abc`` aligned (:func:`align_plane`) on each half of the pixels ``uv1``
    (N, 2), split at their median row and at their median column, gives the same partners
    (:data:`AGREE_PX`) over all of them: one planar surface. ``each_own``: halves whose planes
    part over all the pixels still agree where each half's plane gives its own pixels the
    partners ``abc`` gives them: a half's tilt, fixed by a faint texture over its own extent
    alone, can carry its partners apart far beyond it (a floor's far half, at a grazing
    angle). The halves of a fold part from the whole plane on their own pixels where its
    step is over about three times :data:`AGREE_PX` (a step of 6 px fails, one of 3 px
    passes: the plane a median of 1 px or less from each half)."""
    p = np.column_stack([uv1, np.ones(len(uv1))])
    for axis in (1, 0):
        lower = uv1[:, axis] < np.median(uv1[:, axis])
        if min(np.count_nonzero(lower), np.count_nonzero(~lower)) < MIN_HALF_PIXELS:
            return False
        a = align_plane(images, A, e, uv1[lower], abc)
        b = align_plane(images, A, e, uv1[~lower], abc)
        if median_apart(A, e, p, a, b) <= AGREE_PX:
            continue
        if not (each_own and median_apart(A, e, p[lower], a, abc) <= AGREE_PX
                and median_apart(A, e, p[~lower], b, abc) <= AGREE_PX):
            return False
    return True


def _normalised_within(gray: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """:func:`normalised` of ``gray`` (h, w) uint8 over the pixels of ``mask`` (h, w) bool alone
    (each blur and window mean weighted by it): no intensity beyond the mask, an edge's
    included, reaches its pixels. (h, w) float32, meaningful on ``mask``."""
    m = mask.astype(np.float32)
    g = gray.astype(np.float32)
    b = cv2.GaussianBlur(g * m, (0, 0), sigma) / np.maximum(cv2.GaussianBlur(m, (0, 0), sigma), 1e-6)
    win = (2 * NORM_RADIUS + 1, 2 * NORM_RADIUS + 1)
    n = np.maximum(cv2.boxFilter(m, -1, win), 1e-6)
    mean = cv2.boxFilter(b * m, -1, win) / n
    var = cv2.boxFilter(b * b * m, -1, win) / n - mean * mean
    return (b - mean) / np.sqrt(np.maximum(var, 0.0) + NOISE_VARIANCE)


def normalised_region(gray1: np.ndarray, x0: int, y0: int, region: np.ndarray) -> np.ndarray:
    """Image 1 (``gray1``, (H, W) uint8) as :func:`agreement` compares it: over ``region`` (h, w)
    bool, whose top-left pixel is ``(x0, y0)``, at the finer blur of :data:`SIGMAS`
    (:func:`_normalised_within`); (h, w) float32."""
    h, w = region.shape
    return _normalised_within(gray1[y0:y0 + h, x0:x0 + w], region, SIGMAS[-1])


def agreement(gray1: np.ndarray, gray2: np.ndarray, homography: np.ndarray, x0: int, y0: int,
              region: np.ndarray, masks: tuple, *, image1: np.ndarray | None = None) -> list:
    """How well image 2 warped by a plane's ``homography`` (3, 3: COLMAP positions of image 1 to
    image 2's) matches image 1 about the pixels of each of ``masks`` ((h, w) bool, the top-left
    pixel ``(x0, y0)`` of image 1, within ``region``, (h, w) bool): one (h, w) float32 a mask,
    the ZNCC over the mask's pixels in the normalisation's window (:data:`NORM_RADIUS`) about
    each pixel, NaN where they are under half the window. Both are blurred at the finer blur of
    :data:`SIGMAS` and normalised in image 1's frame (as :func:`align_plane` compares them):
    image 1 within ``region`` alone (:func:`_normalised_within`: a halo of the edge around it
    would correlate with image 2's wherever the plane puts it), image 2 warped over the region's
    box and :data:`MARGIN` px about it. ``gray1``: (H, W) uint8; ``gray2``: (H2, W2) float32;
    ``image1``: image 1 so normalised already (:func:`normalised_region`), where several planes
    are compared over one region."""
    h, w = region.shape
    one = normalised_region(gray1, x0, y0, region) if image1 is None else image1
    m = MARGIN
    two = normalised(_warped(gray2, homography, np.array([x0 - m, y0 - m]), (w + 2 * m, h + 2 * m)),
                     SIGMAS[-1])[m:m + h, m:m + w]
    return [masked_zncc(one, two, mask) for mask in masks]


def masked_zncc(one: np.ndarray, two: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The ZNCC of ``one`` and ``two`` (h, w) float32 over the pixels of ``mask`` (h, w) bool in
    the normalisation's window (:data:`NORM_RADIUS`) about each pixel: (h, w) float32, NaN
    where they are under half the window."""
    win = (2 * NORM_RADIUS + 1, 2 * NORM_RADIUS + 1)

    def total(a):
        return cv2.boxFilter(a, -1, win, normalize=False, borderType=cv2.BORDER_CONSTANT)

    m = mask.astype(np.float32)
    a, b = one * m, two * m
    n = total(m)
    k = np.maximum(n, 1.0)
    sa, sb = total(a), total(b)
    cov = total(a * b) - sa * sb / k
    va = total(a * a) - sa * sa / k
    vb = total(b * b) - sb * sb / k
    z = cov / np.sqrt(np.maximum(va * vb, 1e-12))
    z[n < 0.5 * win[0] * win[1]] = np.nan
    return z
