"""``sefm-recon eval``: the paper's Table 1 and an ablation table, on generated scenes.

Each scene is rendered from its seed (so the tables are reproducible anywhere),
matched by SeFM (true or estimated pose), and scored with
:func:`sefm_recon.evaluate.evaluate_matches` beside SIFT (the geometric inliers
the pose came from) and OpenCV StereoSGBM given the true rectification.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from .config import load_config
from .evaluate import covisibility_mask, evaluate_matches

logger = logging.getLogger(__name__)

#: Ablation rows: each removes (or, marked +, adds) one stage beyond the paper.
ABLATIONS: dict[str, list[str]] = {
    "SeFM, all stages (default)": [],
    "paper only (1-D lines, strict S_v, no extras)": [
        "lines.neighbours=0", "dense.both_directions=false", "dense.open_ends=false", "dense.fill_max_gap=0",
        "dense.subpixel=false", "validity.neighbour_tol_px=0", "validity.sv_max_unmatched=0", "pyramid.min_size=0",
        "dense.propagate_passes=0",
    ],
    "- coarse to fine (one level, SIFT depth band)": ["pyramid.min_size=0"],
    "- neighbour lines (1-D window)": ["lines.neighbours=0"],
    "- both directions": ["dense.both_directions=false"],
    "- open line ends": ["dense.open_ends=false"],
    "- gap filling": ["dense.fill_max_gap=0"],
    "- propagation across lines": ["dense.propagate_passes=0"],
    "- shifted propagation windows (depth edges)": ["dense.propagate_window_shift=0"],
    "- propagation from both sides of a depth edge": ["dense.propagate_split_slack=-1"],
    "- second propagation round (after a validation)": ["dense.propagate_rounds=1"],
    "- gap bridging (short gaps inside a surface interpolated)": ["dense.bridge_max_gap=0"],
    "- depth-edge rules (no fills across folds, no windows moved across steps)": [
        "dense.fill_max_scale=0", "dense.propagate_shift_max_step=0"],
    "- sub-pixel refinement": ["dense.subpixel=false"],
    "- stretched refinement window (slanted surfaces)": ["dense.subpixel_slope_radius=0"],
    "- sheared refinement window (depth changing across lines)": ["dense.subpixel_shear_radius=0"],
    "- refinement on 3 of the 5 lines (all 5)": ["dense.subpixel_neighbours=2"],
    "- 2-D neighbour check (and its median depth)": ["validity.neighbour_tol_px=0"],
    "- 2-D median depth": ["validity.median_depth=false"],
    "- S_p depth runs": ["validity.sp_min_run=1"],
    "strict S_v (paper)": ["validity.sv_max_unmatched=0"],
    "+ colour": ["lines.color=true"],
}

METRICS = ("precision@1", "precision@3", "coverage@1", "coverage@3")


def _scene(seed, size, noise):
    from .synthetic import render_scene

    scene = render_scene(seed=seed, width=size[0], height=size[1], noise_sigma=noise)
    v1, v2 = scene.views[:2]
    R = v2.R @ v1.R.T
    return v1, v2, (R, v2.t - R @ v1.t)


def _sefm(v1, v2, pose, overrides, cov):
    from .pipeline import reconstruct_pair

    cfg = load_config(None, ["output.mesh=false", "output.progress=false", *overrides])
    t0 = time.perf_counter()
    res = reconstruct_pair(v1.image, v2.image, v1.camera(1), v2.camera(2), cfg, pose=pose)
    seconds = time.perf_counter() - t0
    return res, {"seconds": seconds, **evaluate_matches(res.uv1, res.uv2, v1, v2, covisible=cov)}


def scene_table(seeds, size=(1000, 750), pose="true", noise=0.0, overrides=(), sgbm=True) -> list[dict]:
    """Per scene: SeFM, SIFT and StereoSGBM matches, precision and coverage (Table 1 of the paper)."""
    from .baselines import scene_depth_range, sgbm_matches

    rows = []
    for seed in seeds:
        v1, v2, true_pose = _scene(seed, size, noise)
        cov = covisibility_mask(v1, v2)
        res, m = _sefm(v1, v2, true_pose if pose == "true" else None, overrides, cov)
        rows.append({"seed": seed, "method": "SeFM", **m})
        rows.append({"seed": seed, "method": "SIFT", "seconds": float("nan"),
                     **evaluate_matches(res.sift_uv1, res.sift_uv2, v1, v2, covisible=cov)})
        if sgbm:
            t0 = time.perf_counter()
            s1, s2 = sgbm_matches(v1.image, v2.image, v1.K, v1.R, v1.t, v2.K, v2.R, v2.t,
                                  depth_range=scene_depth_range(v1, v2))
            rows.append({"seed": seed, "method": "SGBM", "seconds": time.perf_counter() - t0,
                         **evaluate_matches(s1, s2, v1, v2, covisible=cov)})
        logger.info("seed %d done", seed)
    return rows


def ablation_table(seeds, size=(1000, 750), pose="true", noise=0.0, overrides=()) -> list[dict]:
    """Mean metrics over the seeds with each stage switched off (or on) in turn."""
    scenes = [(_scene(seed, size, noise)) for seed in seeds]
    covs = [covisibility_mask(v1, v2) for v1, v2, _ in scenes]
    rows = []
    for name, extra in ABLATIONS.items():
        ms = [_sefm(v1, v2, p if pose == "true" else None, [*overrides, *extra], cov)[1]
              for (v1, v2, p), cov in zip(scenes, covs)]
        rows.append({"variant": name, "matches": float(np.mean([m["matches"] for m in ms])),
                     **{k: float(np.mean([m[k] for m in ms])) for k in METRICS},
                     "seconds": float(np.mean([m["seconds"] for m in ms]))})
        logger.info("ablation %s done", name)
    return rows


def format_scene_table(rows: list[dict]) -> str:
    lines = ["| scene (seed) | method | matches | precision@1px | precision@3px | coverage@1px | coverage@3px |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['seed']} | {r['method']} | {r['matches']:,} | " +
                     " | ".join(f"{r[k]:.3f}" for k in METRICS) + " |")
    return "\n".join(lines)


def format_ablation_table(rows: list[dict]) -> str:
    lines = ["| variant | matches | precision@1px | precision@3px | coverage@1px | coverage@3px |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['variant']} | {r['matches']:,.0f} | " + " | ".join(f"{r[k]:.3f}" for k in METRICS) + " |")
    return "\n".join(lines)
