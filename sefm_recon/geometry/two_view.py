"""Two-view geometry through pycolmap: SIFT, matching, RANSAC, relative pose.

Works on undistorted pinhole images (see :mod:`sefm_recon.geometry.undistort`),
so cameras here are 3x3 matrices ``K``. The relative pose is COLMAP's
``cam2_from_cam1``: ``x_cam2 = R @ x_cam1 + t``, with ``|t| = 1`` when estimated.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np
import pycolmap

from ..errors import InputError

logger = logging.getLogger(__name__)


@dataclass
class TwoView:
    """Relative geometry of a pair, in the working (undistorted) pixel frame."""

    K1: np.ndarray  #: (3, 3)
    K2: np.ndarray  #: (3, 3)
    R: np.ndarray  #: (3, 3) cam2_from_cam1 rotation
    t: np.ndarray  #: (3,) cam2_from_cam1 translation
    kp1: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  #: (N, 2) inlier SIFT points, image 1
    kp2: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  #: (N, 2) inlier SIFT points, image 2
    num_sift_matches: int = 0  #: putative SIFT matches before geometric verification
    source: str = "estimated"  #: "estimated" or "given"

    @property
    def E(self) -> np.ndarray:
        """Essential matrix, ``x2^T E x1 = 0`` for normalised camera rays."""
        return skew(self.t) @ self.R

    @property
    def F(self) -> np.ndarray:
        """Fundamental matrix in working pixel coordinates (COLMAP convention)."""
        return np.linalg.inv(self.K2).T @ self.E @ np.linalg.inv(self.K1)


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[v]_x``."""
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]], dtype=np.float64)


def sift_scale(w: int, h: int, max_size: int) -> float:
    """The scale SIFT works at: longer side at most ``max_size``, or at most ``max_size**2 / 2`` pixels.

    The pixel bound only matters for a photo longer than 2:1. Scaled by its
    longer side alone, a 4000x100 strip became 1024x26 and kept too few rows
    for SIFT's features ("too little texture" on a textured photo); its pixels
    are fewer than an ordinary photo's at ``max_size``, so it keeps them.
    """
    if not max_size or w * h == 0:
        return 1.0
    return min(1.0, max(max_size / max(w, h), float(np.sqrt(max_size * max_size / 2.0 / (w * h)))))


