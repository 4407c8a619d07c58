"""Relative pose and epipolar accuracy on the ScanNet pairs of ../shared/data/real/scannet.

    .venv/bin/python scripts/eval_scannet.py [--pose estimated|true] [--json out.json] [--two-view-only]

For each pair: the relative pose error (rotation angle, translation direction
angle) of the estimated two-view geometry against the truth, and for the dense
SeFM matches the distance from the TRUE epipolar line (median, share within
1 px and 2 px) and how many there are. ``--two-view-only`` stops after the
SIFT pose (accepted pairs and pose errors in seconds, no dense matching), and counts
the putative SIFT matches within 2 px of the true epipolar lines. Intrinsics in pairs_with_gt.txt use the
OpenCV convention; 0.5 is added to cx, cy for COLMAP's.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

from sefm_recon.config import load_config
from sefm_recon.errors import InputError
from sefm_recon.geometry.refine import pose_change_deg
from sefm_recon.geometry.two_view import TwoView, epipolar_distances
from sefm_recon.geometry.undistort import make_working_view
from sefm_recon.io.cameras import pinhole_camera
from sefm_recon.io.images import read_image
from sefm_recon.pipeline import reconstruct_pair, two_view_stage

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "real" / "scannet"


def read_pairs(folder: Path):
    for line in (folder / "pairs_with_gt.txt").read_text().splitlines():
        f = line.split()
        if len(f) < 38:
            continue
        K0 = np.array(f[4:13], float).reshape(3, 3)
        K1 = np.array(f[13:22], float).reshape(3, 3)
        T = np.array(f[22:38], float).reshape(4, 4)
        for K in (K0, K1):
            K[0, 2] += 0.5
            K[1, 2] += 0.5
        yield f[0], f[1], K0, K1, T[:3, :3], T[:3, 3]


def two_view_only(img0, img1, cam0, cam1, cfg):
    """The pipeline's SIFT pose stage alone (:func:`sefm_recon.pipeline.two_view_stage`)."""
    v0 = make_working_view(img0, cam0, cfg.output.max_size)
    v1 = make_working_view(img1, cam1, cfg.output.max_size)
    return two_view_stage(v0, v1, cfg)[0]


def putative_on_true_lines(img0, img1, F, cfg, max_px: float = 2.0) -> tuple[int, int]:
    """(putative SIFT matches, how many of them lie within ``max_px`` of the true epipolar
    lines): whether there is a right pose among the matches for RANSAC to find."""
    from sefm_recon.geometry.two_view import sift_correspondences
    from sefm_recon.io.images import to_gray

    xy0, xy1 = sift_correspondences(to_gray(img0), to_gray(img1), cfg.sift.max_features, cfg.sift.max_ratio,
                                    max_size=cfg.sift.max_image_size, upsample_max_size=cfg.sift.upsample_max_size)
    return len(xy0), int(np.count_nonzero(epipolar_distances(F, xy0, xy1) <= max_px))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pose", choices=["estimated", "true"], default="estimated")
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--two-view-only", action="store_true", help="stop after the SIFT pose")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    cfg = load_config(None, ["output.mesh=false", *args.overrides], internal=True)
    rows = []
    for n0, n1, K0, K1, R, t in read_pairs(args.data):
        img0, img1 = read_image(args.data / n0), read_image(args.data / n1)
        cam0 = pinhole_camera(K0, img0.shape[1], img0.shape[0], 1)
        cam0.has_prior_focal_length = True  # the true camera, as if given with --camera
        cam1 = pinhole_camera(K1, img1.shape[1], img1.shape[0], 2)
        cam1.has_prior_focal_length = True
        row = {"pair": f"{n0} {n1}"}
        if args.two_view_only:
            row["putative"], row["putative_on_true_lines"] = putative_on_true_lines(img0, img1, TwoView(K0, K1, R, t).F,
                                                                                    cfg)
            print(f"{n0[:22]:22s} {n1[-10:]:10s}  {row['putative_on_true_lines']} of {row['putative']} putative "
                  "SIFT matches within 2 px of the true epipolar lines")
            t0 = time.perf_counter()
            try:
                tv = two_view_only(img0, img1, cam0, cam1, cfg)
            except InputError as err:
                row["error"] = str(err)
                print(f"{n0[:22]:22s} {n1[-10:]:10s}  failed ({time.perf_counter() - t0:.1f} s): {err}")
            else:
                row["seconds"] = round(time.perf_counter() - t0, 2)
                row["rot_err_deg"], row["trans_err_deg"] = pose_change_deg(TwoView(K0, K1, R, t), tv)
                row["sift_inliers"] = int(len(tv.kp1))
                print(f"{n0[:22]:22s} {n1[-10:]:10s}  R {row['rot_err_deg']:6.2f} deg  t {row['trans_err_deg']:6.2f} deg"
                      f"  {row['sift_inliers']} inliers of {tv.num_sift_matches} ({row['seconds']:.1f} s)")
            rows.append(row)
            continue
        try:
            res = reconstruct_pair(img0, img1, cam0, cam1, cfg, pose=(R, t) if args.pose == "true" else None)
        except InputError as err:
            row["error"] = str(err)
            rows.append(row)
            print(f"{n0[:22]:22s} {n1[-10:]:10s}  failed: {err}")
            continue
        true = TwoView(K0, K1, R, t)
        row["rot_err_deg"], row["trans_err_deg"] = pose_change_deg(true, TwoView(K0, K1, res.R, res.t))
        F = true.F
        d = epipolar_distances(F, res.uv1, res.uv2)
        row.update(matches=int(len(d)), epi_median_px=float(np.median(d)) if len(d) else None,
                   epi_within_1px=float(np.mean(d <= 1)) if len(d) else None,
                   epi_within_2px=float(np.mean(d <= 2)) if len(d) else None,
                   sift_inliers=res.counts["sift_inliers"])
        rows.append(row)
        print(f"{n0[:22]:22s} {n1[-10:]:10s}  R {row['rot_err_deg']:6.2f} deg  t {row['trans_err_deg']:6.2f} deg  "
              f"{row['matches']:7d} matches  epipolar median {row['epi_median_px'] or 0:.2f} px, "
              f"<=1px {row['epi_within_1px'] or 0:.2f}")
    ok = [r for r in rows if "error" not in r]
    if ok and args.two_view_only:
        print(json.dumps({"pairs": len(rows), "accepted": len(ok),
                          "over_5_deg": sum(max(r["rot_err_deg"], r["trans_err_deg"]) > 5 for r in ok)}))
    elif ok:
        summary = {
            "pairs": len(rows), "failed": len(rows) - len(ok),
            "rot_err_deg_median": float(np.median([r["rot_err_deg"] for r in ok])),
            "trans_err_deg_median": float(np.median([r["trans_err_deg"] for r in ok])),
            "matches_median": float(np.median([r["matches"] for r in ok])),
            "epi_median_px_median": float(np.median([r["epi_median_px"] for r in ok if r["epi_median_px"] is not None])),
        }
        print(json.dumps(summary))
        if args.json:
            args.json.write_text(json.dumps({"pose": args.pose, "rows": rows, "summary": summary}, indent=1))


if __name__ == "__main__":
    main()
