"""Dense matches -> a COLMAP database (keypoints, matches, two-view geometries).

COLMAP's triangulator and mapper work on keypoints and matches stored in a
SQLite database. SeFM's matches are dense and sub-pixel, and each pair's
matches land at different positions of a shared image, so they are first
*quantised* into one keypoint set per image, the way hloc's ``match_dense``
does for LoFTR-style matchers:

1. every match endpoint falls into a grid cell of ``cell_size`` px (cells are
   centred on multiples of ``cell_size`` in COLMAP pixel coordinates; at most
   one keypoint per cell);
2. inside a cell, the endpoints vote, weighted by their match score, for
   finer bins of ``max_error`` px; the keypoint is put in the winning bin (hloc
   puts it at the bin's centre; we use the score-weighted mean of the endpoints
   in that bin, which keeps the sub-pixel position);
3. each endpoint is assigned to its cell's keypoint when it lies within
   ``max_error`` px of it (hloc's re-assignment step), else its match is dropped;
4. per pair, duplicate and many-to-one matches are removed, best score first, so
   each keypoint has at most one partner in the other image.

A keypoint seen by several pairs thereby links them into multi-view tracks.
The two-view geometry of each pair comes from the given poses (configuration
CALIBRATED, with E, F and ``cam2_from_cam1``); its inlier matches are those
within ``max_epipolar_error`` px of their epipolar line.

Cameras, rigs, frames and images are copied from the workspace model with their
ids, so the database and the model agree (which ``pycolmap.triangulate_points``
requires).

The file is written by pycolmap 4 and then given the ``images`` columns of the
older schema (:func:`add_legacy_columns`), so that COLMAP 3.8 (what Debian 12
and Ubuntu 24.04 install) opens it as well as current COLMAP and pycolmap.
"""

from __future__ import annotations

import logging
import os
import sqlite3
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import pycolmap

log = logging.getLogger(__name__)

__all__ = ["PairMatches", "Quantised", "StoredPairMatches", "add_legacy_columns", "quantise_matches", "two_view_geometry",
           "write_database"]

#: Columns of the ``images`` table up to COLMAP 3.8 that pycolmap 4 (COLMAP >= 3.10 keeps pose priors
#: in their own table) no longer writes. COLMAP 3.8 reads ``SELECT * FROM images`` by column position
#: (image_id, name, camera_id, then these seven), so without them it stops with "SQL logic error".
#: Current COLMAP names its columns and ignores extra ones. NULL is what 3.8 itself stores for "no
#: prior" (its NaN default; SQLite stores NaN as NULL).
LEGACY_IMAGE_COLUMNS = ("prior_qw", "prior_qx", "prior_qy", "prior_qz", "prior_tx", "prior_ty", "prior_tz")


@dataclass
class PairMatches:
    """Dense matches of one image pair (COLMAP pixel coordinates of the original images)."""

    image_id1: int
    image_id2: int
    uv1: np.ndarray  #: (N, 2)
    uv2: np.ndarray  #: (N, 2)
    score: np.ndarray  #: (N,)


class StoredPairMatches:
    """A pair's dense matches read from its ``matches.npz`` when asked for (one pair in memory at a time)."""

    def __init__(self, image_id1: int, image_id2: int, path: str | os.PathLike):
        self.image_id1, self.image_id2, self.path = image_id1, image_id2, Path(path)

    def _get(self, key: str) -> np.ndarray:
        with np.load(self.path) as f:
            return f[key]

    uv1 = property(lambda self: self._get("uv1"))
    uv2 = property(lambda self: self._get("uv2"))
    score = property(lambda self: self._get("score"))


@dataclass
class Quantised:
    keypoints: dict[int, np.ndarray]  #: image_id -> (K, 2) float32 keypoints
    matches: dict[tuple[int, int], np.ndarray]  #: (image_id1, image_id2) -> (M, 2) uint32 keypoint indices
    dropped: int = 0  #: dense matches that found no keypoint within max_error