def extract_sift(gray: np.ndarray, max_features: int = 8192, max_size: int = 0,
                 upsample_max_size: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints and descriptors with pycolmap (COLMAP's CPU SIFT).

    Args:
        gray: (H, W) uint8 image.
        max_size: longest side SIFT works at (:func:`sift_scale`; 0 = full size).
        upsample_max_size: start at octave -1 (COLMAP's default) when the image
            SIFT works on is no longer than this; else at octave 0.
    Returns:
        xy (N, 2) float64 keypoint positions (COLMAP pixel convention) and
        (N, 128) float32 descriptors.
    """
    small, factor = _sift_input(gray, max_size)
    xy, desc = _colmap_sift(small, max_features, upsample_max_size)
    return xy * factor, desc


def _sift_input(gray: np.ndarray, max_size: int) -> tuple[np.ndarray, np.ndarray]:
    """The image SIFT works on (:func:`sift_scale`) and the factor (2,) back to ``gray``'s pixels."""
    h, w = gray.shape[:2]
    s = sift_scale(w, h, max_size)
    if s >= 1.0:
        return np.ascontiguousarray(gray), np.ones(2)
    # Relative pose needs well spread inliers, not full resolution, and SIFT's
    # cost grows with the pixels. COLMAP pixel edges scale exactly.
    ws, hs = max(1, round(w * s)), max(1, round(h * s))
    return cv2.resize(gray, (ws, hs), interpolation=cv2.INTER_AREA), np.array([w / ws, h / hs])


def _colmap_sift(gray: np.ndarray, max_features: int, upsample_max_size: int) -> tuple[np.ndarray, np.ndarray]:
    """pycolmap's CPU SIFT on ``gray`` as it is: positions (N, 2) float64 and descriptors (N, 128) float32."""
    opts = pycolmap.FeatureExtractionOptions()
    opts.sift.max_num_features = int(max_features)
    # COLMAP starts at octave -1 (the image upsampled 2x) for the finest
    # features: on a small photo they are the matches a pose needs; a large one
    # has plenty at octave 0, where the cost is a quarter.
    opts.sift.first_octave = -1 if max(gray.shape[:2]) <= upsample_max_size else 0
    opts.use_gpu = False
    extractor = pycolmap.FeatureExtractor.create(opts, device=pycolmap.Device.cpu)
    keypoints, descriptors = extractor.extract_from_uint8_array(np.ascontiguousarray(gray))
    xy = pycolmap.keypoints_to_matrix(keypoints)[:, :2].astype(np.float64)
    return xy, np.asarray(descriptors.data, dtype=np.float32)


def extract_sift_pair(gray1: np.ndarray, gray2: np.ndarray, max_features: int = 8192, max_size: int = 0,
                      upsample_max_size: int = 0):
    """:func:`extract_sift` of both images, image 2's in a child process where one can run beside this one.

    COLMAP's CPU SIFT runs on one core and holds Python's interpreter lock, so two
    threads take as long as one image after the other; a child forked for image 2
    (:class:`~sefm_recon.forked.Forked`) gives the same features in half the time on
    two cores (the bench pair: 1.5 s against 2.8 s). Where it cannot run (not Linux,
    one core) or fails, image 2 is done here.
    Returns ``((xy1, desc1), (xy2, desc2))`` as :func:`extract_sift`'s.
    """
    from ..forked import Forked

    small1, f1 = _sift_input(gray1, max_size)
    small2, f2 = _sift_input(gray2, max_size)
    with Forked(_colmap_sift, small2, max_features, upsample_max_size) as second:
        xy1, d1 = _colmap_sift(small1, max_features, upsample_max_size)
        xy2, d2 = second.result()
    return (xy1 * f1, d1), (xy2 * f2, d2)


def match_descriptors(desc1: np.ndarray, desc2: np.ndarray, max_ratio: float = 0.8) -> np.ndarray:
    """Mutual nearest neighbours that pass Lowe's ratio test, (M, 2) uint32 indices.

    OpenCV's FLANN matcher: pycolmap's CPU matcher gives nearly the same matches
    but is several times slower for a few thousand features.
    """
    if len(desc1) < 2 or len(desc2) < 2:
        return np.zeros((0, 2), np.uint32)
    # FLANN's randomised k-d trees: near-exact for SIFT, several times faster
    # than brute force for thousands of features. Their random draws come from
    # OpenCV's RNG, so it is seeded: otherwise a pair's matches (and pose) depend
    # on what ran before in the process (Bowling1 rect: 227 putative matches alone,
    # 229 after another pair, 0.007 of precision at 1 px between the two).
    # The two directions run side by side (OpenCV lets go of Python's lock; 0.44 -> 0.24-0.28 s
    # on the bench pair's 9,900 features each), each seeding its own thread's generator
    # (OpenCV's RNG is per thread): the same trees whichever thread runs first.
    def nearest(query, train, k):
        cv2.setRNGSeed(0)
        matcher = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})
        return matcher.knnMatch(query, train, k=k)

    with ThreadPoolExecutor(max_workers=2) as pool:
        job = pool.submit(nearest, desc2, desc1, 1)
        fwd = nearest(desc1, desc2, 2)
        bwd = [m[0] for m in job.result() if m]
    back = np.full(len(desc2), -1, np.int64)
    for m in bwd:
        back[m.queryIdx] = m.trainIdx
    pairs = [
        (m[0].queryIdx, m[0].trainIdx)
        for m in fwd
        if len(m) == 2 and m[0].distance < max_ratio * m[1].distance and back[m[0].trainIdx] == m[0].queryIdx
    ]
    return np.asarray(pairs, dtype=np.uint32).reshape(-1, 2)


def sift_correspondences(gray1, gray2, max_features: int = 8192, max_ratio: float = 0.8, min_features: int = 0,
                         names: tuple[str, str] = ("image 1", "image 2"), max_size: int = 0,
                         upsample_max_size: int = 0):
    """Putative SIFT correspondences ``(xy1 (M, 2), xy2 (M, 2))`` between two images.

    Raises :class:`InputError` when an image has fewer than ``min_features``
    SIFT features (a textureless image: nothing to estimate geometry from).
    """
    (xy1, d1), (xy2, d2) = extract_sift_pair(gray1, gray2, max_features, max_size, upsample_max_size)
    for xy, name in ((xy1, names[0]), (xy2, names[1])):
        if len(xy) < min_features:
            raise InputError(
                f"{name} has too little texture: {len(xy)} SIFT features found, at least {min_features} are "
                "needed to estimate the geometry (a blank, flat or heavily blurred image cannot be matched)"
            )
    m = match_descriptors(d1, d2, max_ratio)
    logger.info("SIFT: %d and %d features, %d putative matches", len(xy1), len(xy2), len(m))
    return xy1[m[:, 0]], xy2[m[:, 1]]


def calibrated_ransac(cam1: pycolmap.Camera, xy1: np.ndarray, cam2: pycolmap.Camera, xy2: np.ndarray,
                      max_error: float, min_num_inliers: int, seed: int = 0,
                      planar: bool = True) -> pycolmap.TwoViewGeometry:
    """pycolmap's essential-matrix RANSAC and relative pose on the correspondences ``xy1[i] <-> xy2[i]``
    (M, 2), with ``max_error`` (px) as inlier threshold and its random draws from ``seed``; without
    ``planar``, the essential matrix's pose even where one homography holds most inliers (COLMAP's
    planar configuration, whose pose it takes from the homography)."""
    opts = pycolmap.TwoViewGeometryOptions()
    opts.compute_relative_pose = True
    opts.ransac.max_error = float(max_error)
    opts.ransac.random_seed = int(seed)
    opts.min_num_inliers = int(min_num_inliers)
    opts.detect_watermark = False
    if not planar:
        # the most COLMAP allows: planar only where a homography holds more inliers than E
        opts.max_H_inlier_ratio = 1.0
    matches = np.stack([np.arange(len(xy1)), np.arange(len(xy1))], 1).astype(np.uint32)
    return pycolmap.estimate_calibrated_two_view_geometry(
        cam1, np.ascontiguousarray(xy1, np.float64), cam2, np.ascontiguousarray(xy2, np.float64), matches, opts)


def estimate_two_view(
    xy1: np.ndarray,
    xy2: np.ndarray,
    K1: np.ndarray,
    K2: np.ndarray,
    size1: tuple[int, int],
    size2: tuple[int, int],
    min_inliers: int = 30,
    max_error: float = 2.0,
    min_tri_angle_deg: float = 0.5,
    focal_known: bool = True,
) -> TwoView:
    """Essential matrix by RANSAC and the relative pose, through pycolmap.

    Args:
        xy1, xy2: (M, 2) putative correspondences, working pixel coordinates.
        size1, size2: (width, height) of the working images.
        focal_known: False when ``K1``/``K2`` are guesses (no EXIF, no --camera):
            then a pure rotation cannot be told from its triangulation angles,
            and the homography's own test (:func:`rotation_homography`) is used.
    Raises:
        InputError: too few inliers (unrelated images or too little overlap), or
            no baseline (the same photo twice, or a pure rotation: :func:`rotation_parallax`).
            A narrow baseline (median triangulation angle below ``min_tri_angle_deg``)
            is only a warning: its depth is noisy, not wrong.
    """
    from ..io.cameras import pinhole_camera

    cam1 = pinhole_camera(K1, *size1, 1)
    cam2 = pinhole_camera(K2, *size2, 2)

    def ransac(min_num_inliers: int):
        tvg = calibrated_ransac(cam1, xy1, cam2, xy2, max_error, min_num_inliers)
        return tvg, np.asarray(tvg.inlier_matches, dtype=np.int64).reshape(-1, 2), int(tvg.config)

    def too_little_overlap(found: int) -> InputError:
        return InputError(
            f"too little overlap between the images: {found} geometric inliers found among {len(xy1)} SIFT "
            f"matches, at least {min_inliers} are needed (do both photos show the same scene, from nearby "
            "viewpoints?)"
        )

    C = pycolmap.TwoViewGeometryConfiguration
    bad = (int(C.UNDEFINED), int(C.DEGENERATE))
    if len(xy1) < min_inliers:
        # Count the inliers anyway (5 is the least an essential matrix needs), for the message.
        found = len(ransac(5)[1]) if len(xy1) >= 5 else 0
        raise too_little_overlap(min(found, len(xy1)))
    tvg, inliers, config = ransac(min_inliers)
    names = {int(v): k for k, v in C.__members__.items()}
    logger.info("two-view geometry: %s with %d inliers of %d", names.get(config, config), len(inliers), len(xy1))
    if len(inliers) < min_inliers or config in bad:
        found = len(inliers)
        if found == 0:
            _, inl, cfg5 = ransac(5)
            found = len(inl) if cfg5 not in bad else 0
        raise too_little_overlap(found)
    if config in (int(C.PANORAMIC), int(C.PLANAR_OR_PANORAMIC)) and _median_parallax_px(xy1[inliers[:, 0]], xy2[inliers[:, 1]]) < 1.0:
        raise InputError(
            "no baseline between the images: they are the same photo, or the camera did not move, "
            "so no depth can be recovered (take the second photo from a different position)"
        )
    planar = (int(C.PANORAMIC), int(C.PLANAR_OR_PANORAMIC), int(C.PLANAR))
    if not focal_known and config in planar:
        turn = rotation_homography(xy1[inliers[:, 0]], xy2[inliers[:, 1]], max_error)
        if turn is not None:
            raise InputError(
                f"no baseline between the images: one homography maps every match, as a pure rotation of the camera "
                f"(by about {turn:.1f} deg) does, so no depth can be recovered; if the camera did move and the scene "
                "is one flat surface, give the true camera with --camera"
            )
    pose = tvg.cam2_from_cam1
    if pose is None:
        raise InputError("could not recover a relative pose from the matches (degenerate geometry)")
    pose = refine_on_inliers(pose, cam1, cam2, xy1[inliers[:, 0]], xy2[inliers[:, 1]])
    if focal_known and config in planar:
        pose, inliers = _essential_if_better(pose, inliers, cam1, cam2, xy1, xy2, max_error, min_inliers)
    tv = TwoView(K1, K2, *rotation_translation(pose), xy1[inliers[:, 0]], xy2[inliers[:, 1]], len(xy1))
    angle = float(np.degrees(np.median(triangulation_angles(tv))))
    turn, parallax = rotation_parallax(tv)
    if not np.isfinite(parallax) or parallax < ROTATION_PARALLAX_PX:
        raise InputError(
            f"no baseline between the images: a pure rotation of the camera (by {turn:.1f} deg) explains the SIFT "
            f"inliers to a median {parallax:.2f} px (median triangulation angle {angle:.2f} deg), so the camera "
            "only turned or did not move and no depth can be recovered (take the second photo from a different "
            "position)"
        )
    if angle < min_tri_angle_deg:
        logger.warning(
            "narrow baseline: median triangulation angle %.2f deg, below the comfortable %g deg "
            "(geometry.min_tri_angle_deg); the depth will be noisy (%.1f px of parallax beyond a pure rotation)",
            angle, min_tri_angle_deg, parallax)
    return tv


#: Where one homography holds most SIFT inliers (a wall filling the view), COLMAP takes the
#: pose from it; decomposed, a homography gives two poses that explain the plane alike, and the
#: one kept can be the wrong one (generated zoom seed 75: 4.2 deg off in rotation, 21 deg in
#: translation direction, against 0.05 and 0.23 deg from the essential matrix). The essential
#: matrix's pose replaces it where it holds clearly more of the matches within the RANSAC
#: threshold (seed 75: 222 more of 2,342): more by over this many standard deviations of a
#: fair coin's count over the matches the two poses disagree on (a sign test; two, the usual
#: 95 % bound), and by at least as many as a geometry needs (``geometry.min_inliers``): a
#: handful near the threshold tells two right poses apart by their noise (converging seed 9:
#: 7 more for the essential matrix's pose, 0.18 deg off in translation direction against the
#: homography's 0.08). On a plane alone both poses hold the same matches and the
#: homography's, the more accurate there (0.1-0.9 deg against 0.5-1.3 in rotation on a
#: generated plane), stays.
ESSENTIAL_SIGMAS = 2.0


def _essential_if_better(pose: pycolmap.Rigid3d, inliers: np.ndarray, cam1: pycolmap.Camera, cam2: pycolmap.Camera,
                         xy1: np.ndarray, xy2: np.ndarray, max_error: float, min_inliers: int):
    """``(pose, inliers)``: the homography's refined ``pose`` and its ``inliers`` (k, 2), or the
    essential matrix's where its epipolar lines hold clearly more of the matches ``xy1``,
    ``xy2`` (M, 2) within ``max_error`` px, by :data:`ESSENTIAL_SIGMAS` and ``min_inliers``."""
    C = pycolmap.TwoViewGeometryConfiguration
    alt = calibrated_ransac(cam1, xy1, cam2, xy2, max_error, min_inliers, planar=False)
    alt_inl = np.asarray(alt.inlier_matches, dtype=np.int64).reshape(-1, 2)
    if alt.cam2_from_cam1 is None or int(alt.config) != int(C.CALIBRATED) or len(alt_inl) < min_inliers:
        return pose, inliers
    alt_pose = refine_on_inliers(alt.cam2_from_cam1, cam1, cam2, xy1[alt_inl[:, 0]], xy2[alt_inl[:, 1]])
    K1, K2 = cam1.calibration_matrix(), cam2.calibration_matrix()
    held = [epipolar_distances(TwoView(K1, K2, *rotation_translation(p)).F, xy1, xy2) <= max_error
            for p in (pose, alt_pose)]
    gain, loss = int(np.count_nonzero(held[1] & ~held[0])), int(np.count_nonzero(held[0] & ~held[1]))
    if gain - loss > max(ESSENTIAL_SIGMAS * np.sqrt(gain + loss), min_inliers):
        logger.info("the essential matrix's pose holds %d more SIFT matches than the homography's: kept", gain - loss)
        return alt_pose, alt_inl
    return pose, inliers


#: The pose is then refined again over the inliers within this many standard deviations
#: of its epipolar lines (sigma from their median distance, half-normal: median = 0.6745
#: sigma), and again with the inliers that pass around the new pose, until they stay the
#: same or :data:`ROBUST_ROUNDS` have run. Least squares over every RANSAC inlier (up to
#: its 2 px threshold) lets the few near the threshold pull the pose; 3 sigma is the usual
#: outlier bound of a normal error. Over the 60 real cases (true camera) the median
#: rotation error fell 0.071 -> 0.030 deg and the translation direction's 0.295 -> 0.177
#: deg (mean 0.689 -> 0.318, largest 3.05 -> 1.92); over the 20 generated scenes 0.020 ->
#: 0.006 and 0.091 -> 0.028 deg (scripts/eval_pose.py).
ROBUST_SIGMAS = 3.0
ROBUST_ROUNDS = 5


def refine_on_inliers(pose: pycolmap.Rigid3d, cam1: pycolmap.Camera, cam2: pycolmap.Camera,
                      xy1: np.ndarray, xy2: np.ndarray) -> pycolmap.Rigid3d:
    """The relative pose refined over its inliers: first over all of them (pycolmap's
    ``refine_relative_pose``: least squares of the tangent Sampson error), kept where that
    brings them closer to its epipolar lines (median distance), then over those within
    :data:`ROBUST_SIGMAS` of its lines, repeated (:data:`ROBUST_ROUNDS`).

    ``estimate_calibrated_two_view_geometry`` decomposes the essential matrix its RANSAC
    found without refining the pose over every inlier; where the geometry is nearly
    degenerate (the camera moving along its axis: a generated zoom pair) that left a pose
    6.2 deg off in rotation and 22 deg in translation direction, refined to 0.09 and 0.27
    deg (inliers' median 0.208 -> 0.186 px). Least squares over all of them is not robust:
    on a converging pair, a few inliers near the 2 px threshold pulled a pose 0.09 deg off
    in translation direction to 1.2 deg, and the inliers' median rose 0.090 -> 0.116 px;
    the median keeps the better of the two. The rounds over the inliers near the lines
    then leave those few out. (Those rounds alone, from RANSAC's pose, kept the zoom
    pair's: its inliers within 3 sigma of a pose 6 deg off are those that pose fits.)
    """
    xy1, xy2 = np.ascontiguousarray(xy1, np.float64), np.ascontiguousarray(xy2, np.float64)
    K1, K2 = cam1.calibration_matrix(), cam2.calibration_matrix()
    old_tv = TwoView(K1, K2, *rotation_translation(pose), xy1, xy2)
    out = pycolmap.refine_relative_pose(pose, cam1, xy1, cam2, xy2, np.ones((len(xy1), 1), bool))
    if out is not None:
        new = out["cam2_from_cam1"]
        new_tv = TwoView(K1, K2, *rotation_translation(new))
        if inlier_evidence(new_tv, old_tv)[0] < inlier_evidence(old_tv, old_tv)[0]:
            pose = new
    mask = None
    for _ in range(ROBUST_ROUNDS):
        d = epipolar_distances(TwoView(K1, K2, *rotation_translation(pose)).F, xy1, xy2)
        near = d <= ROBUST_SIGMAS * np.median(d) / 0.6745
        if (mask is not None and np.array_equal(near, mask)) or near.sum() < 8:  # 8: as many as an F needs
            break
        mask = near
        out = pycolmap.refine_relative_pose(pose, cam1, xy1, cam2, xy2, mask.reshape(-1, 1))
        if out is None:
            break
        pose = out["cam2_from_cam1"]
    return pose


#: The consensus test (:func:`resampled_consensus`) draws this many subsets of the
#: putative matches, each :data:`RESAMPLE_SHARE` of them: most of the matches, so that a
#: pose they determine comes back (0.97-1.0 of its inliers explained over the 60 real
#: cases), and enough draws for a steady median, at eight RANSACs' cost.
RESAMPLE_ROUNDS = 8
RESAMPLE_SHARE = 0.8


def resampled_consensus(xy1: np.ndarray, xy2: np.ndarray, tv: TwoView, size1: tuple[int, int],
                        size2: tuple[int, int], max_error: float = 2.0, rounds: int = RESAMPLE_ROUNDS,
                        share: float = RESAMPLE_SHARE) -> float:
    """How much of the pose's consensus survives when the matches are resampled: the
    median, over ``rounds`` random subsets of ``share`` of the putative matches (seeded),
    of the share of ``tv``'s inliers that the essential matrix RANSAC finds on the subset
    places within ``max_error`` (px) of its epipolar lines (0 where it finds none).

    A pose the matches determine comes back from any large subset of them (0.9-1.0); a
    consensus found by chance among a few distinctive matches does not: another subset
    gives another pose, which explains another set of matches.

    Args:
        xy1, xy2: (M, 2) putative correspondences, working pixel coordinates.
        tv: the pose found on all of them, with its inliers.
        size1, size2: (width, height) of the working images.
    """
    from ..io.cameras import pinhole_camera

    if len(tv.kp1) == 0:
        return 0.0
    cam1, cam2 = pinhole_camera(tv.K1, *size1, 1), pinhole_camera(tv.K2, *size2, 2)
    rng = np.random.default_rng(0)
    n = max(5, int(round(share * len(xy1))))
    shares = []
    for k in range(rounds):
        pick = np.sort(rng.choice(len(xy1), size=min(n, len(xy1)), replace=False))
        g = calibrated_ransac(cam1, xy1[pick], cam2, xy2[pick], max_error, 5, seed=k + 1)  # 5: an E's least
        if g.cam2_from_cam1 is None:
            shares.append(0.0)
            continue
        other = TwoView(tv.K1, tv.K2, *rotation_translation(g.cam2_from_cam1))
        shares.append(float(np.mean(epipolar_distances(other.F, tv.kp1, tv.kp2) < max_error)))
    return float(np.median(shares))


def rotation_translation(pose: pycolmap.Rigid3d) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` of a pycolmap ``cam2_from_cam1``, ``t`` of unit length (an estimated pose has no scale)."""
    R = np.asarray(pose.rotation.matrix(), dtype=np.float64)
    t = np.asarray(pose.translation, dtype=np.float64).reshape(3)
    return R, t / max(np.linalg.norm(t), 1e-12)


#: A pose is refused as a pure rotation when the best rotation alone moves the SIFT
#: inliers to within this median distance (px) of their matches: SIFT keypoints are
#: located to about half a pixel, so a pure rotation leaves about that, while a pair
#: with depth from its baseline (tsukuba, 384x288, 5-15 px disparities) leaves more.
ROTATION_PARALLAX_PX = 1.0


def rotation_parallax(tv: TwoView) -> tuple[float, float]:
    """The rotation (deg) that best maps image 1's inlier rays onto image 2's, and the
    median distance (px, at image 2's focal length) it leaves: the parallax a
    translation has to explain. Wahba's problem (SVD), independent of ``tv.R``: a
    pure rotation's essential matrix leaves the translation undetermined.
    """
    if len(tv.kp1) < 3:
        return 0.0, float("nan")
    r1 = np.c_[tv.kp1, np.ones(len(tv.kp1))] @ np.linalg.inv(tv.K1).T
    r2 = np.c_[tv.kp2, np.ones(len(tv.kp2))] @ np.linalg.inv(tv.K2).T
    r1 /= np.linalg.norm(r1, axis=1, keepdims=True)
    r2 /= np.linalg.norm(r2, axis=1, keepdims=True)
    U, _, Vt = np.linalg.svd(r2.T @ r1)
    Rw = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    p = (r1 @ Rw.T) @ tv.K2.T
    d = np.linalg.norm(p[:, :2] / p[:, 2:3] - tv.kp2, axis=1)
    turn = float(np.degrees(np.arccos(np.clip((np.trace(Rw) - 1) / 2, -1, 1))))
    return turn, float(np.median(d))


#: A homography whose eigenvalues differ in magnitude by less than this share is
#: taken for a pure rotation (a rotation's homography ``K R K^-1`` is similar to
#: ``R``: eigenvalues 1, e^{+-i theta}, whatever ``K``).
ROTATION_EIG_TOL = 0.002


def rotation_homography(xy1: np.ndarray, xy2: np.ndarray, max_error: float = 2.0) -> float | None:
    """Rotation angle (deg) when the matches fit a homography similar to a rotation, else None.

    The test needs no intrinsics: ``H = K2 R K1^-1`` with ``K1 = K2`` has the
    eigenvalues of ``R`` up to scale. A flat scene seen after a translation gives
    ``K (R + t n^T / d) K^-1`` instead, whose eigenvalue magnitudes differ (but
    not always: the test is only used when the focal length is a guess).
    """
    if len(xy1) < 8:
        return None
    H, mask = cv2.findHomography(xy1.astype(np.float64), xy2.astype(np.float64), cv2.RANSAC, float(max_error))
    if H is None or mask is None or mask.mean() < 0.9:
        return None
    det = np.linalg.det(H)
    if not np.isfinite(det) or abs(det) < 1e-12:
        return None
    lam = np.linalg.eigvals(H / np.cbrt(det))
    mag = np.abs(lam)
    theta = float(np.degrees(np.max(np.abs(np.angle(lam)))))
    if mag.max() / mag.min() - 1.0 < ROTATION_EIG_TOL and theta > 0.5:
        return theta
    return None


def _median_parallax_px(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.median(np.linalg.norm(a - b, axis=1))) if len(a) else 0.0


def triangulation_angles(tv: TwoView) -> np.ndarray:
    """Angle (radians) between the two viewing rays of each inlier SIFT match."""
    r1 = np.c_[tv.kp1, np.ones(len(tv.kp1))] @ np.linalg.inv(tv.K1).T
    r2 = (np.c_[tv.kp2, np.ones(len(tv.kp2))] @ np.linalg.inv(tv.K2).T) @ tv.R  # into cam1 axes
    r1 /= np.linalg.norm(r1, axis=1, keepdims=True)
    r2 /= np.linalg.norm(r2, axis=1, keepdims=True)
    return np.arccos(np.clip(np.sum(r1 * r2, axis=1), -1, 1))


def epipolar_distances(F: np.ndarray, xy1: np.ndarray, xy2: np.ndarray) -> np.ndarray:
    """Symmetric point-to-epipolar-line distance in pixels, (N,)."""
    h1 = np.c_[xy1, np.ones(len(xy1))]
    h2 = np.c_[xy2, np.ones(len(xy2))]
    l2 = h1 @ F.T
    l1 = h2 @ F
    num = np.abs(np.sum(h2 * l2, axis=1))
    d2 = num / np.maximum(np.hypot(l2[:, 0], l2[:, 1]), 1e-12)
    d1 = num / np.maximum(np.hypot(l1[:, 0], l1[:, 1]), 1e-12)
    return 0.5 * (d1 + d2)


def inlier_evidence(pose: TwoView, tv: TwoView) -> tuple[float, int]:
    """Median distance (px) of ``tv``'s SIFT inliers from ``pose``'s epipolar lines, and their number
    (NaN, 0: none)."""
    if len(tv.kp1) == 0:
        return float("nan"), 0
    return float(np.median(epipolar_distances(pose.F, tv.kp1, tv.kp2))), len(tv.kp1)


def with_known_pose(K1, K2, R, t, xy1, xy2, max_error: float = 2.0) -> TwoView:
    """Geometry from given poses; SIFT matches are kept where they agree with it.

    The kept matches only serve to bound the depth range searched by the matcher.
    """
    # Poses read from text are rounded: project R back onto the rotations.
    U, _, Vt = np.linalg.svd(np.asarray(R, float))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    tv = TwoView(np.asarray(K1, float), np.asarray(K2, float), R, np.asarray(t, float).reshape(3),
                 source="given", num_sift_matches=len(xy1))
    if len(xy1):
        keep = epipolar_distances(tv.F, xy1, xy2) < max_error
        tv.kp1, tv.kp2 = xy1[keep], xy2[keep]
    return tv
