"""Cameras: parsing COLMAP camera strings, EXIF inference, defaults.

A camera on the command line is a COLMAP ``cameras.txt`` line without its id:
``MODEL WIDTH HEIGHT PARAMS...``, e.g. ``PINHOLE 1000 750 850 850 500 375``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pycolmap

from ..errors import InputError

logger = logging.getLogger(__name__)

#: Focal length of the default camera, as a multiple of max(width, height);
#: COLMAP's own default when an image has no EXIF focal length.
DEFAULT_FOCAL_FACTOR = 1.2

#: The field of view a camera may have across its longer side, degrees. Matching
#: runs on a pinhole view of each photo; near 180 deg a pinhole view stretches
#: a few pixels over most of the image (a focal length of 18.5 px on a 640 px
#: photo, 173 deg: 92 s instead of 9 and 2.6 M "matches" of 104 k distinct
#: pixels), and the widest rectilinear lenses see about 120 deg. Below 1 deg
#: (beyond a 2000 mm lens on a full-frame camera) the rays of a photo are
#: almost parallel and depth is hardly measurable. Either is a typo in a focal
#: length far more often than a real camera.
MIN_FOV_DEG, MAX_FOV_DEG = 1.0, 170.0


def parse_camera(text: str, camera_id: int = 1) -> pycolmap.Camera:
    """Parse ``"MODEL WIDTH HEIGHT PARAMS..."`` into a :class:`pycolmap.Camera`.

    Raises :class:`InputError` with a one-line reason on any malformed string.
    """
    fields = text.replace(",", " ").split()
    if len(fields) < 4:
        raise InputError(
            f"bad camera {text!r}: expected 'MODEL WIDTH HEIGHT PARAMS...', "
            "e.g. 'PINHOLE 1000 750 850 850 500 375'"
        )
    model = fields[0].upper()
    try:
        width, height = int(fields[1]), int(fields[2])
        params = [float(v) for v in fields[3:]]
    except ValueError:
        raise InputError(f"bad camera {text!r}: WIDTH, HEIGHT and PARAMS must be numbers") from None
    if width <= 0 or height <= 0:
        raise InputError(f"bad camera {text!r}: WIDTH and HEIGHT must be positive")
    try:
        camera = pycolmap.Camera.create_from_model_name(camera_id, model, 1.0, width, height)
    except Exception:
        raise InputError(
            f"bad camera {text!r}: unknown camera model {model!r} "
            "(COLMAP models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, ...)"
        ) from None
    expected = len(camera.params)
    if len(params) != expected:
        raise InputError(
            f"bad camera {text!r}: model {model} takes {expected} parameters "
            f"({camera.params_info}), got {len(params)}"
        )
    camera.params = np.asarray(params, dtype=np.float64)
    camera.has_prior_focal_length = True  # given by the user: trusted
    if not camera.verify_params() or camera.has_bogus_params(0.01, 100.0, 10.0):
        raise InputError(f"bad camera {text!r}: implausible parameters ({camera.params_info})")
    why = implausible_field_of_view(camera)
    if why:
        raise InputError(f"bad camera {text!r}: {why}")
    return camera


def implausible_field_of_view(camera: pycolmap.Camera) -> str | None:
    """Why the camera's field of view (across its longer side) is outside :data:`MIN_FOV_DEG`..:data:`MAX_FOV_DEG`."""
    K = calibration_matrix(camera)
    f, size, side = (K[0, 0], camera.width, "width") if camera.width >= camera.height else \
        (K[1, 1], camera.height, "height")
    fov = float(np.degrees(2.0 * np.arctan2(size / 2.0, f))) if f > 0 else 180.0
    if MIN_FOV_DEG <= fov <= MAX_FOV_DEG:
        return None
    return (f"a focal length of {f:.4g} px sees {fov:.1f} deg across the {size} px {side}, a camera sees "
            f"{MIN_FOV_DEG:g} to {MAX_FOV_DEG:g} deg (is the focal length in pixels?)")


