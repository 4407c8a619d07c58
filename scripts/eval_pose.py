"""Errors of the SIFT pose against the true pose, with the true camera: the real pairs
with ground truth (all three variants) and the generated scenes.

    .venv/bin/python scripts/eval_pose.py [--real DIR] [--seeds 0 1 ...] [--refinement all|least-squares|none]

For each case the rotation angle and the translation direction angle (degrees) of the
pose the two-view stage returns, then their medians, means and largest values per set.
``--refinement`` stops the SIFT pose's refinement over its inliers
(``two_view.refine_on_inliers``) part way, for the table in docs/results.md:
``least-squares`` leaves out the rounds within 3 sigma of the lines
(``two_view.ROBUST_ROUNDS = 0``), ``none`` keeps RANSAC's pose.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

import sefm_recon.geometry.two_view as two_view
from sefm_recon.config import load_config
from sefm_recon.errors import InputError
from sefm_recon.eval_tables import MOTIONS, _cameras, generated_case, real_cases
from sefm_recon.geometry.refine import pose_change_deg
from sefm_recon.geometry.undistort import make_working_view
from sefm_recon.pipeline import two_view_stage

ROOT = Path(__file__).resolve().parents[1]


def pose_errors(cases, cfg) -> np.ndarray:
    """(N, 2) rotation and translation-direction errors in degrees; a refused case is printed and left out."""
    out = []
    for case in cases:
        c1, c2 = _cameras(case)
        v1 = make_working_view(case.img1, c1, cfg.output.max_size)
        v2 = make_working_view(case.img2, c2, cfg.output.max_size)
        try:
            tv = two_view_stage(v1, v2, cfg)[0]
        except InputError as e:
            print(f"{case.name} {case.variant}: refused: {e}")
            continue
        R, t = case.pose
        err = pose_change_deg(two_view.TwoView(tv.K1, tv.K2, R, t / np.linalg.norm(t)), tv)
        print(f"{case.name} {case.variant}: rotation {err[0]:.3f} deg, translation direction {err[1]:.3f} deg",
              flush=True)
        out.append(err)
    return np.array(out).reshape(-1, 2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--real", type=Path, default=ROOT.parent / "shared" / "data" / "real_gt")
    ap.add_argument("--seeds", type=int, nargs="*", default=list(range(20)))
    ap.add_argument("--refinement", choices=("all", "least-squares", "none"), default="all")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    if args.refinement == "least-squares":
        two_view.ROBUST_ROUNDS = 0
    elif args.refinement == "none":
        two_view.refine_on_inliers = lambda pose, *a: pose
    cfg = load_config(None, ["output.mesh=false", "output.progress=false"], internal=True)
    sets = []
    if args.real.is_dir():
        sets.append(("real", real_cases(str(args.real), ["rect", "unrect", "conv"], None)))
    else:
        print(f"{args.real}: not found, real pairs skipped")
    if args.seeds:
        sets.append(("generated", (generated_case(s, motion=MOTIONS[s % 4]) for s in args.seeds)))
    rows = []
    for name, cases in sets:
        e = pose_errors(cases, cfg)
        if len(e):
            rows.append(f"| {len(e)} {name} | {np.median(e[:, 0]):.3f} / {np.median(e[:, 1]):.3f} | "
                        f"{e[:, 0].mean():.3f} / {e[:, 1].mean():.3f} | {e[:, 1].max():.2f} |")
    print(f"\nSIFT pose, refinement: {args.refinement}; degrees, rotation / translation direction\n")
    print("| cases | median | mean | largest translation error |\n|---|---|---|---|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
