"""``sefm-recon eval``: SeFM beside its peers on real pairs and on generated scenes.

Every pair is matched, in the same run, by four methods (:data:`METHODS`):

* ``SeFM (true pose)`` — the pipeline given the true relative pose;
* ``SeFM (own pose)`` — the pipeline estimating the pose itself, as ``pair`` does with
  the true camera;
* ``SGBM`` — OpenCV StereoSGBM on the true rectification (:func:`baselines.sgbm_matches`;
  SGBM_3WAY, block 5, P1 = 8·3·25, P2 = 32·3·25, uniqueness 10, speckle 100/2,
  disp12MaxDiff 1), searching the disparities the ground truth needs ± :data:`SGBM_MARGIN_PX`;
  it cannot run where an epipole lies inside an image (forward motion, zoom);
* ``DIS`` — OpenCV DIS optical flow (PRESET_MEDIUM on grey images), forward and backward,
  kept where they agree within 1 px (:func:`baselines.dis_matches`).

A method that fails scores 0 and its row says why. Scoring is
:func:`sefm_recon.evaluate.score_matches` (precision: matches on occluded pixels are
wrong; coverage: share of co-visible pixels of image 1 holding a correct match).
On real pairs, matches on pixels whose ground truth is unknown are left out (neither
right nor wrong), as Middlebury's own evaluation does.

Real pairs: ``../shared/data/real_gt`` in three variants (:mod:`sefm_recon.realgt`).
Generated scenes: :func:`sefm_recon.synthetic.render_scene`'s randomised style, the
motion kinds in turn.
"""

from __future__ import annotations

import logging
import re
import time
from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np

from .config import load_config
from .errors import InputError
from .evaluate import covisibility_mask, pixel_index, score_matches, true_correspondences

logger = logging.getLogger(__name__)

METHODS = ("SeFM (true pose)", "SeFM (own pose)", "SGBM", "DIS")
METRICS = ("precision@1", "precision@3", "coverage@1", "coverage@3")
#: The issue's peer protocol: SGBM searches the ground truth's disparity range ± 8 px.
SGBM_MARGIN_PX = 8.0
#: Motion kinds of the generated table, taken in turn by the seed's number (:func:`seed_motion`).
MOTIONS = ("lateral", "converging", "forward", "zoom")

#: Ablation rows of the default matcher (``dense.method = "sgm"``): each switches one stage
#: off, or back to the simpler choice in brackets.
SGM_ABLATIONS: dict[str, list[str]] = {
    "SGM over polar line images, all stages (default)": [],
    "- 4 full aggregation paths (OpenCV's 3 directions)": ["sgm.full_paths=false"],
    "- estimates that SGM at half size, sure there, contradicts dropped": ["sgm.half_check=false"],
    "- cells left without an estimate filled by SGM at half size": ["sgm.half_fill=false"],
    "- left-right check (SGM from image 2 at half size)": ["sgm.lr_check=false"],
    "- uniqueness test": ["sgm.uniqueness=0"],
    "- jump penalty chosen per pair (OpenCV's 32)": ["sgm.jump_penalty=32"],
    "- speckle filter": ["sgm.speckle=false"],
    "- speckle window a share of the view (100 px alone)": ["sgm.speckle_share=false"],
    "- search range from the SIFT parallax (their depths x2 and /2)": ["sgm.sift_range=false"],
    "+ range margin of a quarter span (8 columns alone)": ["sgm.range_margin=0.25"],
    "- image 2's tones matched to image 1's": ["sgm.tone_match=false"],
    "- range extended towards the camera by a coarse pass": ["sgm.near_range=false"],
    "- estimates at the near end without a coarse surface there dropped": ["sgm.near_check=false"],
    "- estimates far from the coarse pass's, where that is sure, dropped": ["sgm.coarse_check=false"],
    "- estimates on texture repeating along the lines, on surfaces without other texture, dropped":
        ["sgm.repeat_check=false"],
    "- estimates at the far end of cells image 2 sees at no nearer parallax dropped": ["sgm.far_check=false"],
    "- far end estimates on surfaces image 2 sees nowhere at every parallax dropped": ["sgm.far_surface_check=false"],
    "- estimates at the ends of the search dropped": ["sgm.end_check=false"],
    "- estimates whose window reaches into an area of one value dropped": ["sgm.flat_check=false"],
    "- estimates whose window in image 2 reaches beyond it dropped": ["sgm.outside_check=false"],
    "- runs matching image 1's edge to image 2's beyond a nearer surface's occlusion dropped":
        ["sgm.frame_check=false"],
    "- the nearer surface's cell at each depth edge dropped": ["sgm.edge_check=false"],
    "- of two surfaces reaching one pixel of image 2, the one whose colour differs dropped": ["sgm.collision_check=false"],
    "- plain cells a nearer surface carries into an unmatched region dropped": ["sgm.occlusion_check=false"],
    "- plain cells a nearer surface carries across a depth jump dropped": ["sgm.carried_check=false"],
    "- bicubic line images (bilinear)": ["sgm.bicubic=false"],
    "- interpolated read-back at each pixel (nearest cell)": ["sgm.interpolate=false"],
    "- median over each surface": ["sgm.median=false"],
    "- median about the window's plane where it lies on one (the plain median)": ["sgm.slanted_median=false"],
    "- plane fit on plain windows": ["sgm.plain_fit=false"],
    "- wide plane fit on plain windows": ["sgm.wide_fit=false"],
    "- holes of plain planes filled": ["sgm.planes=false"],
    "- matches without signal on plain planes moved onto them": ["sgm.plane_snap=false"],
    "- matches of plain regions mostly unmatched and on no one plane dropped": ["sgm.scattered_check=false"],
    "- a plane aligned by the intensities kept there where its halves agree": ["sgm.aligned_planes=false"],
    "- small plain regions on the plane of their rim": ["sgm.rim_planes=false"],
    "- plain regions with no surface of their own filled from another region's aligned plane":
        ["sgm.borrowed_planes=false"],
    "- a second surface beside a plain region's aligned plane kept apart from it": ["sgm.two_surfaces=false"],
    "- islands the checks leave under the speckle window dropped": ["sgm.speckle_after=false"],
    "- matches a period off the largest aligned planes moved onto them": ["sgm.dominant_planes=false"],
    "- estimates on repeating texture given back on those planes": ["sgm.repeat_restore=false"],
    "- estimates the left-right check dropped on repeating texture given back there": ["sgm.lr_restore=false"],
}

