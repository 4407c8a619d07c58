"""The pair pipeline: two photos -> geometry -> SeFM matches -> points, mesh, model.

Stages run in order, each timed; :func:`reconstruct_pair` works on arrays and
returns a :class:`PairResult`, :func:`write_pair_outputs` writes it, and
:func:`run_pair` does both from file names (what ``sefm-recon pair`` calls).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import logging
import time
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from . import __version__, interrupt
from .config import Config
from .errors import InputError
from .geometry.two_view import estimate_two_view, sift_correspondences, with_known_pose
from .geometry.undistort import WorkingView, make_working_view
from .io.cameras import camera_to_string, infer_camera, parse_camera
from .io.images import check_texture, read_image, to_gray
from .matching.sefm import DenseMatches, match_pair

logger = logging.getLogger(__name__)


@dataclass
class PairResult:
    """Everything the pair pipeline found; coordinates in the original images."""

    uv1: np.ndarray  #: (N, 2) matches in image 1 (original pixels, COLMAP convention)
    uv2: np.ndarray  #: (N, 2)
    score: np.ndarray  #: (N,)
    xyz: np.ndarray  #: (N, 3) points in camera 1's frame (world = camera 1)
    rgb: np.ndarray  #: (N, 3) uint8 colours from image 1
    normals: np.ndarray | None  #: (N, 3)
    camera1: pycolmap.Camera
    camera2: pycolmap.Camera
    R: np.ndarray  #: cam2_from_cam1
    t: np.ndarray
    image_size: list  #: [[w1, h1], [w2, h2]] original sizes
    counts: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    notes: dict = field(default_factory=dict)
    mesh: tuple | None = None  #: (vertices, triangles, colours, normals)
    view1: WorkingView | None = None
    view2: WorkingView | None = None
    image1: np.ndarray | None = None  #: the original photos (references, for the match picture)
    image2: np.ndarray | None = None
    sift_uv1: np.ndarray | None = None  #: (M, 2) SIFT matches consistent with the geometry, image 1
    sift_uv2: np.ndarray | None = None


def resolve_cameras(path1, path2, img1, img2, camera: str | None, camera2: str | None):
    """Cameras from the command line, else EXIF, else COLMAP's default; checked against the images."""
    sizes = [(img1.shape[1], img1.shape[0]), (img2.shape[1], img2.shape[0])]
    texts = [camera, camera2 if camera2 is not None else camera]
    cams, sources = [], []
    for i, (text, path, (w, h)) in enumerate(zip(texts, (path1, path2), sizes), start=1):
        if text is not None:
            cam = parse_camera(text, camera_id=i)
            if (cam.width, cam.height) != (w, h):
                which = "--camera2" if i == 2 and camera2 is not None else "--camera"
                raise InputError(
                    f"{which} is for a {cam.width}x{cam.height} image but image {i} ({Path(path).name}) "
                    f"is {w}x{h}"
                )
            cams.append(cam)
            sources.append("given")
        else:
            cam, source = infer_camera(path, w, h, camera_id=i)
            cams.append(cam)
            sources.append(source)
    said = {"given": "given with --camera", "exif": "from the photo's EXIF data",
            "default": "to be estimated from the pair (no --camera, no EXIF; COLMAP's guess 1.2 x the longer side)"}
    for i, (cam, src) in enumerate(zip(cams, sources), start=1):
        logger.info("camera %d: focal length %.1f px %s; %s", i, cam.mean_focal_length(), said.get(src, src),
                    camera_to_string(cam))
    return cams[0], cams[1], sources