def pinhole_camera(K: np.ndarray, width: int, height: int, camera_id: int = 1) -> pycolmap.Camera:
    """A COLMAP ``PINHOLE`` camera from a 3x3 matrix (COLMAP pixel convention)."""
    return pycolmap.Camera(camera_id=camera_id, model="PINHOLE", width=int(width), height=int(height),
                           params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]])


def camera_to_string(camera: pycolmap.Camera) -> str:
    """Inverse of :func:`parse_camera`."""
    params = " ".join(f"{p:.10g}" for p in camera.params)
    return f"{camera.model_name} {camera.width} {camera.height} {params}"


def default_camera(width: int, height: int, camera_id: int = 1) -> pycolmap.Camera:
    """COLMAP's default: SIMPLE_RADIAL, f = 1.2 * max(W, H), centred principal point."""
    f = DEFAULT_FOCAL_FACTOR * max(width, height)
    camera = pycolmap.Camera.create_from_model_name(camera_id, "SIMPLE_RADIAL", f, width, height)
    camera.has_prior_focal_length = False  # a guess
    return camera


def infer_camera(path: str | Path, width: int, height: int, camera_id: int = 1) -> tuple[pycolmap.Camera, str]:
    """Camera from the image's EXIF focal length through pycolmap, else the default.

    Returns the camera and its source, ``"exif"`` or ``"default"``. ``width`` and
    ``height`` are those of the decoded (EXIF-rotated) image; when EXIF rotation
    swaps the axes, the focal length is kept and the principal point re-centred.
    """
    try:
        camera = pycolmap.infer_camera_from_image(str(path))
        has_prior = bool(camera.has_prior_focal_length)
    except Exception as err:  # unreadable EXIF is not an error: fall back
        logger.debug("EXIF camera inference failed for %s: %s", path, err)
        camera, has_prior = None, False
    if camera is None or not has_prior:
        return default_camera(width, height, camera_id), "default"
    f = float(camera.mean_focal_length())
    scale = max(width, height) / max(camera.width, camera.height)
    out = pycolmap.Camera.create_from_model_name(camera_id, "SIMPLE_RADIAL", f * scale, width, height)
    out.has_prior_focal_length = True
    why = implausible_field_of_view(out)
    if why:
        raise InputError(f"implausible camera from the EXIF data of {Path(path).name}: {camera_to_string(out)}: "
                         f"{why}; give the camera with --camera")
    return out, "exif"


def calibration_matrix(camera: pycolmap.Camera) -> np.ndarray:
    """3x3 pinhole matrix of a camera (ignoring distortion), COLMAP pixel convention."""
    return np.asarray(camera.calibration_matrix(), dtype=np.float64)


def has_distortion(camera: pycolmap.Camera) -> bool:
    """True when the model has non-zero distortion parameters."""
    if camera.model_name in ("SIMPLE_PINHOLE", "PINHOLE"):
        return False
    extra = np.asarray(camera.params)[list(camera.extra_params_idxs())]
    return bool(np.any(np.abs(extra) > 0))


def read_strecha_camera(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]]:
    """A ``*.camera`` file of Strecha et al.'s data sets (fountain-P11) in COLMAP's terms.

    The file holds K (3x3), 3 distortion values, R camera-to-world (3x3), the centre
    C and the size; its principal point assumes integer pixel centres.
    Returns ``K`` (principal point moved by 0.5 to COLMAP's pixel centres),
    ``R``, ``t`` (``x_cam = R @ X + t``) and ``(width, height)``.
    """
    v = np.array(Path(path).read_text().split(), float)
    K, R_c2w, C = v[:9].reshape(3, 3).copy(), v[12:21].reshape(3, 3), v[21:24]
    K[:2, 2] += 0.5
    return K, R_c2w.T, -R_c2w.T @ C, (int(v[24]), int(v[25]))
