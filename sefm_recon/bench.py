"""``sefm-recon bench``: SeFM against StereoSGBM on one generated pair, timed, in one process.

The pair is rendered with ground truth (default 2000x1500). SeFM runs the way
``sefm-recon pair --camera`` does (estimated pose, every stage including the
output files, written to a temporary folder); StereoSGBM gets the true
rectification and the disparity range the scene needs. Each is run ``repeat``
times and the last run is reported (numba's caches and the OS file cache are
warm by then). Peak memory is the process's resident-set high-water mark,
reset before each method (Linux ``/proc/self/clear_refs``), so it includes the
images and everything held at the time. The report names the libraries' versions
(:func:`.versions.library_versions`): OpenCV's release alone moves some scenes' figures.
"""

from __future__ import annotations

import json
import logging
import tempfile
import time
from pathlib import Path

from .versions import format_versions, library_versions

logger = logging.getLogger(__name__)

#: Stages counted as "matching" for the SeFM/SGBM comparison: what replaces SGBM (coarse: the reduced-size level).
MATCHING_STAGES = ("coarse", "line_pairs", "matching", "validity", "propagate")


def reset_peak_memory() -> bool:
    """Reset the kernel's peak-RSS counter of this process (Linux); False where unsupported.

    Freed memory the allocator keeps for reuse (see :mod:`sefm_recon.memory`)
    is returned first, so the next method's peak is its own.
    """
    from .memory import release_freed_memory

    release_freed_memory()
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def peak_memory_mb() -> float:
    """Peak resident set size of this process since the last reset, MiB."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_sefm(v1, v2, cfg, write: bool = True) -> tuple[dict, dict]:
    """One timed SeFM run (as ``sefm-recon pair --camera``); returns (timings, counts) and the matches."""
    from .pipeline import reconstruct_pair, write_pair_outputs

    cam1, cam2 = v1.camera(1), v2.camera(2)
    cam1.has_prior_focal_length = cam2.has_prior_focal_length = True  # the true cameras, as --camera gives them
    reset_peak_memory()
    t0 = time.perf_counter()
    res = reconstruct_pair(v1.image, v2.image, cam1, cam2, cfg)
    if write:
        with tempfile.TemporaryDirectory() as tmp:
            write_pair_outputs(res, cfg, Path(tmp), (v1.name, v2.name))
    wall = time.perf_counter() - t0
    stages = {k: round(v, 3) for k, v in res.timings.items()}
    return {"wall_s": round(wall, 3), "stages_s": stages, "peak_mb": round(peak_memory_mb(), 1),
            "matching_s": round(sum(res.timings.get(k, 0.0) for k in MATCHING_STAGES), 3)}, res


def run_sgbm(v1, v2) -> tuple[dict, tuple]:
    from .baselines import scene_depth_range, sgbm_matches

    reset_peak_memory()
    t0 = time.perf_counter()
    uv = sgbm_matches(v1.image, v2.image, v1.K, v1.R, v1.t, v2.K, v2.R, v2.t,
                      depth_range=scene_depth_range(v1, v2))
    wall = time.perf_counter() - t0
    return {"wall_s": round(wall, 3), "peak_mb": round(peak_memory_mb(), 1)}, uv


def bench(size=(2000, 1500), seed: int = 7, repeat: int = 2, overrides=(), write: bool = True) -> dict:
    """Time SeFM and StereoSGBM on one rendered pair; returns the report of the last repeat."""
    from .config import load_config
    from .evaluate import covisibility_mask, evaluate_matches
    from .synthetic import render_scene

    cfg = load_config(None, ["output.progress=false", *overrides], internal=True)
    t0 = time.perf_counter()
    scene = render_scene(seed=seed, width=size[0], height=size[1], style="classic")
    v1, v2 = scene.views[:2]
    logger.info("rendered %dx%d pair (seed %d) in %.1f s", size[0], size[1], seed, time.perf_counter() - t0)
    cov = covisibility_mask(v1, v2)
    report: dict = {"size": list(size), "seed": seed, "repeat": repeat, "config_overrides": list(overrides),
                    "libraries": library_versions()}
    for rep in range(repeat):
        # each method's results are scored and let go before the next run, so that no run's
        # peak memory holds another's
        last = rep == repeat - 1
        sefm, res = run_sefm(v1, v2, cfg, write)
        if last:
            sefm.update(evaluate_matches(res.uv1, res.uv2, v1, v2, covisible=cov))
        res = None
        sgbm, (s1, s2) = run_sgbm(v1, v2)
        if last:
            sgbm.update(evaluate_matches(s1, s2, v1, v2, covisible=cov))
        s1 = s2 = None
        logger.info("run %d: SeFM %.2f s, SGBM %.2f s", rep + 1, sefm["wall_s"], sgbm["wall_s"])
    report["sefm"] = sefm
    report["sgbm"] = sgbm
    report["ratio_matching_to_sgbm"] = round(sefm["matching_s"] / max(sgbm["wall_s"], 1e-9), 3)
    report["ratio_wall_to_sgbm"] = round(sefm["wall_s"] / max(sgbm["wall_s"], 1e-9), 3)
    return report


def format_report(r: dict) -> str:
    w, h = r["size"]
    s, g = r["sefm"], r["sgbm"]
    rows = [
        f"sefm-recon bench: {w}x{h} generated pair (seed {r['seed']}), run {r['repeat']} of {r['repeat']} reported",
        format_versions(r["libraries"]),
        "",
        f"{'':10} {'wall s':>8} {'matches':>9} {'p@1':>6} {'p@3':>6} {'cov@1':>6} {'cov@3':>6} {'peak MB':>8}",
    ]
    for name, m in (("SeFM", s), ("SGBM", g)):
        rows.append(f"{name:10} {m['wall_s']:8.2f} {m['matches']:9d} {m['precision@1']:6.3f} {m['precision@3']:6.3f} "
                    f"{m['coverage@1']:6.3f} {m['coverage@3']:6.3f} {m['peak_mb']:8.0f}")
    rows.append("")
    rows.append("SeFM stages (s): " + ", ".join(f"{k} {v:.2f}" for k, v in s["stages_s"].items()))
    rows.append(f"SeFM matching stages ({' + '.join(MATCHING_STAGES)}): {s['matching_s']:.2f} s")
    rows.append(f"time ratio SeFM/SGBM: matching stages {r['ratio_matching_to_sgbm']:.2f}x, "
                f"whole pipeline {r['ratio_wall_to_sgbm']:.2f}x")
    return "\n".join(rows)


def scaling(sizes, seed: int = 7, overrides=()) -> list[dict]:
    """Per-stage time and peak memory of SeFM at several sizes (second run of each), no downscaling."""
    from .config import load_config
    from .synthetic import render_scene

    cfg = load_config(None, ["output.progress=false", "output.max_size=0", *overrides], internal=True)
    rows = []
    for w, h in sizes:
        scene = render_scene(seed=seed, width=w, height=h, style="classic")
        v1, v2 = scene.views[:2]
        for _ in range(2):
            res = None  # (the first run's results are not part of the second's peak memory)
            out, res = run_sefm(v1, v2, cfg, write=True)
        rows.append({"size": [w, h], "megapixels": w * h / 1e6, **out, "matches": int(len(res.uv1))})
        logger.info("%dx%d: %.2f s", w, h, out["wall_s"])
    return rows


def format_scaling(rows: list[dict]) -> str:
    stages = []
    for r in rows:
        for k in r["stages_s"]:
            if k not in stages:
                stages.append(k)
    head = "| size | Mpx | matches | " + " | ".join(f"{k} s" for k in stages) + " | wall s | s per Mpx | peak MB |"
    lines = [head, "|" + "---|" * (len(stages) + 6)]
    for r in rows:
        lines.append(f"| {r['size'][0]}x{r['size'][1]} | {r['megapixels']:.2f} | {r['matches']:,} | " +
                     " | ".join(f"{r['stages_s'].get(k, 0):.2f}" for k in stages) +
                     f" | {r['wall_s']:.2f} | {r['wall_s'] / r['megapixels']:.2f} | {r['peak_mb']:.0f} |")
    return "\n".join(lines)


def dump(report, path) -> None:
    Path(path).write_text(json.dumps(report, indent=1, default=float))