def reconstruct_pair(
    img1: np.ndarray,
    img2: np.ndarray,
    camera1: pycolmap.Camera,
    camera2: pycolmap.Camera,
    cfg: Config,
    pose: tuple[np.ndarray, np.ndarray] | None = None,
    progress: bool = False,
    names: tuple[str, str] = ("image 1", "image 2"),
) -> PairResult:
    """Run every stage on two decoded photos.

    Args:
        img1, img2: (H, W, 3) uint8 RGB, original resolution.
        camera1, camera2: their cameras (original resolution).
        pose: known ``(R, t)`` cam2_from_cam1; estimated from SIFT when None.
        names: how messages call the two images.
    Raises:
        InputError: a textureless image, too little overlap, no baseline, or no
            point that survives matching.
    """
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    v1 = make_working_view(img1, camera1, cfg.output.max_size)
    v2 = make_working_view(img2, camera2, cfg.output.max_size)
    timings["load"] = time.perf_counter() - t0
    if v1.scale < 1 or v2.scale < 1:
        logger.info("working at %dx%d and %dx%d", *v1.size, *v2.size)
    check_texture(v1.image, names[0])  # fail early and say why, not "too little overlap"
    check_texture(v2.image, names[1])

    t0 = time.perf_counter()
    tv, v1, v2, two_view_notes = two_view_stage(v1, v2, cfg, pose, names)
    camera1, camera2 = v1.camera, v2.camera
    timings["two_view"] = time.perf_counter() - t0

    dm = _match(v1, v2, tv, cfg, progress)
    timings.update(dm.timings)
    notes: dict = {}
    if pose is None and cfg.geometry.refine_pose:
        t0 = time.perf_counter()
        tv, dm, notes = _check_and_refine_pose(v1, v2, tv, dm, cfg, progress)
        timings["pose_refine"] = time.perf_counter() - t0
        if "focal" in two_view_notes:
            _check_unknown_camera(notes["pose_check"], two_view_notes["focal"])

    t0 = time.perf_counter()
    from .reconstruct.points import clean_points, estimate_normals, grid_normals, sample_colors

    rgb = sample_colors(v1.image, dm.uv1) if len(dm.uv1) else np.zeros((0, 3), np.uint8)
    xyz, uv1w, uv2w, score = dm.xyz, dm.uv1, dm.uv2, dm.score
    if cfg.output.clean_outliers and len(dm.xyz) > 32:
        keep = clean_points(dm.xyz)
        xyz, uv1w, uv2w, score, rgb = xyz[keep], uv1w[keep], uv2w[keep], score[keep], rgb[keep]
    centres = np.stack([np.zeros(3), -tv.R.T @ tv.t])
    if len(xyz) == 0:
        raise InputError(
            f"no 3D point could be reconstructed: {dm.counts.get('dense_matches', 0)} dense matches, none valid "
            "(too little texture along the epipolar lines, or too little overlap)"
        )
    if len(xyz) < 3:
        normals = None
    elif cfg.output.normals == "grid":
        normals = grid_normals(uv1w, xyz, v1.image.shape[:2])
    else:
        normals = estimate_normals(xyz, centres)
    timings["points"] = time.perf_counter() - t0

    counts = {
        "sift_matches": int(tv.num_sift_matches),
        "sift_inliers": int(len(tv.kp1)),
        **dm.counts,
        "points": int(len(xyz)),
    }
    result = PairResult(
        uv1=v1.to_original(uv1w), uv2=v2.to_original(uv2w), score=score, xyz=xyz, rgb=rgb, normals=normals,
        camera1=camera1, camera2=camera2, R=tv.R, t=tv.t,
        image_size=[[img1.shape[1], img1.shape[0]], [img2.shape[1], img2.shape[0]]],
        counts=counts, timings=timings, view1=v1, view2=v2,
        notes={"pose": tv.source, **notes, **two_view_notes},
        sift_uv1=v1.to_original(tv.kp1), sift_uv2=v2.to_original(tv.kp2), image1=img1, image2=img2,
    )
    if cfg.output.mesh != "none":
        t0 = time.perf_counter()
        result.mesh = _mesh(result, cfg, uv1w, v1.image.shape[:2], float(tv.K1[0, 0]))
        timings["mesh"] = time.perf_counter() - t0
    return result


def two_view_stage(v1: WorkingView, v2: WorkingView, cfg: Config, pose: tuple[np.ndarray, np.ndarray] | None = None,
                   names: tuple[str, str] = ("image 1", "image 2")):
    """SIFT, and the pose (estimated and checked, or the given one kept).

    Without a prior focal length (no ``--camera``, no EXIF) the focal length is
    estimated from the pair where it can be (:func:`_estimate_focal`). An estimated
    pose must explain the independently found fundamental matrix (:func:`_check_geometry`)
    and, found from few inliers, survive a resampling of its matches (:func:`_check_consensus`).
    Photos longer than ``sift.quick_max_size`` with known cameras are tried first with SIFT
    on copies that long, and only where that fails (any refusal) with the full front end.
    Returns ``(TwoView, view1, view2, notes)``; the views carry the cameras used.
    """
    sc = cfg.sift
    known = v1.camera.has_prior_focal_length and v2.camera.has_prior_focal_length
    # (an unknown focal length is estimated from the SIFT matches: they need the full front end's accuracy)
    if sc.quick_max_size and (known or pose is not None) and max(*v1.size, *v2.size) > sc.quick_max_size:
        quick = min(sc.quick_max_size, sc.max_image_size or sc.quick_max_size)
        try:
            tv, v1q, v2q, notes = _two_view(v1, v2, cfg, pose, names, quick, 0)
            return tv, v1q, v2q, {**notes, "sift_max_size": quick}
        except InputError as err:
            logger.info("SIFT at %d px: %s; running it at %s", quick, err,
                        f"{sc.max_image_size} px" if sc.max_image_size else "full size")
    tv, v1, v2, notes = _two_view(v1, v2, cfg, pose, names, sc.max_image_size, sc.upsample_max_size)
    return tv, v1, v2, {**notes, "sift_max_size": sc.max_image_size}


