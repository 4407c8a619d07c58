"""The mesh of a pair's points: camera 1's pixel grid (the default) or screened Poisson.

:func:`grid_mesh` joins the points on camera 1's pixel grid into triangles where
the surface is continuous (a range image's mesh): linear time, and only what was
matched. :func:`poisson_mesh` is open3d's screened Poisson surface with density
trimming: smooth and closed over holes, seconds more. open3d is imported lazily
inside the functions (its import costs ~1 s), so importing this module is cheap.
"""

from __future__ import annotations

import logging
import time

import numpy as np
from numba import njit

from ..arrays import finite_rows

log = logging.getLogger(__name__)

__all__ = ["MAX_GRAZING_DEG", "MIN_POISSON_POINTS", "grid_mesh", "poisson_mesh", "voxel_downsample_to"]

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


# --- the grid mesh: camera 1's pixel grid, triangulated where the surface is continuous ---

#: A triangle (or a cell's point) seen at more than this angle from camera 1's viewing ray is a
#: depth jump between two surfaces, not a surface: the mesh leaves it open. Two samples d pixels
#: apart at depth z lie on one surface when their depths differ by at most tan(angle) * d * z / f.
#: 84 degrees keeps slanted floors and walls (a road seen at 80 degrees: 5.7 px of depth a pixel
#: against 9.5) and cuts the jump from a foreground object to the wall 3 % of the depth behind it
#: at the default 5-pixel grid of a 2000-pixel photo (f ~ 1700 px).
MAX_GRAZING_DEG = 84.0
#: The grid has at most this many cells a vertex of the budget: its arrays (~70 bytes a cell)
#: stay near 100 MB at the default 150 000 vertices however large the photo and few its matches.
MAX_CELLS_PER_VERTEX = 8


@njit(cache=True)
def _pixel(uv, k, h, w):
    """Row and column of point ``k``'s pixel (COLMAP pixels: the centre of pixel (0, 0) is (0.5, 0.5))."""
    return min(max(int(np.floor(uv[k, 1])), 0), h - 1), min(max(int(np.floor(uv[k, 0])), 0), w - 1)


