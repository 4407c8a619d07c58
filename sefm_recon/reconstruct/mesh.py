"""Screened Poisson surface reconstruction (open3d) with density trimming.

open3d is imported lazily inside the functions (its import costs ~1 s), so
importing this module is cheap.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from ..arrays import finite_rows

log = logging.getLogger(__name__)

__all__ = ["MIN_POISSON_POINTS", "poisson_mesh", "voxel_downsample_to"]

#: Fewer oriented points than this cannot define a meaningful surface.
MIN_POISSON_POINTS = 100
#: Points kept per voxel-downsampled point, at most, before the voxel averaging.
PRESAMPLE = 4


def voxel_downsample_to(pcd, max_points: int, max_iter: int = 6):
    """Voxel-downsample an open3d PointCloud to roughly ``max_points`` points.

    The voxel size is searched assuming surface-like data (count ~ size^-2);
    the result is within ~20 % of ``max_points`` and never above it by more
    than that. Positions, colours and normals are averaged per voxel (normals
    re-normalised). Returns ``(pcd, voxel_size)``; ``voxel_size`` is 0 when no
    downsampling was needed.
    """
    n = len(pcd.points)
    if n <= max_points:
        return pcd, 0.0
    pts = np.asarray(pcd.points)
    lo, hi = np.percentile(pts, [1, 99], axis=0)
    extent = np.maximum(hi - lo, 1e-12)
    # surface area guess: the two largest faces of the robust bounding box
    area = np.sort(extent)[1:].prod() * 2.0
    voxel = float(np.sqrt(area / max_points))
    best = None
    for _ in range(max_iter):
        down = pcd.voxel_down_sample(voxel)
        m = len(down.points)
        if m <= 1.2 * max_points and (best is None or m > len(best[0].points)):
            best = (down, voxel)
        if 0.8 * max_points <= m <= 1.2 * max_points:
            break
        voxel *= float(np.clip(np.sqrt(m / max_points), 0.5, 3.0))
    if best is None:  # never got small enough: take the last (coarsest) try
        best = (pcd.voxel_down_sample(voxel), voxel)
    down, voxel = best
    if down.has_normals():
        nrm = np.asarray(down.normals)
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    log.debug("voxel downsample %d -> %d points (voxel %.4g)", n, len(down.points), voxel)
    return down, voxel


def poisson_mesh(
    xyz: np.ndarray,
    normals: np.ndarray,
    rgb: np.ndarray | None = None,
    depth: int = 9,
    density_quantile: float = 0.05,
    crop_to_points: bool = True,
    crop_margin: float = 0.05,
    max_points: int | None = 300_000,
    n_threads: int = -1,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """Screened Poisson mesh of an oriented, coloured point cloud.

    Steps: drop non-finite points; voxel-downsample to about ``max_points``
    (None = never; from a regular subset of ``PRESAMPLE * max_points`` points
    when there are more); open3d screened Poisson at ``depth``; remove vertices whose
    Poisson density (number of samples supporting them) is below the
    ``density_quantile`` quantile (Poisson extrapolates a closed surface, the
    low-density parts are that extrapolation); optionally crop to the input
    points' axis-aligned bounding box enlarged by ``crop_margin`` x its extent
    on every side; drop unreferenced vertices and degenerate triangles.

    Args:
        xyz: (N, 3) float points, world units.
        normals: (N, 3) float normals, oriented outwards (towards the cameras),
            e.g. from :func:`sefm_recon.reconstruct.points.estimate_normals`.
        rgb: (N, 3) uint8 colours or None.
        depth: octree depth (grid resolution <= 2**depth per axis).
        density_quantile: in [0, 1); 0 disables density trimming.
        max_points: voxel-downsample target; runtime grows ~linearly with it.
        n_threads: -1 = all cores.

    Returns:
        ``(vertices (V, 3) float64, triangles (F, 3) int64,
        vertex_colors (V, 3) uint8 or None (when rgb is None),
        vertex_normals (V, 3) float64 unit)``. Colours are Poisson's
        interpolation of the input colours.

    Raises:
        ValueError: fewer than ``MIN_POISSON_POINTS`` finite points, bad
            shapes, or nothing left after trimming.
    """
    import open3d as o3d

    xyz = np.asarray(xyz, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or normals.shape != xyz.shape:
        raise ValueError(f"xyz and normals must both be (N, 3), got {xyz.shape}, {normals.shape}")
    if rgb is not None:
        rgb = np.asarray(rgb)
        if rgb.shape != xyz.shape:
            raise ValueError(f"rgb must be {xyz.shape}, got {rgb.shape}")
    if not 0.0 <= density_quantile < 1.0:
        raise ValueError(f"density_quantile must be in [0, 1), got {density_quantile}")
    ok = finite_rows(xyz, normals)
    ok &= np.einsum("ij,ij->i", normals, normals) > 1e-24
    idx = np.flatnonzero(ok)
    if len(idx) < MIN_POISSON_POINTS:
        raise ValueError(
            f"Poisson meshing needs at least {MIN_POISSON_POINTS} points with normals, got {len(idx)}"
        )
    if max_points is not None and len(idx) > PRESAMPLE * max_points:
        # Every k-th point (in the matcher's line order, so spread over the
        # image) before the voxel averaging: the voxels still hold several
        # points each, and open3d gets a few times fewer to copy and hash.
        idx = idx[:: len(idx) // (PRESAMPLE * max_points)]
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(xyz.take(idx, axis=0))
    pcd.normals = o3d.utility.Vector3dVector(normals.take(idx, axis=0))
    if rgb is not None:
        pcd.colors = o3d.utility.Vector3dVector(rgb.take(idx, axis=0).astype(np.float64) / 255.0)
    n_ok = len(idx)
    if max_points is not None and n_ok > max_points:
        pcd, _ = voxel_downsample_to(pcd, int(max_points))

    t0 = time.perf_counter()
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            pcd, depth=int(depth), n_threads=int(n_threads)
        )
    dens = np.asarray(dens)
    log.debug(
        "Poisson depth %d on %d points: %d vertices, %d triangles in %.2f s",
        depth, len(pcd.points), len(mesh.vertices), len(mesh.triangles),
        time.perf_counter() - t0,
    )
    if density_quantile > 0 and len(dens):
        mesh.remove_vertices_by_mask(dens < np.quantile(dens, density_quantile))
    if crop_to_points:
        pts = np.asarray(pcd.points)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        pad = crop_margin * (hi - lo) + 1e-9
        box = o3d.geometry.AxisAlignedBoundingBox(lo - pad, hi + pad)
        mesh = mesh.crop(box)
    mesh.remove_degenerate_triangles()
    mesh.remove_unreferenced_vertices()
    if len(mesh.triangles) == 0:
        raise ValueError("Poisson mesh is empty after density trimming/cropping")
    mesh.compute_vertex_normals()

    vertices = np.asarray(mesh.vertices, dtype=np.float64).copy()
    triangles = np.asarray(mesh.triangles, dtype=np.int64).copy()
    vnormals = np.asarray(mesh.vertex_normals, dtype=np.float64).copy()
    colors = None
    if rgb is not None and mesh.has_vertex_colors():
        colors = np.clip(np.rint(np.asarray(mesh.vertex_colors) * 255.0), 0, 255).astype(np.uint8)
    return vertices, triangles, colors, vnormals