def _two_view(v1: WorkingView, v2: WorkingView, cfg: Config, pose, names, max_size: int, upsample_max_size: int):
    """:func:`two_view_stage` with SIFT on copies at most ``max_size`` long, upsampled
    (octave -1) where at most ``upsample_max_size``."""
    from .geometry.focal import fundamental_matrix

    g = cfg.geometry
    xy1, xy2 = sift_correspondences(to_gray(v1.image), to_gray(v2.image), cfg.sift.max_features, cfg.sift.max_ratio,
                                    min_features=g.min_inliers if pose is None else 0,
                                    names=names, max_size=max_size, upsample_max_size=upsample_max_size)
    if pose is not None:
        return with_known_pose(v1.K, v2.K, pose[0], pose[1], xy1, xy2, g.ransac_max_error), v1, v2, {}
    notes = {}
    known = v1.camera.has_prior_focal_length and v2.camera.has_prior_focal_length
    # The fundamental matrix (for the check, and for the focal length where it is unknown)
    # by its own RANSAC, beside the essential matrix's where the cameras are known: pycolmap
    # lets go of Python's lock (the bench pair: 0.5 -> 0.4 s for the two).
    with ThreadPoolExecutor(max_workers=1) as pool:
        fit_job = pool.submit(fundamental_matrix, xy1, xy2, g.ransac_max_error) if len(xy1) >= g.min_inliers else None
        if not known:
            fit = fit_job.result() if fit_job else None
            v1, v2, notes["focal"] = _estimate_focal(v1, v2, fit, cfg)
        tv = estimate_two_view(xy1, xy2, v1.K, v2.K, v1.size, v2.size, g.min_inliers, g.ransac_max_error,
                               g.min_tri_angle_deg, focal_known=known)
        fit = fit_job.result() if fit_job else None
    check = _check_geometry(tv, xy1, xy2, fit, g.ransac_max_error, known)
    consensus = _check_consensus(tv, xy1, xy2, v1.size, v2.size, g.ransac_max_error, known)
    if consensus is not None:
        check["resampled_consensus"] = round(consensus, 4)
    if check:
        notes["geometry_check"] = check
    return tv, v1, v2, notes


def _estimate_focal(v1: WorkingView, v2: WorkingView, fit: tuple | None, cfg: Config):
    """The focal length of each camera without a prior, from the pair's fundamental matrix.

    ``fit`` is ``(F, inlier mask)`` of the SIFT matches (:func:`~.geometry.focal.fundamental_matrix`).
    Returns the two views (with new cameras where the focal length was estimated)
    and a note for the report. Where the pair does not determine it, the guess stays.
    """
    from .geometry.focal import estimate_focal
    from .geometry.undistort import pinhole_matrix

    note = {"fundamental_inliers": 0 if fit is None else int(fit[1].sum()), "source": "default"}
    if note["fundamental_inliers"] < cfg.geometry.min_inliers:
        return v1, v2, note  # too few matches: estimate_two_view says so
    est = estimate_focal(fit[0], v1.size, v2.size,
                         K1=v1.K if v1.camera.has_prior_focal_length else None,
                         K2=v2.K if v2.camera.has_prior_focal_length else None)
    note.update(factor=round(est.factor, 4), cost=float(f"{est.cost:.3g}"), cost_rise=float(f"{est.rise:.3g}"),
                determined=est.determined)
    if not est.determined:
        logger.warning(
            "the focal length cannot be estimated from this pair (its optical axes are parallel, or both cameras "
            "turned towards one point alike), so the "
            "guess of %.2f x the longer side stays: the matches do not depend on it, the depths' scale does; give "
            "--camera when the camera is known", v1.K[0, 0] / max(v1.size))
        return v1, v2, note
    views = []
    for v in (v1, v2):
        if v.camera.has_prior_focal_length:
            views.append(v)
            continue
        cam = copy.copy(v.camera)
        w, h = cam.width, cam.height
        cam.focal_length = est.factor * max(w, h)  # one focal length: COLMAP's SIMPLE_RADIAL guess
        views.append(WorkingView(v.image, pinhole_matrix(cam, v.scale), cam, v.scale))
    note["source"] = "estimated"
    logger.info("focal length estimated from the pair: %.1f px (%.2f x the longer side; %d matches fit its "
                "fundamental matrix)", views[0].camera.mean_focal_length(), est.factor, note["fundamental_inliers"])
    return views[0], views[1], note


