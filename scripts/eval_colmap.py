"""Measure `sefm-recon colmap` on a generated workspace with true poses, or on a real photo set.

    .venv/bin/python scripts/eval_colmap.py --seed 21 --width 1000 --height 750 --views 3 [--workers 2]
    .venv/bin/python scripts/eval_colmap.py --real fountain --data ../shared/data/multiview --images 8 --scale 0.5
    .venv/bin/python scripts/eval_colmap.py --real dino --data ../shared/data/multiview

Real sets (`--real`, see ../shared/data/multiview/README.md): the workspace is made from the
ground-truth cameras as a posed model without points (fountain-P11: the first `--images`
photos, downscaled by `--scale`; dinoSparseRing: all 16 views), the CLI runs on it with its
default of one worker per core unless `--workers` says otherwise (its peak memory is the summed
proportional set size of the run's processes: the CLI, the forkserver and the pair workers), and a table row is printed for fused.ply and for
every pair's points.ply: points, the share of points that agree with the matches of three or
more views (a view agrees when one of its pairs observed, within 1 px of the point's projection,
a depth within 1 % of the point's: each pair side's depths are kept apart, so a point's own pair
gives it two views), and for the dino the share inside the published bounding box and the share
that projects onto the object (the dataset's silhouette recipe: grey > 0.19, dilated 10 px,
eroded 7 px) in every view whose image it falls into.

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


def _write_model(dst: Path, entries) -> None:
    """A COLMAP text model with PINHOLE cameras, the given poses and no points."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    for i, (name, K, R, t, w, h) in enumerate(entries, start=1):
        rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=w, height=h, camera_id=i,
                                                        params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]]))
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=i, image_id=i),
                                         pycolmap.Rigid3d(np.hstack([R, np.reshape(t, (3, 1))])))
    (dst / "sparse").mkdir(parents=True, exist_ok=True)
    rec.write_text(str(dst / "sparse"))


def fountain_workspace(src: Path, dst: Path, n: int, scale: float) -> None:
    """fountain-P11's first ``n`` photos downscaled by ``scale`` (INTER_AREA), cameras from gt_dense_cameras."""
    import cv2

    from sefm_recon.io.cameras import read_strecha_camera

    (dst / "images").mkdir(parents=True, exist_ok=True)
    entries = []
    for name in sorted(p.name for p in (src / "images").glob("*.jpg"))[:n]:
        K, R, t, (W, H) = read_strecha_camera(src / "gt_dense_cameras" / f"{name}.camera")
        K[:2] *= scale
        w, h = int(round(W * scale)), int(round(H * scale))
        img = cv2.imread(str(src / "images" / name), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
        if (w, h) != (W, H):
            img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(dst / "images" / name), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
        entries.append((name, K, R, t, w, h))
    _write_model(dst, entries)


def dino_workspace(src: Path, dst: Path) -> None:
    import shutil

    import cv2

    (dst / "images").mkdir(parents=True, exist_ok=True)
    entries = []
    for line in (src / "dinoSR_par.txt").read_text().splitlines()[1:]:
        f = line.split()
        if not f:
            continue
        v = np.array(f[1:], float)
        K = v[:9].reshape(3, 3).copy()
        K[0, 2] += 0.5
        K[1, 2] += 0.5
        shutil.copy(src / f[0], dst / "images" / f[0])
        h, w = cv2.imread(str(src / f[0])).shape[:2]
        entries.append((f[0], K, v[9:18].reshape(3, 3), v[18:21], w, h))
    _write_model(dst, entries)


DINO_BOX = (np.array([-0.061897, -0.018874, -0.057845]), np.array([0.010897, 0.068227, 0.015495]))


def _silhouette(path: Path) -> np.ndarray:
    """The dataset's recipe: grey > 0.19, dilated by 10 px, eroded by 7 px."""
    import cv2

    grey = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255.0
    m = (grey > 0.19).astype(np.uint8)
    m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (21, 21)))
    return cv2.erode(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (15, 15))).astype(bool)


def _tree_pss(proc) -> int:
    """Summed proportional set size (bytes) of a process and its descendants (pool workers, forkserver)."""
    import psutil

    total = 0
    for p in [proc, *proc.children(recursive=True)]:
        try:
            total += p.memory_full_info().pss
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            pass
    return total


def run_cli(ws: Path, out: Path, workers: int | None, overrides: list[str]) -> tuple[int, float, float]:
    """``sefm-recon colmap ws -o out``: (exit status, wall seconds, peak summed PSS of the run's process tree in
    MB, sampled every 0.2 s); stderr on failure. ``workers=None``: the CLI's default (one per core)."""
    import psutil

    cmd = [sys.executable, "-m", "sefm_recon", "colmap", str(ws), "-o", str(out), "--overwrite", "-q"]
    if workers:
        cmd += ["--workers", str(workers)]
    for o in overrides:
        cmd += ["--set", o]
    t0 = time.perf_counter()
    with tempfile.TemporaryFile("w+") as log:  # a file, not a pipe: a chatty run cannot block on it
        r = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=log, text=True)
        proc, peak = psutil.Process(r.pid), 0
        while r.poll() is None:
            peak = max(peak, _tree_pss(proc))
            time.sleep(0.2)
        log.seek(0)
        err = log.read()
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        print(err, file=sys.stderr)
    return r.returncode, wall, peak / 2**20