@njit(cache=True)
def _grid_cells(uv, z, h, w, step):
    """Per cell of ``step`` pixels: the point nearest the cell's centre (-1: none)."""
    rows, cols = -(-h // step), -(-w // step)
    rep = np.full((rows, cols), -1, np.int64)
    best = np.full((rows, cols), np.inf)
    half = 0.5 * (step - 1)
    for k in range(uv.shape[0]):
        r, c = _pixel(uv, k, h, w)
        i, j = r // step, c // step
        d = (r - i * step - half) ** 2 + (c - j * step - half) ** 2
        if d < best[i, j] and np.isfinite(z[k]) and z[k] > 0:
            best[i, j] = d
            rep[i, j] = k
    return rep


@njit(cache=True)
def _grid_vertices(uv, xyz, rgb, rep, h, w, step, slope):
    """Each cell's vertex: the sums of its points on the representative's surface (position,
    colour when ``rgb`` has rows) and their count."""
    rows, cols = rep.shape
    acc = np.zeros((rows, cols, 3))
    col = np.zeros((rows, cols, 3))
    cnt = np.zeros((rows, cols))
    for k in range(uv.shape[0]):
        r, c = _pixel(uv, k, h, w)
        i, j = r // step, c // step
        q = rep[i, j]
        if q < 0:
            continue
        zq = xyz[q, 2]
        if abs(xyz[k, 2] - zq) <= slope * step * zq:
            for a in range(3):
                acc[i, j, a] += xyz[k, a]
            if rgb.shape[0]:
                for a in range(3):
                    col[i, j, a] += rgb[k, a]
            cnt[i, j] += 1.0
    return acc, col, cnt


@njit(cache=True)
def _joined(za, zb, tol):
    return abs(za - zb) <= tol * min(za, zb)


@njit(cache=True)
def _put(tris, n, a, b, c):
    """Triangle ``(a, b, c)`` as row ``n`` of ``tris``; returns the next row."""
    tris[n, 0], tris[n, 1], tris[n, 2] = a, b, c
    return n + 1


@njit(cache=True)
def _grid_triangles(z, has, slope, step):
    """Two triangles a cell of four vertices (one where a corner is missing), each
    kept where its edges join one surface; wound so that they face camera 1."""
    rows, cols = z.shape
    tris = np.empty((2 * rows * cols, 3), np.int64)
    n = 0
    tol = slope * step
    tol_d = tol * np.sqrt(2.0)
    for i in range(rows - 1):
        for j in range(cols - 1):
            a, b, c, d = i * cols + j, i * cols + j + 1, (i + 1) * cols + j, (i + 1) * cols + j + 1
            ha, hb, hc, hd = has[i, j], has[i, j + 1], has[i + 1, j], has[i + 1, j + 1]
            za, zb, zc, zd = z[i, j], z[i, j + 1], z[i + 1, j], z[i + 1, j + 1]
            ab = ha and hb and _joined(za, zb, tol)
            ac = ha and hc and _joined(za, zc, tol)
            bd = hb and hd and _joined(zb, zd, tol)
            cd = hc and hd and _joined(zc, zd, tol)
            bc = hb and hc and _joined(zb, zc, tol_d)
            ad = ha and hd and _joined(za, zd, tol_d)
            # the diagonal whose ends are closer in depth (the one a fold runs along)
            if bc and (not ad or abs(zb - zc) <= abs(za - zd)):
                if ab and ac:
                    n = _put(tris, n, a, c, b)
                if bd and cd:
                    n = _put(tris, n, b, c, d)
            elif ad:
                if ab and bd:
                    n = _put(tris, n, a, d, b)
                if ac and cd:
                    n = _put(tris, n, a, c, d)
    return tris[:n]


@njit(cache=True)
def _vertex_normals(v, f):
    """Area-weighted unit vertex normals of a triangle mesh."""
    out = np.zeros_like(v)
    for k in range(f.shape[0]):
        a, b, c = f[k, 0], f[k, 1], f[k, 2]
        ux, uy, uz = v[b, 0] - v[a, 0], v[b, 1] - v[a, 1], v[b, 2] - v[a, 2]
        wx, wy, wz = v[c, 0] - v[a, 0], v[c, 1] - v[a, 1], v[c, 2] - v[a, 2]
        nx, ny, nz = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
        for q in (a, b, c):
            out[q, 0] += nx
            out[q, 1] += ny
            out[q, 2] += nz
    for q in range(v.shape[0]):
        norm = np.sqrt(out[q, 0] ** 2 + out[q, 1] ** 2 + out[q, 2] ** 2)
        if norm > 0:
            out[q] /= norm
    return out


def grid_mesh(
    uv: np.ndarray,
    xyz: np.ndarray,
    rgb: np.ndarray | None,
    shape: tuple[int, int],
    focal: float,
    *,
    max_vertices: int = 150_000,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """A triangle mesh on camera 1's pixel grid: the surface the matches saw, open at its depth jumps.

    The dense matches sit on camera 1's pixel grid, so the grid is their mesh's
    connectivity (a range image's mesh, as a depth camera's): cells of ``step``
    pixels (the least that gives at most ``max_vertices`` vertices) each get one
    vertex, the mean of the cell's points on the surface of the point nearest its
    centre; neighbouring vertices are joined into triangles unless the triangle
    would be seen at more than ``MAX_GRAZING_DEG`` from the viewing ray (a depth
    jump). Vertices without a triangle are dropped. Linear time: no surface is
    invented where nothing was matched (unlike Poisson, whose surface closes holes).

    Args:
        uv: (N, 2) positions in camera 1's image (COLMAP pixels).
        xyz: (N, 3) points in camera 1's frame (camera at the origin, z the depth).
        rgb: (N, 3) uint8 colours or None. shape: (height, width) of camera 1's image.
        focal: camera 1's focal length, pixels.
        max_vertices: the most vertices the mesh has.
    Returns:
        Like :func:`poisson_mesh`: ``(vertices (V, 3) float64, triangles (F, 3) int64
        facing camera 1, colours (V, 3) uint8 or None, unit vertex normals (V, 3))``.
    Raises:
        ValueError: fewer than 3 points, or no triangle joins them.
    """
    xyz = np.ascontiguousarray(xyz, np.float64)
    uv = np.ascontiguousarray(uv, np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or uv.shape != (len(xyz), 2):
        raise ValueError(f"uv and xyz must be (N, 2) and (N, 3), got {uv.shape}, {xyz.shape}")
    if not focal > 0 or max_vertices < 3:
        raise ValueError(f"focal must be > 0 and max_vertices >= 3, got {focal}, {max_vertices}")
    h, w = int(shape[0]), int(shape[1])
    step = max(1, int(np.ceil(np.sqrt(len(xyz) / max_vertices))))
    # at most MAX_CELLS_PER_VERTEX cells a vertex: few matches on a large image need no finer grid
    step = max(step, int(np.ceil(np.sqrt(h * w / (MAX_CELLS_PER_VERTEX * max_vertices)))))
    # the largest relative depth step a pixel on one surface: tan(angle) / f
    slope = float(np.tan(np.radians(MAX_GRAZING_DEG)) / focal)
    colours = np.zeros((0, 3), np.uint8) if rgb is None else np.ascontiguousarray(rgb, np.uint8)
    rep = _grid_cells(uv, np.ascontiguousarray(xyz[:, 2]), h, w, step)
    acc, col, cnt = _grid_vertices(uv, xyz, colours, rep, h, w, step, slope)
    has = cnt > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        vert = acc / cnt[..., None]
    tris = _grid_triangles(np.where(has, vert[..., 2], np.inf), has, slope, step)
    if len(tris) == 0:
        raise ValueError("no triangle: the points do not form a surface on camera 1's grid")
    used = np.zeros(has.size, bool)
    used[tris.ravel()] = True
    new = np.cumsum(used) - 1
    v = vert.reshape(-1, 3)[used]
    f = new[tris]
    cv = None if rgb is None else np.clip(np.rint(col.reshape(-1, 3)[used] / cnt.reshape(-1)[used, None]), 0, 255).astype(np.uint8)
    return v, f, cv, _vertex_normals(v, f)