#: A pose is accepted when it explains at least this share of the inliers of the
#: fundamental matrix found independently (RANSAC on the same SIFT matches, without
#: the cameras) within the RANSAC threshold. A right pose explains them all but a
#: few borderline ones (an essential matrix has two degrees of freedom fewer; 0.86-1.0
#: on the real pairs even with a guessed camera); where the two models pick different
#: matches (3 % on a ScanNet pair whose pose was 84 deg off), neither is to be trusted.
MIN_EXPLAINED_SHARE = 0.8


def _check_geometry(tv, xy1: np.ndarray, xy2: np.ndarray, fit: tuple | None, max_error: float,
                    camera_known: bool) -> dict:
    """Refuse a pose that does not explain the matches of the independently found fundamental matrix."""
    from .geometry.two_view import epipolar_distances

    if fit is None or not fit[1].any():
        return {}
    inl = fit[1]
    share = float(np.mean(epipolar_distances(tv.F, xy1[inl], xy2[inl]) < max_error))
    note = {"fundamental_inliers": int(inl.sum()), "pose_inliers": int(len(tv.kp1)), "explained_share": round(share, 4)}
    logger.debug("geometry check: the pose explains %.0f %% of the %d inliers of the fundamental matrix",
                 100 * share, inl.sum())
    if share >= MIN_EXPLAINED_SHARE:
        return note
    seen = (f"the relative pose ({len(tv.kp1)} SIFT inliers) explains only {100 * share:.0f} % of the {int(inl.sum())} "
            f"matches that fit the pair's fundamental matrix (at least {100 * MIN_EXPLAINED_SHARE:.0f} % are needed)")
    if camera_known:
        raise InputError(f"the geometry of the pair is ambiguous: {seen}; two different geometries fit the matches, so "
                         "the pose cannot be trusted (too few distinctive matches: try photos closer together)")
    raise InputError(f"the focal length could not be found: with {tv.K1[0, 0]:.0f} px {seen}; give the camera "
                     "with --camera \"PINHOLE W H fx fy cx cy\"")


#: The consensus test runs where the pose has fewer SIFT inliers than this. The wrong poses
#: seen had 30-92 inliers (scene0758 of ScanNet: 33-37, at 1.6-14 deg off depending on
#: FLANN's random trees alone; public tourist pairs: 30-92); a consensus of hundreds of
#: matches is not found by chance. The test's eight RANSACs take 0.1-0.15 s below this
#: and would take 0.8 s over the bench pair's thousands.
CONSENSUS_BELOW_INLIERS = 300
#: ... and refuses it where the poses found again explain a median share of its inliers
#: below this. A pose the matches determine keeps 0.97-1.0 with the true camera (the 60
#: real cases) and 0.95-1.0 on the pairs kept without one; scene0758's eleven draws of
#: FLANN's trees gave 0.38-0.84 (0.83 and 0.84 for poses 12 and 4 deg off, which the
#: check against the fundamental matrix let through). Stricter than that check's
#: :data:`MIN_EXPLAINED_SHARE`: the same pose found again, not a second model, is compared.
CONSENSUS_MIN_SHARE = 0.9


def _check_consensus(tv, xy1: np.ndarray, xy2: np.ndarray, size1: tuple[int, int], size2: tuple[int, int],
                     max_error: float, camera_known: bool) -> float | None:
    """Refuse a pose from few inliers whose consensus does not survive resampling the matches
    (:func:`~.geometry.two_view.resampled_consensus`); returns its figure (None: not run)."""
    from .geometry.two_view import RESAMPLE_ROUNDS, RESAMPLE_SHARE, resampled_consensus

    if len(tv.kp1) >= CONSENSUS_BELOW_INLIERS:
        return None
    kept = resampled_consensus(xy1, xy2, tv, size1, size2, max_error)
    logger.debug("consensus test: %.0f %% of the pose's inliers kept by the poses of resampled matches", 100 * kept)
    if kept >= CONSENSUS_MIN_SHARE:
        return kept
    seen = (f"the relative pose ({len(tv.kp1)} SIFT inliers of {len(xy1)} matches) is not determined by the matches: "
            f"the poses found again from {RESAMPLE_ROUNDS} random subsets of {100 * RESAMPLE_SHARE:.0f} % of them "
            f"explain a median {100 * kept:.0f} % of its inliers (at least {100 * CONSENSUS_MIN_SHARE:.0f} % are needed)")
    if camera_known:
        raise InputError(f"the geometry of the pair is ambiguous: {seen}; its consensus is a chance one, so the pose "
                         "cannot be trusted (too few distinctive matches: try photos closer together)")
    raise InputError(f"the focal length could not be found: with {tv.K1[0, 0]:.0f} px {seen}; give the camera "
                     "with --camera \"PINHOLE W H fx fy cx cy\"")