def _assign(uv: np.ndarray, score: np.ndarray, cell_size: float, max_error: float):
    """Quantise one image's match endpoints; returns (keypoints (K, 2), keypoint id per endpoint or -1)."""
    n = len(uv)
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, np.int64)
    cells = np.round(uv / cell_size).astype(np.int64)
    bins = np.round(uv / max_error).astype(np.int64)
    cells -= cells.min(0)
    bins -= bins.min(0)
    ck = cells[:, 0] * (int(cells[:, 1].max()) + 1) + cells[:, 1]
    fk = bins[:, 0] * (int(bins[:, 1].max()) + 1) + bins[:, 1]
    del cells, bins  # an image in many pairs holds millions of endpoints: free each temporary when done
    order = np.lexsort((fk, ck))
    ck_s, fk_s = ck[order], fk[order]
    del ck, fk
    new_group = np.r_[True, (ck_s[1:] != ck_s[:-1]) | (fk_s[1:] != fk_s[:-1])]
    del fk_s
    group = np.cumsum(new_group) - 1  # (cell, bin) group of each sorted endpoint
    votes = np.bincount(group, weights=score[order])
    g_cell = ck_s[new_group]
    new_cell = np.r_[True, g_cell[1:] != g_cell[:-1]]
    cell_of_group = np.cumsum(new_cell) - 1
    n_cells = int(cell_of_group[-1]) + 1
    # the winning bin of each cell: most votes (ties: the first bin)
    by_votes = np.lexsort((-votes, cell_of_group))
    first = np.r_[True, cell_of_group[by_votes][1:] != cell_of_group[by_votes][:-1]]
    winner = np.empty(n_cells, np.int64)
    winner[cell_of_group[by_votes[first]]] = by_votes[first]
    # keypoint: score-weighted mean of the endpoints in the winning bin
    in_winner = winner[cell_of_group[group]] == group
    w = score[order] * in_winner
    cell_s = cell_of_group[group]
    wsum = np.bincount(cell_s, weights=w, minlength=n_cells)
    kp = np.stack([np.bincount(cell_s, weights=w * uv[order, k], minlength=n_cells) for k in (0, 1)], 1)
    kp /= np.maximum(wsum, 1e-12)[:, None]
    ids_sorted = np.where(np.linalg.norm(uv[order] - kp[cell_s], axis=1) <= max_error, cell_s, -1)
    ids = np.empty(n, np.int64)
    ids[order] = ids_sorted
    return kp, ids


