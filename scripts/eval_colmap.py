"""Measure `sefm-recon colmap` on a generated workspace with true poses.

    .venv/bin/python scripts/eval_colmap.py --seed 21 --width 1000 --height 750 --views 3 [--workers 2]

Renders the scene (images/, a COLMAP text model with the true poses and no
points, gt/ depth maps) into a temporary folder, runs the CLI on it, and prints:
pairs and time, fused.ply points (counted by pymeshlab when installed, else from
the PLY header), the share of fused points within 1 % (and 0.5 %, 0.1 %) of the
scene size of the true surface, database.db contents (opened with pycolmap), and
the triangulated sparse/ model's points, mean reprojection error, track length
and accuracy; last, the run's row of the workspace table in docs/results.md.

The distance of a point to the true surface is bounded from above by projecting
it into every view and comparing its depth with that view's depth map along the
same ray (:func:`sefm_recon.evaluate.surface_distances`); the scene size is the
diagonal of the bounding box of everything the views see.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np  # before pycolmap (otherwise cv2 cannot write PNGs)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=21)
    ap.add_argument("--width", type=int, default=1000)
    ap.add_argument("--height", type=int, default=750)
    ap.add_argument("--views", type=int, default=3)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--keep", metavar="DIR", help="write the workspace and results here instead of a temporary folder")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--sfm", action="store_true",
                    help="replace the true model by pycolmap's own SfM of the images (SIFT, exhaustive matching, "
                         "incremental mapping); points are compared with the truth after a similarity alignment")
    a = ap.parse_args(argv)

    import pycolmap

    from sefm_recon.evaluate import surface_distances
    from sefm_recon.io.ply import read_ply_header, read_point_cloud
    from sefm_recon.synthetic import align_to_truth, colmap_sfm, render_scene, write_workspace

    tmp = None
    if a.keep:
        root = Path(a.keep)
        root.mkdir(parents=True, exist_ok=True)
    else:
        tmp = tempfile.TemporaryDirectory()
        root = Path(tmp.name)
    scene = render_scene(seed=a.seed, width=a.width, height=a.height, n_views=a.views, style="classic")
    ws = write_workspace(scene, root / "ws")
    align = (1.0, np.eye(3), np.zeros(3))
    if a.sfm:
        align = align_to_truth(colmap_sfm(ws), scene)
    out = root / "out"
    cmd = [sys.executable, "-m", "sefm_recon", "colmap", str(ws), "-o", str(out), "--overwrite", "-q"]
    if a.workers:
        cmd += ["--workers", str(a.workers)]
    for o in a.overrides:
        cmd += ["--set", o]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        print(r.stderr, file=sys.stderr)
        return r.returncode
    report = json.loads((out / "report.json").read_text())
    size = scene.meta["scene_size"]

    try:
        import pymeshlab

        ms = pymeshlab.MeshSet()
        ms.load_new_mesh(str(out / "fused.ply"))
        n_fused, counted_by = ms.current_mesh().vertex_number(), "pymeshlab"
    except ImportError:
        n_fused, counted_by = read_ply_header(out / "fused.ply")["elements"]["vertex"]["count"], "PLY header"
    s_, R_, t_ = align
    xyz, _, _ = read_point_cloud(out / "fused.ply")
    d = surface_distances(s_ * xyz @ R_.T + t_, scene.views)

    db = pycolmap.Database.open(str(out / "database.db"))
    try:
        db_counts = (db.num_cameras(), db.num_images(), db.num_keypoints(), db.num_matches(),
                     db.num_inlier_matches(), db.num_verified_image_pairs())
    finally:
        db.close()
    rec = pycolmap.Reconstruction(str(out / "sparse"))
    P = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    dP = surface_distances(s_ * P @ R_.T + t_, scene.views)

    c = report["counts"]
    print(f"scene seed {a.seed}, {a.views} views {a.width}x{a.height}, scene size {size:.2f}, "
          f"model: {'pycolmap SfM (aligned to the truth)' if a.sfm else 'true poses'}")
    if a.sfm:
        model = pycolmap.Reconstruction(str(ws / "sparse" / "0"))
        M = np.array([p.xyz for p in model.points3D.values()])
        dM = surface_distances(s_ * M @ R_.T + t_, scene.views)
        print(f"the SfM model's own {len(M)} points: within 1%: {np.mean(dM <= 0.01 * size):.4f}, "
              f"2%: {np.mean(dM <= 0.02 * size):.4f}, 3%: {np.mean(dM <= 0.03 * size):.4f}; "
              f"fused.ply within 2%: {np.mean(d <= 0.02 * size):.4f}, 3%: {np.mean(d <= 0.03 * size):.4f}")
    print(f"pairs: {c['pairs_done']} of {c['pairs']} ({report['execution']['workers']} workers), "
          f"{c['valid_matches']} dense matches; wall {wall:.1f} s "
          f"(report: {json.dumps(report['timings_s'])})")
    print(f"fused.ply: {n_fused} points ({counted_by}); within 1% of scene size: {np.mean(d <= 0.01 * size):.4f}, "
          f"0.5%: {np.mean(d <= 0.005 * size):.4f}, 0.1%: {np.mean(d <= 0.001 * size):.4f}; "
          f"median distance {np.median(d) / size * 100:.3f}% of scene size")
    print("database.db: %d cameras, %d images, %d keypoints, %d matches, %d inlier matches, %d verified pairs"
          % db_counts)
    print(f"sparse/: {rec.num_reg_images()} images, {rec.num_points3D()} points, mean reprojection error "
          f"{rec.compute_mean_reprojection_error():.3f} px, mean track length {rec.compute_mean_track_length():.2f}; "
          f"within 1%: {np.mean(dP <= 0.01 * size):.4f}, 0.5%: {np.mean(dP <= 0.005 * size):.4f}")
    # last: this run's row of the workspace table in docs/results.md
    print(f"| {a.seed} | {n_fused:,} | {np.mean(d <= 0.01 * size):.1%} / {np.mean(d <= 0.005 * size):.1%} | "
          f"{db_counts[2]:,} / {db_counts[3]:,} | {rec.num_points3D():,} | "
          f"{rec.compute_mean_reprojection_error():.2f} px | {np.mean(dP <= 0.01 * size):.1%} | {wall:.0f} s |")
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