def _match(v1: WorkingView, v2: WorkingView, tv, cfg: Config, progress: bool) -> DenseMatches:
    if cfg.dense.method == "sgm":
        from .matching.sgm import match_pair_sgm

        return match_pair_sgm(v1.image, v2.image, tv, cfg, progress=progress)
    return match_pair(v1.image, v2.image, tv, cfg, progress=progress)


#: The refined pose is used (and the pair matched again) where it brings the free dense
#: tracks closer to its lines than the pose they were matched with (medians), and the SIFT
#: inliers, evidence the tracks do not share, do not speak against it: their median
#: distance from the refined pose's lines at most this many standard errors of a median
#: (1.17/sqrt(n) of it, half-normal distances) above the old pose's, which was fitted to
#: them. Where the tracks are biased (a scale change the tracker does not model:
#: generated forward pairs whose refined pose was 2-3 deg off), the SIFT inliers lie
#: 23-40 % farther from the refined pose's lines, 13-15 standard errors; where the SIFT
#: pose is off (real pairs, 0.2-3 deg), the refined pose's lines are as close or closer
#: to them (-34 % to +6.5 %, at most 1.4 standard errors). The tracks' distance from a
#: pose's lines is no measure by itself: with a right pose it is 0.04-0.07 px on the
#: published real pairs, 0.09-0.27 px where an image was warped (the conv and unrect
#: variants) and 0.05-0.6 px on the generated scenes.
SIFT_AGREE_SE = 2.0
#: Standard error of the median of n half-normal distances, times sqrt(n) over the median.
MEDIAN_SE = 1.17
#: ... and where it brings the tracks nearer its lines by more than this many standard
#: errors of their median (MEDIAN_SE): a pose fitted to the tracks lies a little nearer
#: them whatever, by their noise alone where the pose it refines is right; one standard
#: error is that noise. The generated pairs, whose SIFT poses are right to hundredths of
#: a degree: 0.1-1.07; the 17 of 60 real pairs matched again: 1.07-12. Lines moved by
#: hundredths of a pixel still change the matches: the 20 real pairs whose refined pose
#: moved them 0.01-0.09 px (90th percentile) scored, matched again, nearer their
#: true-pose figures (Midd1 rect coverage 0.664 -> 0.680, true 0.693); on generated
#: lateral pair 0 a refinement within the noise (0.25) lost 0.03 of precision at 1 px.
TRACKS_GAIN_SE = 1.0
#: Dense matches sampled for the lines' move (90th percentile, reported): its error at
#: 100,000 is a small fraction of a percent.
SHIFT_SAMPLE = 100_000
#: The tracks refine the pose only where at least this share of the tried matches
#: tracked (forward and backward within 0.5 px): the generated zoom pairs, whose scale
#: change the tracker does not model, keep 18-26 % (one pose refined from 19 % lost 0.5
#: of precision at 1 px); the other generated pairs 30-71 %, the real pairs 42-97 %.
#: The bound lies midway between the zoom pairs and the rest.
MIN_TRACKED_SHARE = 0.28
#: The tracks do not tell a wrong pose from a right one where the 2-D tracker fails:
#: a grossly wrong pose of a generated pair (70 deg of translation direction) left them
#: a median 2.3 px off its lines, the right pose of a generated zoom pair 2.6 px (the
#: tracker does not model the scale change), with 18-21 % of the matches tracking in
#: both. So they refine the pose, and no pose is refused on their evidence.