#: Ablation rows of the sequential DP: each removes (or, marked +, adds) one stage beyond the paper.
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


@dataclass
class GeneratedCase:
    """A rendered pair in the shape of :class:`sefm_recon.realgt.StereoCase`."""

    name: str
    variant: str  # the motion kind
    view1: object  # SyntheticView
    view2: object

    def __post_init__(self):
        for k, v in (("1", self.view1), ("2", self.view2)):
            setattr(self, "img" + k, v.image)
            setattr(self, "K" + k, v.K)
            setattr(self, "R" + k, v.R)
            setattr(self, "t" + k, v.t)

    @property
    def pose(self):
        R = self.view2.R @ self.view1.R.T
        return R, self.view2.t - R @ self.view1.t

    def truth(self, uv1):
        return true_correspondences(self.view1, self.view2, uv1)

    def covisible(self):
        return covisibility_mask(self.view1, self.view2)

    def judged(self):
        return np.ones(self.view1.depth.shape, bool)

    def depth_range(self):
        from .baselines import scene_depth_range

        return scene_depth_range(self.view1, self.view2, margin=0.0)


def seed_motion(seed: int) -> str:
    """The motion kind generated scene ``seed`` is evaluated with: the kinds of :data:`MOTIONS`
    in turn by the seed's number, so that a seed is the same scene run alone as in any list."""
    return MOTIONS[seed % len(MOTIONS)]


def generated_case(seed: int, size=(1000, 750), motion: str | None = None, style: str = "random") -> GeneratedCase:
    """Render scene ``seed`` (two views) as an evaluation case; random style: with ``motion``,
    by default the seed's own (:func:`seed_motion`)."""
    from .synthetic import render_scene

    kw = {"motion": motion or seed_motion(seed)} if style == "random" else {}
    scene = render_scene(seed=seed, width=size[0], height=size[1], style=style, **kw)
    kind = scene.meta.get("options", {}).get("motion", "classic") if style == "random" else "classic"
    return GeneratedCase(str(seed), kind, scene.views[0], scene.views[1])


def generated_cases(seeds, size=(1000, 750), style: str = "random"):
    """:func:`generated_case` of each seed, each with its motion kind (random style)."""
    for seed in seeds:
        yield generated_case(seed, size, style=style)


def _cameras(case):
    from .io.cameras import pinhole_camera

    cams = []
    for i, (K, img) in enumerate(((case.K1, case.img1), (case.K2, case.img2)), start=1):
        cam = pinhole_camera(K, img.shape[1], img.shape[0], i)
        cam.has_prior_focal_length = True  # the true camera, as if given with --camera
        cams.append(cam)
    return cams


def _sefm(case, overrides: Iterable[str], own_pose: bool):
    from .pipeline import reconstruct_pair

    cfg = load_config(None, ["output.mesh=false", "output.progress=false", *overrides], internal=True)
    cam1, cam2 = _cameras(case)
    res = reconstruct_pair(case.img1, case.img2, cam1, cam2, cfg, pose=None if own_pose else case.pose)
    return res.uv1, res.uv2