def _unique_matches(ids1: np.ndarray, ids2: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Indices of the matches kept: each keypoint used once on each side, best score first."""
    idx = np.flatnonzero((ids1 >= 0) & (ids2 >= 0))
    idx = idx[np.argsort(-score[idx], kind="stable")]
    _, first = np.unique(ids1[idx], return_index=True)
    idx = idx[np.sort(first)]
    _, first = np.unique(ids2[idx], return_index=True)
    return idx[np.sort(first)]


def quantise_matches(pairs: list[PairMatches], cell_size: float = 4.0, max_error: float = 1.0) -> Quantised:
    """Turn dense pair matches into per-image keypoints and per-pair keypoint matches.

    Args:
        pairs: the dense matches of each pair (each unordered pair at most once).
        cell_size: px; at most one keypoint per ``cell_size`` x ``cell_size`` cell.
        max_error: px; an endpoint farther than this from its cell's keypoint loses
            its match. Also the size of the voting bins inside a cell.

    Returns:
        Keypoints of every image that takes part in a pair (only those used by a
        kept match), and the matches of each pair as keypoint indices.
    """
    if cell_size <= 0 or max_error <= 0:
        raise ValueError("cell_size and max_error must be positive")
    # gather every endpoint of each image over all its pairs
    per_image: dict[int, list[tuple[int, int]]] = {}
    for p, pm in enumerate(pairs):
        per_image.setdefault(pm.image_id1, []).append((p, 0))
        per_image.setdefault(pm.image_id2, []).append((p, 1))
    kp_ids: dict[tuple[int, int], np.ndarray] = {}
    keypoints: dict[int, np.ndarray] = {}
    for image_id, sides in per_image.items():
        uvs = [np.asarray(pairs[p].uv1 if s == 0 else pairs[p].uv2, np.float64).reshape(-1, 2) for p, s in sides]
        scores = [np.asarray(pairs[p].score, np.float64).reshape(-1) for p, _ in sides]
        lengths = [len(uv) for uv in uvs]
        uv_all, score_all = np.concatenate(uvs), np.concatenate(scores)
        del uvs, scores
        kp, ids = _assign(uv_all, score_all, cell_size, max_error)
        del uv_all, score_all
        ids = ids.astype(np.int32)  # held for every pair until the matches are made: half the memory
        keypoints[image_id] = kp
        start = 0
        for (p, s), n in zip(sides, lengths):
            kp_ids[(p, s)] = ids[start:start + n]
            start += n
    matches: dict[tuple[int, int], np.ndarray] = {}
    used: dict[int, list[np.ndarray]] = {i: [] for i in keypoints}
    dropped = 0
    for p, pm in enumerate(pairs):
        i1, i2 = kp_ids[(p, 0)], kp_ids[(p, 1)]
        dropped += int(np.sum((i1 < 0) | (i2 < 0)))
        keep = _unique_matches(i1, i2, np.asarray(pm.score, np.float64))
        m = np.stack([i1[keep], i2[keep]], 1)
        matches[(pm.image_id1, pm.image_id2)] = m
        used[pm.image_id1].append(m[:, 0])
        used[pm.image_id2].append(m[:, 1])
    # drop keypoints no kept match refers to, and renumber
    for image_id, kp in keypoints.items():
        ref = np.unique(np.concatenate(used[image_id])) if used[image_id] else np.zeros(0, np.int64)
        remap = np.full(len(kp), -1, np.int64)
        remap[ref] = np.arange(len(ref))
        keypoints[image_id] = np.ascontiguousarray(kp[ref], np.float32)
        for (a, b), m in matches.items():
            if a == image_id:
                m[:, 0] = remap[m[:, 0]]
            if b == image_id:
                m[:, 1] = remap[m[:, 1]]
    matches = {k: np.ascontiguousarray(m, np.uint32) for k, m in matches.items()}
    return Quantised(keypoints, matches, dropped)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]], dtype=np.float64)


def two_view_geometry(
    image1: pycolmap.Image,
    image2: pycolmap.Image,
    camera1: pycolmap.Camera,
    camera2: pycolmap.Camera,
    kp1: np.ndarray,
    kp2: np.ndarray,
    matches: np.ndarray,
    max_epipolar_error: float = 4.0,
) -> pycolmap.TwoViewGeometry:
    """A CALIBRATED two-view geometry from the images' poses; inliers by epipolar distance.

    The epipolar distance is measured between undistorted normalised rays and
    converted to pixels with each camera's mean focal length.
    """
    import pycolmap

    T1, T2 = image1.cam_from_world(), image2.cam_from_world()
    rel = T2 * T1.inverse()
    M = np.asarray(rel.matrix(), np.float64)
    R, t = M[:, :3], M[:, 3]
    E = _skew(t) @ R
    K1 = np.asarray(camera1.calibration_matrix(), np.float64)
    K2 = np.asarray(camera2.calibration_matrix(), np.float64)
    F = np.linalg.inv(K2).T @ E @ np.linalg.inv(K1)
    inliers = np.zeros((0, 2), np.uint32)
    tri_angle = 0.0
    if len(matches):
        x1 = np.asarray(camera1.cam_from_img(np.ascontiguousarray(kp1[matches[:, 0]], np.float64)), np.float64)
        x2 = np.asarray(camera2.cam_from_img(np.ascontiguousarray(kp2[matches[:, 1]], np.float64)), np.float64)
        h1 = np.c_[x1, np.ones(len(x1))]
        h2 = np.c_[x2, np.ones(len(x2))]
        l2 = h1 @ E.T  # epipolar lines in image 2 (normalised)
        l1 = h2 @ E
        num = np.abs(np.sum(h2 * l2, 1))
        d2 = num / np.maximum(np.hypot(l2[:, 0], l2[:, 1]), 1e-12) * camera2.mean_focal_length()
        d1 = num / np.maximum(np.hypot(l1[:, 0], l1[:, 1]), 1e-12) * camera1.mean_focal_length()
        ok = np.isfinite(d1) & np.isfinite(d2) & (np.maximum(d1, d2) <= max_epipolar_error)
        inliers = np.ascontiguousarray(matches[ok], np.uint32)
        # median angle between the viewing rays (world axes)
        r1 = h1[ok] @ np.asarray(T1.rotation.matrix()).copy()  # R1^T x1 as rows
        r2 = h2[ok] @ np.asarray(T2.rotation.matrix()).copy()
        if len(r1):
            c = np.sum(r1 * r2, 1) / (np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1))
            tri_angle = float(np.median(np.arccos(np.clip(c, -1, 1))))
    g = pycolmap.TwoViewGeometry()
    g.config = int(pycolmap.TwoViewGeometryConfiguration.CALIBRATED)
    g.E = E
    g.F = F
    g.cam2_from_cam1 = rel
    g.inlier_matches = inliers
    g.tri_angle = tri_angle
    return g


def write_database(
    path: str | os.PathLike,
    reconstruction: pycolmap.Reconstruction,
    quantised: Quantised,
    max_epipolar_error: float = 4.0,
) -> dict:
    """Write a new COLMAP database at ``path`` (which must not exist).

    Every camera, rig, frame and image of ``reconstruction`` is written with its
    id; images without keypoints get an empty keypoint list. Returns counts.
    """
    import pycolmap

    path = Path(path)
    if path.exists():
        raise FileExistsError(path)
    n_matches = n_inliers = n_pairs = 0
    db = pycolmap.Database.open(str(path))
    try:
        for cam in reconstruction.cameras.values():
            db.write_camera(cam, use_camera_id=True)
        for rig in reconstruction.rigs.values():
            db.write_rig(rig, use_rig_id=True)
        for frame in reconstruction.frames.values():
            db.write_frame(frame, use_frame_id=True)
        for image_id in sorted(reconstruction.images):
            im = reconstruction.images[image_id]
            db.write_image(pycolmap.Image(name=im.name, camera_id=im.camera_id, image_id=image_id),
                           use_image_id=True)
            kp = quantised.keypoints.get(image_id, np.zeros((0, 2), np.float32))
            db.write_keypoints(image_id, np.ascontiguousarray(kp, np.float32))
        for (a, b), m in quantised.matches.items():
            ia, ib = reconstruction.images[a], reconstruction.images[b]
            db.write_matches(a, b, m)
            g = two_view_geometry(ia, ib, ia.camera, ib.camera, quantised.keypoints[a], quantised.keypoints[b],
                                  m, max_epipolar_error)
            db.write_two_view_geometry(a, b, g)
            n_pairs += 1
            n_matches += len(m)
            n_inliers += len(g.inlier_matches)
        counts = {
            "db_images": db.num_images(),
            "db_keypoints": int(db.num_keypoints()),
            "db_matched_pairs": n_pairs,
            "db_matches": n_matches,
            "db_inlier_matches": n_inliers,
        }
    finally:
        db.close()
    add_legacy_columns(path)
    log.info("database: %d keypoints, %d matches (%d geometric inliers) over %d pairs",
             counts["db_keypoints"], n_matches, n_inliers, n_pairs)
    return counts


def add_legacy_columns(path: str | os.PathLike) -> list[str]:
    """Add the ``images`` columns COLMAP 3.8 expects (:data:`LEGACY_IMAGE_COLUMNS`) where missing.

    ``ALTER TABLE ... ADD COLUMN`` appends them after ``camera_id``, the positions
    3.8 reads them from. Returns the columns added (none for a database that has them).
    """
    con = sqlite3.connect(str(path))
    try:
        have = [row[1] for row in con.execute("PRAGMA table_info(images)")]
        extra = have[3:]
        if have[:3] != ["image_id", "name", "camera_id"] or extra != list(LEGACY_IMAGE_COLUMNS[:len(extra)]):
            # columns we do not know sit where 3.8 reads its priors: appending would not help it
            log.warning("database %s: images table has columns %s; left as it is (COLMAP 3.8 may not read it)",
                        path, have)
            return []
        added = [c for c in LEGACY_IMAGE_COLUMNS if c not in have]
        with con:
            for c in added:
                con.execute(f"ALTER TABLE images ADD COLUMN {c} REAL")
    finally:
        con.close()
    return added
