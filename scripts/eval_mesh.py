"""The two meshes (``output.mesh = grid`` and ``poisson``) against the true depth of generated scenes.

    .venv/bin/python scripts/eval_mesh.py [--seeds 0 1 ...] [--size 1000 750]

Each seed's pair is matched with the true pose (so the points are in the scene's units,
camera 1 at the origin); both meshes are built from the same points. A vertex is
scored by its depth against view 1's true depth at the pixel it projects to; "within
1 %" is the share of vertices whose depth is off by less than 1 % of the true depth,
"covers" the share of view 1's 8 x 8-pixel blocks with a true surface that hold a vertex.
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np

from sefm_recon.config import load_config
from sefm_recon.eval_tables import _cameras, generated_cases
from sefm_recon.pipeline import reconstruct_pair
from sefm_recon.reconstruct.mesh import grid_mesh, poisson_mesh

BLOCK = 8  #: px, the blocks "covers" counts: about the grid mesh's cell at 1000 x 750


def score(vertices: np.ndarray, K: np.ndarray, depth: np.ndarray) -> tuple[float, float, float]:
    """(median relative depth error, share within 1 %, share of true-surface blocks covered)."""
    h, w = depth.shape
    p = vertices @ K.T
    u, v = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h) & (p[:, 2] > 0)
    r, c = np.clip(v.astype(int), 0, h - 1), np.clip(u.astype(int), 0, w - 1)
    true = depth[r, c].astype(np.float64)
    rel = np.where(inside & np.isfinite(true), np.abs(vertices[:, 2] - true) / true, np.inf)
    blocks = np.zeros((-(-h // BLOCK), -(-w // BLOCK)), bool)
    blocks[r[inside] // BLOCK, c[inside] // BLOCK] = True
    surface = np.isfinite(depth[::BLOCK, ::BLOCK])
    return float(np.median(rel)), float(np.mean(rel < 0.01)), float((blocks & surface).sum() / surface.sum())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    ap.add_argument("--size", type=int, nargs=2, default=(1000, 750))
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    cfg = load_config(None, ["output.mesh=none", "output.progress=false"], internal=True)
    rows = {"grid": [], "poisson": []}
    print(f"{'seed':>4} {'motion':>8} | {'grid: s':>7} {'verts':>6} {'med err':>8} {'<1%':>6} {'covers':>6} | "
          f"{'poisson: s':>10} {'verts':>6} {'med err':>8} {'<1%':>6} {'covers':>6}")
    for case in generated_cases(args.seeds, tuple(args.size)):
        res = reconstruct_pair(case.img1, case.img2, *_cameras(case), cfg, pose=case.pose)
        t0 = time.perf_counter()
        assert res.view1.scale == 1.0  # no downscaling: the matches' pixels are the working image's
        g = grid_mesh(res.uv1, res.xyz, res.rgb, res.view1.image.shape[:2],
                      float(res.view1.K[0, 0]), max_vertices=cfg.output.mesh_max_points)
        t1 = time.perf_counter()
        p = poisson_mesh(res.xyz, res.normals, res.rgb, depth=cfg.output.poisson_depth,
                         density_quantile=cfg.output.density_quantile, max_points=cfg.output.mesh_max_points)
        t2 = time.perf_counter()
        line = f"{case.name:>4} {case.variant:>8}"
        for name, mesh, dt in (("grid", g, t1 - t0), ("poisson", p, t2 - t1)):
            s = score(mesh[0], case.K1, case.view1.depth)
            rows[name].append((dt, len(mesh[0]), *s))
            line += f" | {dt:>{7 if name == 'grid' else 10}.2f} {len(mesh[0]):>6} {s[0]:>8.4f} {s[1]:>6.3f} {s[2]:>6.3f}"
        print(line, flush=True)
    for name, r in rows.items():
        a = np.mean(r, axis=0)
        print(f"mean {name}: {a[0]:.2f} s, {a[1]:.0f} vertices, median error {a[2]:.4f}, within 1 % {a[3]:.3f}, "
              f"covers {a[4]:.3f}")


if __name__ == "__main__":
    main()
