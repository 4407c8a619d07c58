"""Image 2's tones matched to image 1's before SGM: a gain and a power per channel.

OpenCV's StereoSGBM (:mod:`.stereo_sgbm`) adds to the Birchfield-Tomasi difference of the
x-gradient images that of the raw values, divided by 4. Where the photos differ in tone
(exposure, white balance, tone curve) that second term is off at the true match, and on
smooth shading, whose gradient term is flat along the ramp, it decides: the match slides
along the ramp until the values agree (Gaussian hills of shading seen with the generated
scenes' kind of difference, exposure 0.75-1.25 and 10 % a channel each view: SGBM's matches a
median 2-12 columns off, tests/test_tone.py), and the uniqueness test and the checks reject
much of the rest (the generated scenes gained 0.05-0.07 of coverage at 1 px with the curve,
docs/results.md "Image 2's tones matched to image 1's"). Image 2 is mapped through
``v1 = gain * v2 ** power`` per channel, fitted (:func:`fit_tone_curve`) to the colours at
the coarse pass's matches (:func:`matched_colours`): tens of thousands of area-averaged
cells on every surface the pass matched, where the SIFT inliers are a few hundred blob
centres whose blurred values depend on the scale each view sees them at (on the real pairs
their fit was 2-19 levels off the curve the ground truth gives, the coarse pass's 0.3-3).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["ToneCurve", "apply_tone_curve", "fit_tone_curve", "matched_colours"]

#: Values at or below this, or at or above :data:`CLIP_HIGH`, take no part in the fit: a
#: channel clipped in either view (black or saturated) says nothing of the curve there.
CLIP_LOW = 8
CLIP_HIGH = 247
#: Fewer samples than this in a channel give no fit: a power and a gain need a spread of
#: values, and a coarse pass with fewer matches found little of the scene.
MIN_SAMPLES = 200
#: The curve is applied only where it moves image 2's values by at least this many levels on
#: average over the samples: SGBM divides its raw-value difference by 4, so a smaller shift
#: costs nearly nothing, while any remap moves the 8-bit steps on which plain walls are
#: matched (the real pairs but Monopoly: 0.1-2.0 levels; remapped,
#: Midd1 conv lost 0.073 and Midd2 unrect 0.080 of coverage at 1 px). Monopoly's pair
#: differs by 6.7 levels, the generated scenes by 2.7-30.
MIN_MEAN_SHIFT = 4.0


@dataclass(frozen=True)
class ToneCurve:
    """``v1 = gain * v2 ** power`` per channel, mapping image 2's values onto image 1's."""

    gain: np.ndarray  #: (channels,)
    power: np.ndarray  #: (channels,)
    mean_shift: float  #: mean |change| of the samples' image-2 values under the curve, grey levels

    def lut(self) -> np.ndarray:
        """(channels, 256) uint8: the curve at every 8-bit value, rounded and clipped."""
        x = np.maximum(np.arange(256.0), 0.5)  # (0 ** power stays 0 for any power > 0)
        return np.clip(np.round(self.gain[:, None] * x[None, :] ** self.power[:, None]), 0, 255).astype(np.uint8)

    @property
    def worth_applying(self) -> bool:
        """Whether the curve moves image 2's values enough to matter (:data:`MIN_MEAN_SHIFT`)."""
        return self.mean_shift >= MIN_MEAN_SHIFT


def matched_colours(L1: np.ndarray, L2: np.ndarray, disp: np.ndarray, min_d: int) -> tuple[np.ndarray, np.ndarray]:
    """The colours of the cells of line image 1 with a disparity (``disp >= min_d``) and of
    their partners in line image 2 (shifted by ``min_d``, as :func:`.lines.line_images` makes
    it): ``(v1, v2)``, each (n, channels) uint8; cells beyond either image (0) are left out."""
    rows, cols = np.nonzero(disp >= min_d)
    c2 = np.round(cols - (disp[rows, cols] - min_d)).astype(np.intp)
    inside = (c2 >= 0) & (c2 < L2.shape[1])
    rows, cols, c2 = rows[inside], cols[inside], c2[inside]
    v1 = L1[rows, cols].reshape(len(rows), -1)
    v2 = L2[rows, c2].reshape(len(rows), -1)
    seen = (v1 > 0).all(axis=1) & (v2 > 0).all(axis=1)
    return v1[seen], v2[seen]


def fit_tone_curve(v1: np.ndarray, v2: np.ndarray) -> ToneCurve | None:
    """The curve mapping the values ``v2`` (n, channels) of image 2 onto ``v1`` of image 1:
    per channel a line through the logarithms of their quantiles (sorted values, paired by
    rank), so that a wrong partner among the samples moves the fit no more than its rank
    does; None where a channel has fewer than :data:`MIN_SAMPLES` unclipped pairs."""
    v1 = np.asarray(v1, np.float64).reshape(len(v1), -1)
    v2 = np.asarray(v2, np.float64).reshape(len(v2), -1)
    gain, power, shift = [], [], []
    for c in range(v1.shape[1]):
        q1, q2 = np.sort(v1[:, c]), np.sort(v2[:, c])
        ok = (q1 > CLIP_LOW) & (q1 < CLIP_HIGH) & (q2 > CLIP_LOW) & (q2 < CLIP_HIGH)
        if np.count_nonzero(ok) < MIN_SAMPLES:
            return None
        k, log_a = np.polyfit(np.log(q2[ok]), np.log(q1[ok]), 1)
        gain.append(float(np.exp(log_a)))
        power.append(float(k))
        shift.append(float(np.mean(np.abs(np.exp(log_a) * v2[:, c] ** k - v2[:, c]))))
    return ToneCurve(np.array(gain), np.array(power), float(np.mean(shift)))


def apply_tone_curve(image: np.ndarray, curve: ToneCurve) -> np.ndarray:
    """``image`` (H, W[, channels]) uint8 through ``curve`` (one look-up table a channel)."""
    lut = curve.lut()
    if image.ndim == 2:
        return cv2.LUT(image, lut[0])
    return cv2.merge([cv2.LUT(np.ascontiguousarray(image[..., c]), lut[c]) for c in range(image.shape[2])])