def _refined_pose_holds(tv, new, dm: DenseMatches, before: float, after: float, notes: dict) -> bool:
    """The tracks favour the refined pose by more than their noise (TRACKS_GAIN_SE), and the
    SIFT inliers do not speak against it (SIFT_AGREE_SE)."""
    from .geometry.two_view import epipolar_distances, inlier_evidence

    if not after < before or len(dm.uv1) == 0:
        return False
    gain = (before - after) / (MEDIAN_SE * before / np.sqrt(notes["pose_check"]["tracks"]))
    sift_before, n = inlier_evidence(tv, tv)
    sift_after, _ = inlier_evidence(new, tv)
    step = max(len(dm.uv1) // SHIFT_SAMPLE, 1)  # an even sample is enough for a percentile
    shift = float(np.percentile(epipolar_distances(new.F, dm.uv1[::step], dm.uv2[::step]), 90))
    notes["pose_check"].update(tracks_gain_se=round(float(gain), 2),
                               sift_inliers_epipolar_px=[round(sift_before, 3), round(sift_after, 3)],
                               refined_line_shift_px=round(shift, 3))
    if n == 0 or gain <= TRACKS_GAIN_SE:
        return False
    return bool(sift_after <= sift_before * (1 + SIFT_AGREE_SE * MEDIAN_SE / np.sqrt(n)))


def _check_and_refine_pose(v1: WorkingView, v2: WorkingView, tv, dm: DenseMatches, cfg: Config, progress: bool):
    """Judge the SIFT pose by free 2-D tracks of the dense matches, refine it from them, and
    match again where the refined pose holds (:func:`_refined_pose_holds`)."""
    from .geometry.refine import pose_change_deg, pose_evidence, refine_pose, track_dense

    g1, g2 = to_gray(v1.image), to_gray(v2.image)
    tracks = track_dense(g1, g2, dm.uv1, dm.uv2, dm.score)
    before = pose_evidence(tv, tracks)
    new = refine_pose(tv, tracks, v1.size, v2.size)
    after = pose_evidence(new, tracks) if new is not None else float("nan")
    notes = {"pose_check": {"tracks": len(tracks.uv1), "tracked_of": tracks.tried,
                            "sift_pose_epipolar_px": round(before, 3),
                            "refined_pose_epipolar_px": None if np.isnan(after) else round(after, 3)}}
    logger.debug("pose check: %d of %d dense matches tracked in 2-D; median %.2f px from the SIFT pose's lines, "
                 "%.2f px from the refined pose's", len(tracks.uv1), tracks.tried, before, after)
    final = before
    # Where most matches do not track, the 2-D tracker failed (a scale change, blur) and the few
    # tracks left do not refine a pose (see MIN_TRACKED_SHARE).
    trusted = len(tracks.uv1) >= MIN_TRACKED_SHARE * max(tracks.tried, 1)
    if new is not None and trusted and _refined_pose_holds(tv, new, dm, before, after, notes):
        rot, tr = pose_change_deg(tv, new)
        logger.info("pose refined with the dense matches (%.2f deg rotation, %.2f deg translation direction): "
                    "matching again", rot, tr)
        notes["pose_check"]["refined_change_deg"] = [round(rot, 3), round(tr, 3)]
        tv, final = new, after
        if dm.counts.get("jump_penalty") and not cfg.sgm.jump_penalty:
            # the scene's smoothness, chosen with the first pose, holds for the refined one
            cfg = dataclasses.replace(cfg, sgm=dataclasses.replace(cfg.sgm, jump_penalty=dm.counts["jump_penalty"]))
        dm = _match(v1, v2, tv, cfg, progress)
    # the pose kept's distance from the tracks, median and 75th percentile (None: too few tracks to judge it)
    notes["pose_check"]["final_pose_epipolar_px"] = None if np.isnan(final) else round(final, 3)
    quarter = pose_evidence(tv, tracks, 75.0)
    notes["pose_check"]["final_pose_epipolar_p75_px"] = None if np.isnan(quarter) else round(quarter, 3)
    return tv, dm, notes


#: Without a known camera, a pose is refused when the free dense tracks lie a median
#: more than this (px) from its epipolar lines: matches are judged at 1 px, and lines
#: half a pixel off put a large share of them past it (the real pairs whose images were
#: turned, so their principal points are far off the centre a guess assumes, lost
#: 0.2-0.5 of their precision at 1 px beyond this), while a right camera leaves the
#: tracks' own noise (0.1-0.3 px on fountain-P11 with the focal length estimated). It is
#: refused too where a quarter of them lie more than twice this from its lines: tracks
#: that are noise about the lines (half-normal, whose 75th percentile is 1.7 times its
#: median) with a median within the bar leave three quarters within twice it, while a
#: wrong camera that fits one part of the image leaves a quarter far off (Baby2 conv with
#: the guessed camera: a median 0.46 px, a quarter over 2.1 px, its dense matches a median
#: 1.2 px from the true epipolar lines; the turned pairs kept: 0.43-0.92 px; Wood2 unrect,
#: 1.18 px, its matches 0.49 px from the true lines, is refused with it).
MAX_UNKNOWN_CAMERA_TRACK_PX = 0.5


def _check_unknown_camera(check: dict, focal: dict) -> None:
    """Refuse the pose of a guessed or estimated camera that the dense tracks do not bear out."""
    px = check.get("final_pose_epipolar_px")
    if px is None:
        return
    quarter = check.get("final_pose_epipolar_p75_px") or px  # (both come from the same tracks)
    focal["track_epipolar_px"], focal["track_epipolar_p75_px"] = px, quarter
    if px > MAX_UNKNOWN_CAMERA_TRACK_PX or quarter > 2 * MAX_UNKNOWN_CAMERA_TRACK_PX:
        what = "estimated from the pair" if focal.get("source") == "estimated" else "guessed"
        raise InputError(
            f"the camera is unknown and the pose made with the focal length {what} leaves the dense matches, "
            f"tracked freely, a median {px:.2f} px from its epipolar lines and a quarter of them over {quarter:.2f} "
            f"px (at most {MAX_UNKNOWN_CAMERA_TRACK_PX:g} and {2 * MAX_UNKNOWN_CAMERA_TRACK_PX:g} px are needed): "
            "the geometry is not reliable without the camera; give it with --camera \"PINHOLE W H fx fy cx cy\"")


def _mesh(result: PairResult, cfg: Config, uv1: np.ndarray, shape: tuple[int, int], focal: float):
    """The mesh of ``cfg.output.mesh`` (grid or poisson) from the result's points; None when there are
    too few. ``uv1`` are the points' positions in camera 1's working image of ``shape`` and focal length."""
    from .reconstruct.mesh import grid_mesh, poisson_mesh

    if result.normals is None or len(result.xyz) < 100:
        logger.warning("too few points (%d) for a mesh: mesh.ply not written", len(result.xyz))
        return None
    if cfg.output.mesh == "grid":
        try:
            return grid_mesh(uv1, result.xyz, result.rgb, shape, focal, max_vertices=cfg.output.mesh_max_points)
        except ValueError as e:
            logger.warning("no mesh: %s; mesh.ply not written", e)
            return None
    # open3d holds the interpreter for the whole Poisson solve: a Ctrl-C takes effect when it ends.
    logger.info("meshing %d points (Ctrl-C stops the run once the mesh is done)", len(result.xyz))
    return poisson_mesh(result.xyz, result.normals, result.rgb, depth=cfg.output.poisson_depth,
                        density_quantile=cfg.output.density_quantile, max_points=cfg.output.mesh_max_points)


def build_report(result: PairResult, cfg: Config, names: tuple[str, str]) -> dict:
    """The ``report.json`` contents.

    Its keys are part of the contract with users: the README's "Command line" and
    "Output files" sections; a change here changes them too.
    """
    from .io.cameras import camera_to_string as cts
    from .versions import library_versions

    return {
        "version": __version__,
        "libraries": library_versions(),
        "images": list(names),
        "image_size": result.image_size,
        "cameras": [cts(result.camera1), cts(result.camera2)],
        "pose": {"R": result.R.tolist(), "t": result.t.tolist(), "source": result.notes.get("pose")},
        "config": cfg.to_dict(),
        "timings_s": {k: round(v, 4) for k, v in result.timings.items()},
        "counts": result.counts,
    }


def pair_output_bytes(result: PairResult, cfg: Config) -> int:
    """About how many bytes :func:`write_pair_outputs` writes (checked against the free space first)."""
    n = len(result.xyz)
    m = n if cfg.output.sparse_max_points is None else min(n, cfg.output.sparse_max_points)
    total = 20 * n  # matches.npz: 5 float32 a match
    total += n * (12 + (12 if result.normals is not None else 0) + 3)  # points.ply
    total += 2 * 24 * m + 67 * m  # sparse/: a 2-D point in each image, a 3-D point with its track
    if result.mesh is not None:
        v, f, c, nv = result.mesh
        total += len(v) * (24 + (24 if nv is not None else 0) + (3 if c is not None else 0)) + 13 * len(f)
    if result.image1 is not None and result.image2 is not None:  # matches.png, at most 2000 px wide
        (w1, h1), (w2, h2) = result.image_size
        s = min(1.0, 2000 / (w1 + w2))
        total += int(3 * s * (w1 + w2) * s * max(h1, h2))
    return total + (64 << 10)  # report.json


def _wait_through_interrupts(jobs: list) -> None:
    """Wait until every job (a future) is done, through a Ctrl-C (its handler has recorded it:
    it is raised again after). The staging folder is removed once the writing stops, and a
    writer still at work would create it again: a Ctrl-C while the jobs were started or
    awaited left matches.png and mesh.ply in a folder beside OUT. (The futures, not the
    threads: Python 3.11 marks a thread as ended when a Ctrl-C interrupts joining it, so a
    second join returns while it runs on.)"""
    while True:
        try:
            wait(jobs)
            return
        except KeyboardInterrupt:
            continue


def _write_model(result: PairResult, folder: Path, names: tuple[str, str], max_points: int | None) -> bool:
    """The pair's COLMAP model (``folder``/sparse), for a child process (True: written)."""
    from .io.colmap_model import write_two_view_model

    write_two_view_model(folder / "sparse", result.camera1, result.camera2, names[0], names[1], result.R, result.t,
                         result.uv1, result.uv2, result.xyz, result.rgb, max_points=max_points)
    return True


def write_pair_outputs(result: PairResult, cfg: Config, folder: Path, names: tuple[str, str]) -> dict:
    """Write every output file of a pair into ``folder`` (a staging folder)."""
    from .forked import Forked
    from .io.matches import write_matches
    from .io.ply import write_mesh, write_point_cloud
    from .io.visualize import draw_matches, write_image

    def small_files():
        write_matches(folder / "matches.npz", uv1=result.uv1, uv2=result.uv2, score=result.score)
        if result.mesh is not None:
            write_mesh(folder / "mesh.ply", *result.mesh)
        if result.image1 is not None and result.image2 is not None:
            write_image(folder / "matches.png", draw_matches(result.image1, result.image2, result.uv1, result.uv2))

    t0 = time.perf_counter()
    folder = Path(folder)
    # The COLMAP model's points are added one by one in Python (0.26 s on the bench pair,
    # holding Python's lock): a child process forked before the threads start builds and
    # writes it, while numpy's file writes and OpenCV, which let go of the lock, write the
    # other files side by side here (the write stage 0.54 -> 0.38 s on the bench pair; they
    # write through small reused buffers, so this process copies few of the pages it now
    # shares with the child)
    pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="write")
    jobs: list = []
    try:
        with Forked(_write_model, result, folder, names, cfg.output.sparse_max_points) as model:
            with interrupt.held():  # every job started is one awaited below
                jobs = [pool.submit(write_point_cloud, folder / "points.ply", result.xyz, result.rgb, result.normals),
                        pool.submit(small_files)]
            for job in jobs:
                job.result()
            model.result()
    finally:
        _wait_through_interrupts(jobs)
        pool.shutdown(wait=False)
    result.timings["write"] = time.perf_counter() - t0
    report = build_report(result, cfg, names)
    (folder / "report.json").write_text(json.dumps(report, indent=2))
    return report