def _sgbm(case):
    from .baselines import epipoles_inside, sgbm_matches

    sizes = [(img.shape[1], img.shape[0]) for img in (case.img1, case.img2)]
    if epipoles_inside(case.K1, case.R1, case.t1, case.K2, case.R2, case.t2, *sizes):
        raise InputError("fails: an epipole lies inside the image, no planar rectification")
    return sgbm_matches(case.img1, case.img2, case.K1, case.R1, case.t1, case.K2, case.R2, case.t2,
                        depth_range=case.depth_range(), margin_px=SGBM_MARGIN_PX)


def _dis(case):
    from .baselines import dis_matches

    return dis_matches(case.img1, case.img2)


def method_runners(overrides: Iterable[str] = ()) -> dict[str, Callable]:
    """Method name -> function of a case returning ``(uv1, uv2)``."""
    overrides = list(overrides)
    return {
        "SeFM (true pose)": lambda c: _sefm(c, overrides, own_pose=False),
        "SeFM (own pose)": lambda c: _sefm(c, overrides, own_pose=True),
        "SGBM": _sgbm,
        "DIS": _dis,
    }


def score_case(case, uv1, uv2, covisible=None) -> dict:
    """Score matches of a case; matches on pixels without ground truth are left out."""
    uv1 = np.asarray(uv1, np.float64).reshape(-1, 2)
    uv2 = np.asarray(uv2, np.float64).reshape(-1, 2)
    judged = case.judged()
    keep = judged[pixel_index(uv1, judged.shape)]
    cov = case.covisible() if covisible is None else covisible
    return score_matches(uv1[keep], uv2[keep], case.truth, cov)


def run_case(case, methods: Iterable[str] = METHODS, overrides: Iterable[str] = ()) -> list[dict]:
    """One row per method: matches, precision and coverage at 1 and 3 px, seconds, note."""
    runners = method_runners(overrides)
    cov = case.covisible()
    rows = []
    for name in methods:
        t0 = time.perf_counter()
        note = ""
        try:
            uv1, uv2 = runners[name](case)
        except InputError as err:  # the method refused or cannot run: it scores 0
            uv1 = uv2 = np.zeros((0, 2))
            note = str(err) if name == "SGBM" else "refused: " + re.split(r"; | \(", str(err))[0]
        seconds = time.perf_counter() - t0
        m = score_case(case, uv1, uv2, cov)
        rows.append({"pair": case.name, "variant": case.variant, "method": name, "matches": len(uv1),
                     **{k: m[k] for k in METRICS}, "seconds": seconds, "note": note})
        logger.debug("%s %s %s: %d matches, p@1 %.3f cov@1 %.3f", case.name, case.variant, name, len(uv1),
                     m["precision@1"], m["coverage@1"])
    return rows


def _real_folders(root, pairs=None) -> list:
    """The real pair folders under ``root`` (only those named in ``pairs``, all of them present)."""
    from .io.real_gt import list_pairs

    folders = list_pairs(root)
    if pairs:
        wanted = set(pairs)
        folders = [f for f in folders if f.name in wanted]
        missing = wanted - {f.name for f in folders}
        if missing:
            raise InputError(f"no such pair in {root}: {', '.join(sorted(missing))}")
    return folders


def _pair_cases(folder, variants=None):
    """The cases of one real pair folder, one per variant."""
    from .io.real_gt import load_pair
    from .realgt import VARIANTS, make_case

    pair = load_pair(folder)
    return [make_case(pair, variant) for variant in variants or VARIANTS]


def real_table(root, variants=None, pairs=None, methods: Iterable[str] = METHODS,
               overrides: Iterable[str] = ()) -> list[dict]:
    """Rows of :func:`run_case` for every real pair under ``root`` in every variant."""
    folders = _real_folders(root, pairs)
    rows = []
    for k, folder in enumerate(folders, 1):
        for case in _pair_cases(folder, variants):
            rows += run_case(case, methods, overrides)
        logger.info("[%d/%d] %s done", k, len(folders), folder.name)
    return rows


def real_cases(root, variants=None, pairs=None):
    """Every real pair under ``root`` in every variant, as cases (read one pair at a time)."""
    for folder in _real_folders(root, pairs):
        yield from _pair_cases(folder, variants)


def generated_table(seeds, size=(1000, 750), methods: Iterable[str] = METHODS, overrides: Iterable[str] = (),
                    style: str = "random") -> list[dict]:
    """Rows of :func:`run_case` for generated scenes; the motion kinds are taken in turn."""
    rows = []
    for k, case in enumerate(generated_cases(seeds, size, style), 1):
        rows += run_case(case, methods, overrides)
        logger.info("[%d/%d] seed %s (%s) done", k, len(seeds), case.name, case.variant)
    return rows


