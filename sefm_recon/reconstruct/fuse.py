"""Fusing the point clouds of several image pairs into one cloud.

Pairs that overlap reconstruct the same surface twice or more. The clouds are
merged on a voxel grid (one point per occupied voxel: the mean position and
colour of the points in it), outliers are removed statistically, and normals are
estimated by local PCA and turned towards the cameras that saw each point.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from .points import clean_points

log = logging.getLogger(__name__)

__all__ = ["FusedCloud", "fuse_point_clouds", "orient_normals"]


@dataclass
class FusedCloud:
    xyz: np.ndarray  #: (N, 3) float64
    rgb: np.ndarray  #: (N, 3) uint8
    normals: np.ndarray  #: (N, 3) float64 unit normals, facing the cameras
    support: np.ndarray  #: (N,) number of pairs whose points fell into the point's voxel
    stats: dict = field(default_factory=dict)


def _voxel_groups(xyz: np.ndarray, voxel: float) -> tuple[np.ndarray, int]:
    """Voxel index of every point (0..n_voxels-1) and the number of voxels."""
    keys = np.floor((xyz - xyz.min(0)) / voxel).astype(np.int64)
    dims = keys.max(0) + 1
    if float(dims[0]) * float(dims[1]) * float(dims[2]) < 2**62:
        flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
        _, inv = np.unique(flat, return_inverse=True)
    else:  # a huge extent for the voxel: unique rows instead of one integer key
        _, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    return inv, int(inv.max()) + 1 if len(inv) else 0


def orient_normals(normals: np.ndarray, view_dirs: np.ndarray) -> np.ndarray:
    """Flip each normal so that it points along ``view_dirs`` (towards its cameras)."""
    flip = np.einsum("ij,ij->i", normals, view_dirs) < 0
    out = normals.copy()
    out[flip] *= -1.0
    return out


def fuse_point_clouds(
    clouds: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    voxel: float,
    normals: list[np.ndarray | None] | None = None,
    std_ratio: float = 2.5,
    nb_neighbors: int = 16,
    normal_neighbors: int = 16,
) -> FusedCloud:
    """Merge per-pair clouds in world coordinates.

    Args:
        clouds: per pair ``(xyz (N, 3), rgb (N, 3) uint8, camera_centre (3,))``;
            the centre is that of a camera that saw the points (the pair's first),
            used to orient the normals.
        voxel: voxel edge, world units (> 0).
        normals: optional per-cloud (N, 3) unit normals (each pair's own, from
            its denser neighbourhoods); a fused point gets the mean of those in
            its voxel, turned towards its cameras. Without them (or where one is
            missing), normals are estimated on the fused cloud (slower).
        std_ratio, nb_neighbors: statistical outlier removal (see
            :func:`~sefm_recon.reconstruct.points.clean_points`).

    Returns:
        The fused cloud; ``stats`` has ``input_points``, ``voxel``,
        ``merged_points``, ``multi_pair_points`` (voxels filled by two or more
        pairs) and ``points``.
    """
    import open3d as o3d

    if voxel <= 0 or not np.isfinite(voxel):
        raise ValueError(f"voxel must be positive, got {voxel}")
    if normals is None or len(normals) != len(clouds) or any(n is None for n in normals):
        normals = [None] * len(clouds)
    parts = [(np.asarray(x, np.float64).reshape(-1, 3), np.asarray(c, np.uint8).reshape(-1, 3),
              np.asarray(C, np.float64).reshape(3), None if n is None else np.asarray(n, np.float64).reshape(-1, 3))
             for (x, c, C), n in zip(clouds, normals)]
    parts = [p for p in parts if len(p[0])]
    have_normals = bool(parts) and all(p[3] is not None and len(p[3]) == len(p[0]) for p in parts)
    n_in = sum(len(p[0]) for p in parts)
    empty = FusedCloud(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros((0, 3)), np.zeros(0, np.int64),
                       {"input_points": n_in, "voxel": voxel, "merged_points": 0, "multi_pair_points": 0,
                        "points": 0})
    if not parts:
        return empty
    xyz = np.concatenate([p[0] for p in parts])
    rgb = np.concatenate([p[1] for p in parts]).astype(np.float64)
    src = np.concatenate([np.full(len(p[0]), k, np.int64) for k, p in enumerate(parts)])
    centres = np.stack([p[2] for p in parts])
    nrm = np.concatenate([p[3] for p in parts]) if have_normals else None
    ok = np.isfinite(xyz).all(1)
    if nrm is not None:
        ok &= np.isfinite(nrm).all(1)
        nrm = nrm[ok]
    xyz, rgb, src = xyz[ok], rgb[ok], src[ok]
    view = centres[src] - xyz
    view /= np.maximum(np.linalg.norm(view, axis=1, keepdims=True), 1e-12)

    inv, n_vox = _voxel_groups(xyz, voxel)
    cnt = np.bincount(inv, minlength=n_vox).astype(np.float64)
    mean = lambda a: np.stack([np.bincount(inv, a[:, k], n_vox) for k in range(a.shape[1])], 1) / cnt[:, None]  # noqa: E731
    fx, frgb, fview = mean(xyz), mean(rgb), mean(view)
    fn = None
    if nrm is not None:
        nrm = orient_normals(nrm, view)  # each towards its own camera before averaging
        fn = mean(nrm)
        weak = np.linalg.norm(fn, axis=1) < 1e-3  # opposite normals cancelled: keep one of them
        if weak.any():
            first = np.full(n_vox, -1, np.int64)
            first[inv[::-1]] = np.arange(len(inv))[::-1]
            fn[weak] = nrm[first[weak]]
    # pairs per voxel: distinct (voxel, pair) combinations
    vp = np.unique(inv * len(parts) + src)
    support = np.bincount(vp // len(parts), minlength=n_vox)

    keep = clean_points(fx, nb_neighbors=nb_neighbors, std_ratio=std_ratio) if n_vox > nb_neighbors else np.ones(
        n_vox, bool)
    fx, frgb, fview, support = fx[keep], frgb[keep], fview[keep], support[keep]

    normals = np.zeros_like(fx)
    if fn is not None:
        normals = fn[keep]
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        normals = orient_normals(normals, fview)
    elif len(fx) >= 3:
        pcd = o3d.geometry.PointCloud()
        pcd.points = o3d.utility.Vector3dVector(fx)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=int(normal_neighbors)))
        normals = np.asarray(pcd.normals, np.float64).copy()
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        normals = orient_normals(normals, fview)
    stats = {
        "input_points": int(n_in),
        "voxel": float(voxel),
        "merged_points": int(n_vox),
        "multi_pair_points": int(np.sum(support >= 2)),
        "points": int(len(fx)),
    }
    log.info("fused %d points from %d pairs into %d (voxel %.4g, %d outliers removed)", n_in, len(parts),
             len(fx), voxel, n_vox - len(fx))
    return FusedCloud(fx, np.clip(np.rint(frgb), 0, 255).astype(np.uint8), normals, support, stats)