def run_pair(
    image1: str | Path,
    image2: str | Path,
    out: str | Path,
    cfg: Config,
    camera: str | None = None,
    camera2: str | None = None,
    overwrite: bool = False,
    progress: bool = False,
    pose: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict:
    """``sefm-recon pair``: read, reconstruct, write into ``out`` atomically; returns the report."""
    from .io.output import PAIR_OWNED, PAIR_RESULTS, StagedOutput, check_output_dir

    check_output_dir(out, overwrite)  # fail before the long work, not after
    t0 = time.perf_counter()
    img1 = read_image(image1)
    img2 = read_image(image2)
    names = (f"image 1 ({Path(image1).name})", f"image 2 ({Path(image2).name})")
    if pose is None and img1.shape == img2.shape and np.array_equal(img1, img2):
        raise InputError(
            f"{names[0]} and {names[1]} are the same photo: no baseline, so no depth can be recovered "
            "(take the second photo from a different position)"
        )
    cam1, cam2, sources = resolve_cameras(image1, image2, img1, img2, camera, camera2)
    result = reconstruct_pair(img1, img2, cam1, cam2, cfg, pose=pose, progress=progress, names=names)
    staged = StagedOutput(out, overwrite, results=PAIR_RESULTS, owned=PAIR_OWNED)
    with staged as stage:
        staged.require(pair_output_bytes(result, cfg))
        report = write_pair_outputs(result, cfg, stage, (Path(image1).name, Path(image2).name))
        focal = result.notes.get("focal", {})
        if focal.get("source") == "estimated":
            sources = ["estimated" if s == "default" else s for s in sources]
        report["camera_sources"] = sources
        report["focal_length"] = [{"px": round(float(c.mean_focal_length()), 3), "source": src}
                                  for c, src in zip((result.camera1, result.camera2), sources)]
        if focal:
            report["focal_estimation"] = focal
        report["timings_s"]["total"] = round(time.perf_counter() - t0, 4)
        (stage / "report.json").write_text(json.dumps(report, indent=2))
    return report