def means(rows: list[dict]) -> list[dict]:
    """Mean of every metric per (variant, method), failures counted as 0, in first-seen order."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["variant"], r["method"]), []).append(r)
    out = []
    for (variant, method), rs in groups.items():
        out.append({"variant": variant, "method": method, "pairs": len(rs),
                    "failed": sum(1 for r in rs if r["note"]),
                    "matches": float(np.mean([r["matches"] for r in rs])),
                    **{k: float(np.mean([r[k] for r in rs])) for k in METRICS},
                    "seconds": float(np.mean([r["seconds"] for r in rs]))})
    return out


_HEAD = "| precision@1px | precision@3px | coverage@1px | coverage@3px | seconds |"


def format_means(rows: list[dict], what: str = "variant") -> str:
    """Markdown table of :func:`means`."""
    lines = [f"| {what} | method | pairs | matches {_HEAD} failed |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in means(rows):
        lines.append(f"| {r['variant']} | {r['method']} | {r['pairs']} | {r['matches']:,.0f} | "
                     + " | ".join(f"{r[k]:.3f}" for k in METRICS) + f" | {r['seconds']:.2f} | {r['failed']} |")
    return "\n".join(lines)


def format_summary(rows: list[dict]) -> str:
    """Compact Markdown table: per variant, each method's precision / coverage at 1 px."""
    ms = means(rows)
    methods = list(dict.fromkeys(r["method"] for r in ms))
    lines = ["| variant | " + " | ".join(f"{m} p@1 / cov@1" for m in methods) + " |",
             "|---|" + "---|" * len(methods)]
    for variant in dict.fromkeys(r["variant"] for r in ms):
        cells = {r["method"]: f"{r['precision@1']:.3f} / {r['coverage@1']:.3f}" for r in ms if r["variant"] == variant}
        lines.append(f"| {variant} | " + " | ".join(cells.get(m, "") for m in methods) + " |")
    return "\n".join(lines)


def format_rows(rows: list[dict], what: str = "pair") -> str:
    """Markdown table, one row per pair, variant and method."""
    lines = [f"| {what} | variant | method | matches {_HEAD} note |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        note = r["note"].replace("|", "/")
        lines.append(f"| {r['pair']} | {r['variant']} | {r['method']} | {r['matches']:,} | "
                     + " | ".join(f"{r[k]:.3f}" for k in METRICS) + f" | {r['seconds']:.2f} | {note} |")
    return "\n".join(lines)


def ablation_table(cases, pose="true", overrides=(), peers: bool = True) -> list[dict]:
    """Mean metrics of SeFM over ``cases`` with each stage switched off (or on) in turn:
    the default matcher's stages (:data:`SGM_ABLATIONS`), or the DP's (:data:`ABLATIONS`)
    when ``overrides`` select it; then, with ``peers``, StereoSGBM and DIS on the same cases."""
    cases = list(cases)
    covs = [c.covisible() for c in cases]
    method = load_config(None, list(overrides), internal=True).dense.method
    runs = {name: (lambda c, extra=extra: _sefm(c, [*overrides, *extra], own_pose=pose != "true"))
            for name, extra in (SGM_ABLATIONS if method == "sgm" else ABLATIONS).items()}
    if peers:
        runs |= {"StereoSGBM (true rectification, the peer)": _sgbm, "DIS optical flow (the peer)": _dis}
    rows = []
    for name, run in runs.items():
        ms = []
        for case, cov in zip(cases, covs):
            t0 = time.perf_counter()
            try:
                uv1, uv2 = run(case)
            except InputError:
                uv1 = uv2 = np.zeros((0, 2))
            ms.append({**score_case(case, uv1, uv2, cov), "seconds": time.perf_counter() - t0})
        rows.append({"variant": name, "matches": float(np.mean([m["matches"] for m in ms])),
                     **{k: float(np.mean([m[k] for m in ms])) for k in METRICS},
                     "seconds": float(np.mean([m["seconds"] for m in ms]))})
        logger.info("ablation %s done", name)
    return rows


def format_ablation_table(rows: list[dict]) -> str:
    lines = ["| variant | matches | precision@1px | precision@3px | coverage@1px | coverage@3px |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['variant']} | {r['matches']:,.0f} | " + " | ".join(f"{r[k]:.3f}" for k in METRICS) + " |")
    return "\n".join(lines)


def warm_up() -> None:
    """Compile (or load) SeFM's kernels on a small scene, so that no row's time includes it."""
    case = generated_case(0, (320, 240), style="classic")
    _sefm(case, (), own_pose=False)
