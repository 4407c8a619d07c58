"""Image 2's tones matched to image 1's (matching/tone.py): the fit, its gate, and SGM on smooth shading."""

import cv2
import numpy as np
import pytest

from sefm_recon.matching.stereo_sgbm import sgbm_disparity
from sefm_recon.matching.tone import (MIN_MEAN_SHIFT, ToneCurve, apply_tone_curve, fit_tone_curve,
                                      matched_colours)

#: image 2 = gain * scene ** power per channel: about 0.4 of a stop darker, white balance and tone curve apart
TONES = ((0.75, 1.04), (0.8, 1.03), (0.7, 1.05))


def _noisy_u8(a, rng, sigma=0.7):
    return np.clip(np.round(a + rng.normal(0, sigma, a.shape)), 0, 255).astype(np.uint8)


def _toned(values, tones=TONES):
    return np.stack([g * values ** k for g, k in tones], axis=-1)


def _samples(rng, n=5000):
    """Matched colours (v1, v2), (n, 3) uint8 each: scene values 20..240, image 2 through TONES."""
    scene = rng.uniform(20, 240, n)
    return _noisy_u8(np.stack([scene] * 3, axis=-1), rng), _noisy_u8(_toned(scene), rng)


def test_the_fit_recovers_a_gain_and_power_per_channel_within_a_level():
    curve = fit_tone_curve(*_samples(np.random.default_rng(0)))
    x = np.arange(20, 180.0)  # image 2's values of the scene's 20..240 (or below)
    for c, (g, k) in enumerate(TONES):
        inverse = (x / g) ** (1.0 / k)  # the value image 1 has where image 2 has x
        fitted = curve.gain[c] * x ** curve.power[c]
        assert np.max(np.abs(fitted - inverse)) < 1.0
    assert curve.worth_applying


def test_wrong_partners_among_the_samples_move_the_fit_little():
    rng = np.random.default_rng(1)
    v1, v2 = _samples(rng)
    clean = fit_tone_curve(v1, v2)
    wrong = rng.random(len(v2)) < 0.1  # a tenth matched to some other colour
    v2[wrong] = rng.integers(0, 256, (int(wrong.sum()), 3))
    noisy = fit_tone_curve(v1, v2)
    x = np.arange(30, 170.0)
    for c in range(3):
        assert np.max(np.abs(noisy.gain[c] * x ** noisy.power[c] - clean.gain[c] * x ** clean.power[c])) < 6.0


def test_views_of_one_exposure_are_left_as_they_are():
    rng = np.random.default_rng(2)
    scene = rng.uniform(20, 240, (5000, 3))
    curve = fit_tone_curve(_noisy_u8(scene, rng), _noisy_u8(scene + 1.0, rng))  # one level apart
    assert curve.mean_shift < MIN_MEAN_SHIFT and not curve.worth_applying


def test_too_few_unclipped_samples_give_no_fit():
    rng = np.random.default_rng(3)
    v = rng.integers(0, 256, (150, 3)).astype(np.uint8)
    assert fit_tone_curve(v, v) is None
    saturated = np.full((5000, 3), 255, np.uint8)
    assert fit_tone_curve(saturated, saturated) is None


def test_the_curve_maps_every_value_through_its_channels_table():
    curve = ToneCurve(np.array([1.0, 2.0, 0.5]), np.array([1.0, 1.0, 1.0]), 10.0)
    img = np.dstack([np.full((2, 3), v, np.uint8) for v in (10, 100, 200)])
    out = apply_tone_curve(img, curve)
    assert out.shape == img.shape and out.dtype == np.uint8
    assert (out[..., 0] == 10).all() and (out[..., 1] == 200).all() and (out[..., 2] == 100).all()
    assert (apply_tone_curve(img[..., 1], curve) == 100).all()  # grey: the first channel's table


def test_matched_colours_pairs_each_cell_with_its_partner():
    rng = np.random.default_rng(4)
    L2 = rng.integers(1, 256, (4, 30, 3)).astype(np.uint8)
    L1 = np.zeros_like(L2)
    L1[:, 5:] = L2[:, 2:-3]  # L1[x] = L2[x - 3]: disparity 3 with image 2 unshifted
    disp = np.full((4, 30), -1, np.float32)
    disp[:, 5:] = 3.0
    disp[0, 10] = 40.0  # a partner beyond line image 2's left end
    v1, v2 = matched_colours(L1, L2, disp, 0)
    assert len(v1) == 4 * 25 - 1
    assert np.array_equal(v1, v2)


@pytest.mark.parametrize("sigma", [25.0, 40.0])
def test_sgm_on_smooth_shading_finds_the_true_disparity_once_the_tones_match(sigma):
    """Smooth shading (Gaussian hills, 150 levels high) seen with the tone difference of
    TONES, 12 columns apart: SGBM's raw-value term slides the matches along the ramps;
    through the curve fitted to the true matches' colours they come within a column."""
    rng = np.random.default_rng(5)
    h, w, d, pad = 160, 400, 12, 48
    yy, xx = np.mgrid[0:h, 0:w + d].astype(np.float64)
    scene = 50 + sum(150 * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma**2))
                     for cx, cy in ((100, 60), (250, 110), (340, 40)))
    # line images as SGM gets them: a pad left of both, for the search window of the first columns
    L1, L2 = (cv2.copyMakeBorder(a, 0, 0, pad, 0, cv2.BORDER_REPLICATE) for a in (
        np.dstack([_noisy_u8(scene[:, :w], rng)] * 3), _noisy_u8(_toned(scene[:, d:]), rng)))  # L2[x - 12] = L1[x]

    def within_a_column(B):
        disp = sgbm_disparity(L1, B, 0, 32, 10)[0][:, pad:]
        found = disp >= 0
        return np.mean(np.abs(disp[found] - d) <= 1.0)

    truth = np.full((h, w + pad), d, np.float32)
    truth[:, :pad + d] = -1.0
    curve = fit_tone_curve(*matched_colours(L1, L2, truth, 0))
    assert curve.worth_applying
    assert within_a_column(L2) < 0.3
    assert within_a_column(apply_tone_curve(L2, curve)) > 0.85
