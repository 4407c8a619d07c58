"""Write / read a two-view COLMAP model with pycolmap (>= 3.12 / 4.x API).

The model written by :func:`write_two_view_model` contains

* cameras 1 and 2 (copies of the given ``pycolmap.Camera`` objects, ids set),
  each with a trivial rig (rig_id = camera_id);
* image 1 (``name1``, camera 1) at the identity pose and image 2 (``name2``,
  camera 2) at ``cam_from_world = (R, t)``, each in a trivial frame
  (frame_id = image_id);
* one 3-D point per (sub-sampled) match, whose track is
  ``[(image 1, k), (image 2, k)]``: the k-th 2-D point of each image is that
  match's ``uv1[k]`` / ``uv2[k]`` (COLMAP pixel convention, the same as ours).

pycolmap 4.x writes ``rigs.bin`` and ``frames.bin`` next to the classic
``cameras.bin images.bin points3D.bin``; older COLMAP readers ignore them.

The model is written into a hidden temporary folder next to ``out_dir`` and
renamed into place. If ``out_dir`` already exists and holds only COLMAP model
files it is replaced (moved aside, the new folder renamed in, the old one
deleted: a concurrent reader sees the old or the new model, never a mix, but
there is a moment where ``out_dir`` does not exist). If it holds anything else,
``FileExistsError`` is raised rather than deleting unknown files.
"""

from __future__ import annotations

import logging
import os
import secrets
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..arrays import finite_rows
from .space import check_written

if TYPE_CHECKING:  # pycolmap is imported lazily (keeps `sefm-recon --help` fast)
    import pycolmap

log = logging.getLogger(__name__)

__all__ = ["MODEL_FILES", "check_model_written", "read_model", "write_poses_model", "write_two_view_model"]

#: Files a COLMAP sparse model folder may contain (binary or text).
MODEL_FILES = frozenset(
    f"{stem}.{ext}"
    for stem in ("cameras", "images", "points3D", "rigs", "frames", "project")
    for ext in ("bin", "txt", "ini")
)


def _copy_camera(camera: pycolmap.Camera, camera_id: int) -> pycolmap.Camera:
    import pycolmap

    cam = pycolmap.Camera(camera.todict())
    cam.camera_id = camera_id
    if not cam.is_undistorted():
        log.warning(
            "camera %d (%s) has distortion parameters; the uv written to the model "
            "are assumed to be in its (distorted) image", camera_id, cam.model_name,
        )
    return cam


def _colmap_name(name: str) -> str | bytes:
    """An image name for pycolmap: one that is not UTF-8 (a surrogate-escaped byte of a file name) as its bytes."""
    try:
        name.encode("utf-8")
        return name
    except UnicodeEncodeError:
        return os.fsencode(name)


def _check_rotation(R: np.ndarray) -> np.ndarray:
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"R must be (3, 3), got {R.shape}")
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError("R is not a rotation matrix")
    return R


def _build_reconstruction(
    camera1: pycolmap.Camera,
    camera2: pycolmap.Camera,
    name1: str,
    name2: str,
    R: np.ndarray,
    t: np.ndarray,
    uv1: np.ndarray,
    uv2: np.ndarray,
    xyz: np.ndarray,
    rgb: np.ndarray,
) -> pycolmap.Reconstruction:
    import pycolmap

    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(_copy_camera(camera1, 1))
    rec.add_camera_with_trivial_rig(_copy_camera(camera2, 2))
    im1 = pycolmap.Image(name=_colmap_name(str(name1)), keypoints=uv1, camera_id=1, image_id=1)
    im2 = pycolmap.Image(name=_colmap_name(str(name2)), keypoints=uv2, camera_id=2, image_id=2)
    rec.add_image_with_trivial_frame(im1, pycolmap.Rigid3d())
    rec.add_image_with_trivial_frame(im2, pycolmap.Rigid3d(np.hstack([R, t[:, None]])))
    # one pycolmap call a point (it has no bulk call): the loop holds Python's lock, its
    # names bound once (100,000 points: 0.24 -> 0.19 s)
    new_track, add_point = pycolmap.Track, rec.add_point3D
    for k, (x, c) in enumerate(zip(xyz, rgb)):
        track = new_track()
        track.add_element(1, k)
        track.add_element(2, k)
        add_point(x, track, c)
    rec.update_point_3d_errors()  # store per-point reprojection errors
    return rec