def eval_real(a) -> int:
    """``--real``: build the workspace, run the CLI, print the table rows."""
    import pycolmap

    from sefm_recon.colmap_plugin import pose_of
    from sefm_recon.io.ply import iter_point_cloud
    from sefm_recon.reconstruct.fuse import FusionView, project

    data = Path(a.data)
    root = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="eval_colmap_"))
    ws, out = root / "ws", root / "out"
    if not (ws / "sparse").is_dir():
        if a.real == "fountain":
            fountain_workspace(data / "fountain-P11", ws, a.images, a.scale)
        else:
            dino_workspace(data / "dinoSparseRing", ws)
    wall = float("nan")
    peak_mb = float("nan")
    if not a.reuse:
        rc, wall, peak_mb = run_cli(ws, out, a.workers, a.overrides)
        if rc != 0:
            return rc
    report = json.loads((out / "report.json").read_text())
    rec = pycolmap.Reconstruction(str(ws / "sparse"))
    ids = sorted(rec.images)
    views = [FusionView(rec.images[i].camera, *pose_of(rec.images[i])) for i in ids]
    index = {rec.images[i].name: k for k, i in enumerate(ids)}
    pairs = [(e, index[e["images"][0]], index[e["images"][1]]) for e in report["pairs"] if e.get("status") == "ok"]
    # each pair side's depth map (float32, inf where that pair observed nothing)
    maps: dict[int, list[np.ndarray]] = {k: [] for k in range(len(views))}
    for e, i, j in pairs:
        xyz = np.concatenate([b[0] for b in iter_point_cloud(out / e["folder"] / "points.ply")])
        for v in (i, j):
            pix, z = project(views[v], xyz)
            m = np.full(views[v].width * views[v].height, np.inf, np.float32)
            ok = pix >= 0
            np.minimum.at(m, pix[ok], z[ok])
            maps[v].append(m)
    sil = [_silhouette(ws / "images" / rec.images[i].name) for i in ids] if a.real == "dino" else None

    def judge(xyz: np.ndarray) -> dict:
        agree = np.zeros(len(xyz), np.int64)
        on_object = np.ones(len(xyz), bool)
        for v, view in enumerate(views):
            pix, z = project(view, xyz)
            W, n = view.width, view.width * view.height
            ok = pix >= 0
            if sil is not None:
                on_object[ok] &= sil[v].reshape(-1)[pix[ok]]
            hit = np.zeros(len(xyz), bool)
            x, y = pix % W, pix // W
            for m in maps[v]:
                for dy in (-1, 0, 1):
                    for dx in (-1, 0, 1):
                        q = (y + dy) * W + (x + dx)
                        inside = ok & (x + dx >= 0) & (x + dx < W) & (q >= 0) & (q < n)
                        d = np.full(len(xyz), np.inf, np.float32)
                        d[inside] = m[q[inside]]
                        hit |= np.abs(d - z) <= 0.01 * z
            agree += hit
        out_ = {"points": len(xyz), "agree3": float(np.mean(agree >= 3)) if len(xyz) else 0.0}
        if sil is not None:
            out_["in_box"] = float(np.mean(np.all((xyz >= DINO_BOX[0]) & (xyz <= DINO_BOX[1]), 1)))
            out_["on_object"] = float(np.mean(on_object))
        return out_

    def row(label: str, res: dict, secs: str, mem: str) -> str:
        cells = [label, secs, mem, f"{res['points']:,}", f"{res['agree3']:.3f}"]
        if sil is not None:
            cells += [f"{res['in_box']:.3f}", f"{res['on_object']:.3f}"]
        return "| " + " | ".join(cells) + " |"

    chosen = len(pairs)
    print(f"{a.real}: {len(views)} views, {chosen} pairs chosen ({report['pair_selection']}), "
          f"{len(report.get('pair_candidates_dropped', []))} candidates dropped; wall {wall:.0f} s, "
          f"peak summed PSS {peak_mb:.0f} MB; timings {json.dumps(report['timings_s'])}; fusion {json.dumps(report['fusion'])}")
    head = "| cloud | time | peak memory | points | agree in >= 3 views |"
    if sil is not None:
        head += " in bounding box | on the object in every view |"
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    fused = np.concatenate([b[0] for b in iter_point_cloud(out / "fused.ply")])
    print(row(f"fused.ply ({chosen} pairs)", judge(fused), f"{wall:.0f} s", f"{peak_mb:.0f} MB"))
    for e, i, j in pairs:
        xyz = np.concatenate([b[0] for b in iter_point_cloud(out / e["folder"] / "points.ply")])
        print(row(f"pair {e['images'][0]} {e['images'][1]}", judge(xyz),
                  f"{e['timings_s'].get('total', float('nan')):.0f} s", "-"))
    return 0


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
    ap.add_argument("--real", choices=("fountain", "dino"), help="a real photo set (see the docstring)")
    ap.add_argument("--data", default="../shared/data/multiview", help="--real: the multiview data folder")
    ap.add_argument("--images", type=int, default=8, help="--real fountain: the first this many photos")
    ap.add_argument("--scale", type=float, default=0.5, help="--real fountain: downscaling of the photos")
    ap.add_argument("--reuse", action="store_true", help="--real with --keep: judge the outputs already there")
    a = ap.parse_args(argv)
    if a.real:
        return eval_real(a)

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
    rc, wall, peak_mb = run_cli(ws, out, a.workers, a.overrides)
    if rc != 0:
        return rc
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
          f"{c['valid_matches']} dense matches; wall {wall:.1f} s, peak summed PSS {peak_mb:.0f} MB "
          f"(report: {json.dumps(report['timings_s'])})")
    print(f"fused.ply: {n_fused} points ({counted_by}); within 1% of scene size: {np.mean(d <= 0.01 * size):.4f}, "
          f"0.5%: {np.mean(d <= 0.005 * size):.4f}, 0.1%: {np.mean(d <= 0.001 * size):.4f}; "
          f"median distance {np.median(d) / size * 100:.3f}% of scene size")
    print(f"fusion: {json.dumps(report['fusion'])}")
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