def write_two_view_model(
    out_dir: str | os.PathLike,
    camera1: pycolmap.Camera,
    camera2: pycolmap.Camera,
    name1: str,
    name2: str,
    R: np.ndarray,
    t: np.ndarray,
    uv1: np.ndarray,
    uv2: np.ndarray,
    xyz: np.ndarray,
    rgb: np.ndarray,
    max_points: int | None = 100_000,
    seed: int = 0,
) -> pycolmap.Reconstruction:
    """Write a binary two-view COLMAP model into ``out_dir`` (atomically).

    Args:
        out_dir: model folder (``.../sparse/0``); parents are created.
        camera1, camera2: intrinsics of image 1 / 2 (any COLMAP model; they are
            copied and given camera ids 1 and 2, even if identical).
        name1, name2: image names as COLMAP should see them (paths relative to
            the image folder).
        R (3, 3), t (3,): cam_from_world of image 2 (``x_cam2 = R @ X + t``);
            image 1 is at the identity.
        uv1, uv2: (N, 2) matched COLMAP pixel coordinates in image 1 / 2.
        xyz: (N, 3) triangulated points (world = camera-1 frame).
        rgb: (N, 3) uint8 point colours.
        max_points: keep a uniform random subset of at most this many points
            (None = all). Rows with non-finite values are dropped first.
        seed: RNG seed for the subset.

    Returns:
        The in-memory ``pycolmap.Reconstruction`` that was written (its points
        have their reprojection errors computed, so
        ``compute_mean_reprojection_error()`` is meaningful).
    """
    out_dir = Path(out_dir)
    R = _check_rotation(R)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if t.shape != (3,):
        raise ValueError(f"t must be (3,), got {t.shape}")
    uv1 = np.asarray(uv1, dtype=np.float64)
    uv2 = np.asarray(uv2, dtype=np.float64)
    xyz = np.asarray(xyz, dtype=np.float64)
    rgb = np.asarray(rgb)
    n = len(xyz)
    for name, a, w in (("uv1", uv1, 2), ("uv2", uv2, 2), ("xyz", xyz, 3), ("rgb", rgb, 3)):
        if a.shape != (n, w):
            raise ValueError(f"{name} must be ({n}, {w}), got {a.shape}")
    if rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be uint8, got {rgb.dtype}")

    keep = np.flatnonzero(finite_rows(uv1, uv2, xyz))
    if len(keep) < n:
        log.warning("dropping %d matches with non-finite values", n - len(keep))
    if max_points is not None and len(keep) > max_points:
        rng = np.random.default_rng(seed)
        keep = np.sort(rng.choice(keep, size=int(max_points), replace=False))
    uv1, uv2, xyz, rgb = (a.take(keep, axis=0) for a in (uv1, uv2, xyz, rgb))

    rec = _build_reconstruction(camera1, camera2, name1, name2, R, t, uv1, uv2, xyz, rgb)

    if out_dir.exists():
        if not out_dir.is_dir():
            raise FileExistsError(f"{out_dir} exists and is not a folder")
        extra = [p.name for p in out_dir.iterdir() if p.name not in MODEL_FILES]
        if extra:
            raise FileExistsError(
                f"{out_dir} holds files that are not part of a COLMAP model: {extra[:5]}"
            )
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    token = secrets.token_hex(4)
    tmp = out_dir.with_name(f".{out_dir.name}.tmp-{token}")
    old = out_dir.with_name(f".{out_dir.name}.old-{token}")
    tmp.mkdir()
    try:
        rec.write_binary(str(tmp))
        check_model_written(tmp, rec)
        moved_aside = out_dir.exists()
        if moved_aside:
            os.replace(out_dir, old)
        try:
            os.replace(tmp, out_dir)
        except BaseException:
            if moved_aside:
                os.replace(old, out_dir)
            raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(old, ignore_errors=True)
    log.debug(
        "wrote COLMAP model (%d points, mean reprojection error %.3f px) to %s",
        rec.num_points3D(), rec.compute_mean_reprojection_error(), out_dir,
    )
    return rec


def check_model_written(folder: str | os.PathLike, rec: pycolmap.Reconstruction) -> None:
    """Raise ``OSError`` when pycolmap's binary model files in ``folder`` are shorter than ``rec`` needs.

    pycolmap reports success on files a full disk truncated. Lower bounds of
    COLMAP's binary format: ``images.bin`` holds 24 bytes per 2-D point,
    ``points3D.bin`` 51 per point and 8 per track element.
    """
    folder = Path(folder)
    n2d = sum(im.num_points2D() for im in rec.images.values())
    check_written(folder / "images.bin", 8 + 24 * n2d)
    check_written(folder / "points3D.bin", 8 + 51 * rec.num_points3D() + 8 * rec.compute_num_observations())
    check_written(folder / "cameras.bin", 8 + 24 * rec.num_cameras())


def read_model(path: str | os.PathLike) -> pycolmap.Reconstruction:
    """Read a COLMAP model folder (binary or text; pycolmap auto-detects).

    Raises ``FileNotFoundError`` if ``path`` is not a folder with a model.
    """
    path = Path(path)
    if not path.is_dir():
        raise FileNotFoundError(f"no COLMAP model folder at {path}")
    import pycolmap

    try:
        return pycolmap.Reconstruction(str(path))
    except ValueError as e:  # pycolmap raises ValueError for missing files
        raise FileNotFoundError(f"no COLMAP model in {path}: {e}") from e


def write_poses_model(folder: str | os.PathLike, rec: pycolmap.Reconstruction,
                      keypoints: dict[int, np.ndarray]) -> pycolmap.Reconstruction:
    """Write the input model for ``colmap point_triangulator``: cameras and poses, no 3-D points.

    Each image's 2-D points are its ``database.db`` keypoints (``keypoints``:
    image_id -> (K, 2); images absent get none), so the model agrees with the
    database whatever 2-D points the user's model held: COLMAP's triangulator
    stops when an image has 2-D points and their count differs from the
    database's. Returns the model written (binary, in ``folder``, created).
    """
    import pycolmap

    folder = Path(folder)
    model = pycolmap.Reconstruction(rec)  # a copy: the caller's model keeps its points
    for pid in list(model.point3D_ids()):
        model.delete_point3D(pid)
    for image_id, im in model.images.items():
        kp = np.asarray(keypoints.get(image_id, np.zeros((0, 2))), np.float64).reshape(-1, 2)
        im.points2D.clear()  # pycolmap only assigns 2-D points to an image that has none
        im.points2D = pycolmap.Point2DList([pycolmap.Point2D(xy) for xy in kp])
    folder.mkdir(parents=True, exist_ok=True)
    model.write_binary(str(folder))
    check_model_written(folder, model)
    return model
