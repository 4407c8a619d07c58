"""``sefm-recon colmap``: dense SeFM reconstruction of a COLMAP workspace.

A workspace is ``images/`` and a sparse model (``sparse/`` or ``sparse/0``,
binary or text) whose cameras and poses are used as given. The steps:

1. **read** the model with pycolmap (:func:`open_workspace`);
2. **pairs**: from ``--pairs``, else the images that share enough sparse points
   (each image with its best ``colmap.pairs_per_image`` partners), else, in a
   model without (enough) points, from the poses: viewing-direction angle,
   triangulation angle and distance (:func:`select_pairs`, :func:`pose_pairs`);
   pairs without enough baseline are skipped with a logged reason;
3. **per pair** (:func:`run_pair_task`, on a process pool or a Dask cluster):
   :func:`~sefm_recon.pipeline.reconstruct_pair` with the known relative pose;
   its points are moved into the world frame;
4. **fuse** every pair's points, read back from ``pairs/`` in blocks: each posed
   view agrees with a point, contradicts it or says nothing; consistent
   observations become one point (:mod:`sefm_recon.reconstruct.fuse`);
5. **database**: the dense matches quantised to keypoints, the matches and their
   two-view geometries (:mod:`sefm_recon.io.colmap_database`);
6. **triangulate** those matches with the given poses (``pycolmap.triangulate_points``),
   and write ``sparse_poses/``: the poses with the database's keypoints and no
   points, the input COLMAP's own ``point_triangulator`` needs.

Everything is written into a staging folder and moved into OUT at the end.
"""

from __future__ import annotations

import contextlib
import copy
import json
import logging
import os
import re
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from itertools import combinations
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from . import __version__
from .config import Config
from .errors import InputError
from .io.colmap_model import MODEL_FILES
from .versions import library_versions

logger = logging.getLogger(__name__)

__all__ = [
    "Workspace",
    "PairTask",
    "open_workspace",
    "read_pairs_file",
    "select_pairs",
    "pair_folder_name",
    "run_pair_task",
    "run_colmap",
]

MODEL_STEMS = ("cameras", "images")
#: What ``sefm-recon colmap`` writes into OUT; with ``--overwrite`` these are
#: replaced, everything else in OUT is kept.
COLMAP_RESULTS = ("pairs", "fused.ply", "database.db", "sparse", "sparse_poses", "report.json")
#: Inside those folders, the files it writes; with ``--overwrite`` the user's other files there are kept.
COLMAP_OWNED = {"pairs": ("*/matches.npz", "*/points.ply"), "sparse": MODEL_FILES, "sparse_poses": MODEL_FILES}


# ---------------------------------------------------------------------------- workspace


@dataclass
class Workspace:
    root: Path
    image_dir: Path
    sparse_dir: Path
    rec: object  #: pycolmap.Reconstruction

    def image_path(self, name: str) -> Path:
        return self.image_dir / name


def _has_model(folder: Path) -> bool:
    return folder.is_dir() and all(
        (folder / f"{s}.bin").is_file() or (folder / f"{s}.txt").is_file() for s in MODEL_STEMS)


def find_model_dir(root: Path) -> Path | None:
    """``sparse/`` if it holds a model, else ``sparse/0``, else None."""
    for cand in (root / "sparse", root / "sparse" / "0"):
        if _has_model(cand):
            return cand
    return None


def open_workspace(workspace: str | os.PathLike, image_dir: str | os.PathLike | None = None,
                   sparse_dir: str | os.PathLike | None = None) -> Workspace:
    """Locate and read a COLMAP workspace; raises :class:`InputError` with one line on any problem."""
    import pycolmap

    root = Path(workspace)
    if not root.is_dir():
        raise InputError(f"workspace not found: {root} is not a folder")
    images = Path(image_dir) if image_dir is not None else root / "images"
    if not images.is_dir():
        raise InputError(f"no image folder: {images} does not exist (a COLMAP workspace has images/; "
                         "or pass --image-dir)")
    if sparse_dir is not None:
        model = Path(sparse_dir)
        if not _has_model(model):
            raise InputError(f"no COLMAP model in {model} (need cameras and images .bin or .txt)")
    else:
        model = find_model_dir(root)
        if model is None:
            raise InputError(f"no sparse model in workspace {root}: expected sparse/ or sparse/0 with "
                             "cameras and images (.bin or .txt); or pass --sparse-dir")
    try:
        rec = pycolmap.Reconstruction(str(model))
    except Exception as err:  # pycolmap raises ValueError/RuntimeError on broken files
        raise InputError(f"cannot read the COLMAP model in {model}: {err}".splitlines()[0]) from None
    others = sorted(p.name for p in (model.parent.iterdir() if model.name == "0" else [])
                    if p.is_dir() and p.name.isdigit() and p.name != "0")
    if others:
        logger.info("using model %s; the workspace holds more models (%s): pick one with --sparse-dir",
                    model, ", ".join(others))
    logger.debug("workspace %s: %d images (%d with a pose), %d cameras, %d sparse points (model %s)",
                root, rec.num_images(), sum(1 for im in rec.images.values() if im.has_pose),
                rec.num_cameras(), rec.num_points3D(), model)
    return Workspace(root, images, model, rec)


def pose_of(image) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` cam_from_world of a pycolmap image."""
    M = np.asarray(image.cam_from_world().matrix(), np.float64)
    return M[:, :3].copy(), M[:, 3].copy()


def centre_of(image) -> np.ndarray:
    R, t = pose_of(image)
    return -R.T @ t


# -------------------------------------------------------------------------------- pairs


def read_pairs_file(path: str | os.PathLike, rec) -> list[tuple[int, int]]:
    """Image-id pairs from a file of ``name1 name2`` lines (``#`` comments and blank lines skipped).

    Unknown names, a line without two names, and an image paired with itself are
    input errors that say which line; repeated pairs (in either order) are kept once.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise InputError(f"pairs file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"cannot read pairs file {path}: {err}") from None
    by_name = {im.name: iid for iid, im in rec.images.items()}
    pairs: list[tuple[int, int]] = []
    seen: set[frozenset] = set()
    unknown: list[str] = []
    first_bad_line = None
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        fields = line.split()
        if len(fields) != 2:
            raise InputError(f"pairs file {path}, line {lineno}: expected 'name1 name2', got {line!r}")
        missing = [n for n in fields if n not in by_name]
        if missing:
            unknown.extend(n for n in missing if n not in unknown)
            first_bad_line = first_bad_line or lineno
            continue
        a, b = by_name[fields[0]], by_name[fields[1]]
        if a == b:
            raise InputError(f"pairs file {path}, line {lineno}: image {fields[0]} is paired with itself")
        key = frozenset((a, b))
        if key not in seen:
            seen.add(key)
            pairs.append((a, b))
    if unknown:
        shown = ", ".join(unknown[:5]) + (f" and {len(unknown) - 5} more" if len(unknown) > 5 else "")
        raise InputError(f"pairs file {path} names {len(unknown)} image(s) not in the model "
                         f"(first on line {first_bad_line}): {shown}")
    if not pairs:
        raise InputError(f"pairs file {path} lists no pairs")
    return pairs


def image_points(rec) -> dict[int, np.ndarray]:
    """Sorted point3D ids seen by each image."""
    out = {}
    for iid, im in rec.images.items():
        ids = [p.point3D_id for p in im.points2D if p.has_point3D()]
        out[iid] = np.unique(np.asarray(ids, np.int64))
    return out


def covisibility(rec) -> Counter:
    """Number of sparse points each image pair (id_lo, id_hi) shares."""
    counts: Counter = Counter()
    for p in rec.points3D.values():
        ids = sorted({el.image_id for el in p.track.elements})
        counts.update(combinations(ids, 2))
    return counts


def _axis_crossing(Ca, da, Cb, db) -> tuple[float, float] | None:
    """Distances along two viewing axes to their closest approach; None when parallel or behind a camera."""
    b = float(da @ db)
    denom = 1.0 - b * b
    if denom < 1e-6:  # axes within 0.08 degrees of parallel: no crossing to speak of
        return None
    w = Ca - Cb
    d, e = float(da @ w), float(db @ w)
    sa, sb = (b * e - d) / denom, (e - b * d) / denom
    return (sa, sb) if sa > 0 and sb > 0 else None


def _best_partners(rank: dict[tuple[int, int], float], n: int) -> set[tuple[int, int]]:
    """The pairs kept when each image keeps its ``n`` lowest-``rank`` pairs (ties: lower ids; 0 = all)."""
    if n <= 0:
        return set(rank)
    per_image: dict[int, list[tuple[float, tuple[int, int]]]] = {}
    for pair, r in rank.items():
        for i in pair:
            per_image.setdefault(i, []).append((r, pair))
    keep: set[tuple[int, int]] = set()
    for lst in per_image.values():
        lst.sort()
        keep.update(p for _, p in lst[:n])
    return keep


def pose_pairs(rec, cfg: Config, posed: list[int]) -> tuple[list[tuple[int, int]], list[dict]]:
    """Pairs from the poses alone (a model without sparse points), and why each other candidate was dropped.

    Like hloc's ``pairs_from_poses`` and COLMAP's MVS source-image selection:
    a candidate pair is dropped when its viewing directions (optical axes) differ
    by more than ``colmap.pair_max_view_angle_deg``, or when its rays meet at the
    scene under less than ``geometry.min_tri_angle_deg``. The scene point of a
    pair is where the two optical axes pass closest; for a pair whose axes do not
    meet in front of both cameras, the point at the median of the other pairs'
    distances along each axis (when no axes meet, the angle is not checked). Of the
    rest, each image keeps its ``colmap.pairs_per_image`` nearest partners (camera
    centre distance; 0 = all), and a pair is kept when either image keeps it.
    Returns the pairs and, per dropped candidate, ``{"images", "reason"}``.
    """
    c = cfg.colmap
    C = {i: centre_of(rec.images[i]) for i in posed}
    D = {i: pose_of(rec.images[i])[0][2] for i in posed}  # optical axis in world coordinates: R^T (0, 0, 1)
    name = {i: rec.images[i].name for i in posed}
    crossings = {}
    for a, b in combinations(posed, 2):
        x = _axis_crossing(C[a], D[a], C[b], D[b])
        if x is not None:
            crossings[(a, b)] = x
    depth = float(np.median([v for x in crossings.values() for v in x])) if crossings else None
    if depth is None:
        logger.info("no two optical axes meet in front of the cameras: the triangulation angle of pairs is "
                    "not checked (scene depth unknown)")
    dropped: list[dict] = []
    ok: dict[tuple[int, int], float] = {}
    for a, b in combinations(posed, 2):
        base = float(np.linalg.norm(C[a] - C[b]))
        view = float(np.degrees(np.arccos(np.clip(D[a] @ D[b], -1.0, 1.0))))
        reason = None
        if base <= 1e-9 * max(1.0, float(np.linalg.norm(C[a])), float(np.linalg.norm(C[b]))):
            reason = "no baseline: both images have the same camera centre"
        elif view > c.pair_max_view_angle_deg:
            reason = (f"viewing directions {view:.1f} deg apart (colmap.pair_max_view_angle_deg = "
                      f"{c.pair_max_view_angle_deg:g})")
        elif depth is not None:
            sa, sb = crossings.get((a, b), (depth, depth))
            X = 0.5 * (C[a] + sa * D[a] + C[b] + sb * D[b])
            tri = median_angle_deg(C[a], C[b], X[None])
            if tri < cfg.geometry.min_tri_angle_deg:
                reason = (f"triangulation angle {tri:.2f} deg at the scene (geometry.min_tri_angle_deg = "
                          f"{cfg.geometry.min_tri_angle_deg:g})")
        if reason:
            dropped.append({"images": [name[a], name[b]], "reason": reason})
        else:
            ok[(a, b)] = base
    keep = _best_partners(ok, c.pairs_per_image)  # smallest baseline first
    if c.pairs_per_image > 0:
        for pair in sorted(set(ok) - keep):
            dropped.append({"images": [name[pair[0]], name[pair[1]]],
                            "reason": f"neither image has it among its {c.pairs_per_image} nearest partners "
                                      f"(colmap.pairs_per_image)"})
    return sorted(keep), dropped


def select_pairs(rec, cfg: Config, dropped: list | None = None) -> tuple[list[tuple[int, int]], str]:
    """Pairs to match without a pairs file, and how they were chosen.

    With at least ``colmap.min_covisible`` sparse points: pairs sharing at least
    that many points; each image keeps its ``colmap.pairs_per_image`` best
    partners (0 = all), a pair is kept when either image keeps it. With fewer
    points: pairs from the poses (:func:`pose_pairs`); ``dropped`` (a list)
    receives why each other candidate pair was not kept.
    """
    posed = sorted(iid for iid, im in rec.images.items() if im.has_pose)
    if len(posed) < 2:
        raise InputError(f"the model has {len(posed)} image(s) with a pose; at least 2 are needed")
    if rec.num_points3D() < cfg.colmap.min_covisible:
        pairs, drops = pose_pairs(rec, cfg, posed)
        if dropped is not None:
            dropped.extend(drops)
        if not pairs:
            raise InputError(f"no two of the {len(posed)} posed images view the scene from a usable angle "
                             f"(see colmap.pair_max_view_angle_deg, geometry.min_tri_angle_deg): pass --pairs FILE")
        logger.debug("the model has %d sparse points: %d pairs chosen from the poses, %d candidates dropped",
                     rec.num_points3D(), len(pairs), len(drops))
        return pairs, "poses"
    c = cfg.colmap
    counts = {k: v for k, v in covisibility(rec).items() if v >= c.min_covisible and k[0] in posed and k[1] in posed}
    if not counts:
        raise InputError(f"no two images share {c.min_covisible} or more sparse points: pass --pairs FILE "
                         f"or lower colmap.min_covisible (--set colmap.min_covisible=N)")
    keep = _best_partners({k: -v for k, v in counts.items()}, c.pairs_per_image)  # most shared points first
    pairs = sorted(keep)
    logger.debug("%d pairs share at least %d sparse points; %d kept (best %s per image)", len(counts),
                c.min_covisible, len(pairs), c.pairs_per_image or "all")
    return pairs, "covisibility"


def median_angle_deg(C1: np.ndarray, C2: np.ndarray, X: np.ndarray) -> float:
    """Median angle (degrees) between the rays from two centres to points ``X`` (N, 3)."""
    if len(X) == 0:
        return float("nan")
    r1 = X - C1
    r2 = X - C2
    c = np.sum(r1 * r2, 1) / np.maximum(np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1), 1e-300)
    return float(np.degrees(np.median(np.arccos(np.clip(c, -1.0, 1.0)))))


def baseline_problem(rec, a: int, b: int, cfg: Config, points: dict[int, np.ndarray] | None) -> str | None:
    """Why the pair cannot give depth, judged before matching (None: go ahead)."""
    ia, ib = rec.images[a], rec.images[b]
    Ca, Cb = centre_of(ia), centre_of(ib)
    base = float(np.linalg.norm(Ca - Cb))
    if base <= 1e-9 * max(1.0, float(np.linalg.norm(Ca)), float(np.linalg.norm(Cb))):
        return "no baseline: both images have the same camera centre"
    if points:
        shared = np.intersect1d(points[a], points[b])
        if len(shared) >= 5:
            X = np.stack([rec.points3D[int(p)].xyz for p in shared])
            ang = median_angle_deg(Ca, Cb, X)
            if ang < cfg.geometry.min_tri_angle_deg:
                return (f"baseline too small: median triangulation angle of the {len(shared)} shared sparse "
                        f"points is {ang:.2f} deg (geometry.min_tri_angle_deg = {cfg.geometry.min_tri_angle_deg})")
    return None


_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")


def pair_folder_name(name1: str, name2: str) -> str:
    """``<stem1>__<stem2>``: image names without extension, ``/`` (and other unsafe characters) as ``_``."""
    def stem(n: str) -> str:
        p = Path(n)
        s = str(p.with_suffix("")) if p.suffix else n
        return _UNSAFE.sub("_", s.replace("\\", "/").replace("/", "_"))

    return f"{stem(name1)}__{stem(name2)}"


# ---------------------------------------------------------------------------- pair tasks


@dataclass
class PairTask:
    """Everything one pair needs; picklable, so it can run in another process or on another machine."""

    index: int
    name1: str
    name2: str
    image1: str | bytes  #: a path, or the file's bytes (Dask: workers need no shared file system)
    image2: str | bytes
    camera1: object  #: pycolmap.Camera
    camera2: object
    R1: np.ndarray
    t1: np.ndarray
    R2: np.ndarray
    t2: np.ndarray
    cfg: Config
    numba_threads: int = 0  #: >0: limit numba's threads in this task


def read_workspace_image(path: str | os.PathLike) -> np.ndarray:
    """An image as COLMAP sees it: (H, W, 3) uint8 RGB with the EXIF orientation *not* applied.

    COLMAP ignores the EXIF orientation tag (a camera's intrinsics stay shared
    however the photo was held), so its model describes the stored pixels.
    :func:`~sefm_recon.io.images.read_image` checks the file and converts
    unusual formats; an 8-bit colour image is then decoded again without rotation.
    """
    import cv2

    from .io.images import read_image

    img = read_image(path)
    raw = cv2.imdecode(np.fromfile(str(path), np.uint8), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if raw is not None and raw.dtype == np.uint8 and raw.ndim == 3 and raw.shape[2] == 3:
        return cv2.cvtColor(raw, cv2.COLOR_BGR2RGB)
    return img


def _load_image(src: str | bytes, name: str) -> np.ndarray:
    if isinstance(src, (bytes, bytearray)):
        suffix = Path(name).suffix or ".img"
        fd, tmp = tempfile.mkstemp(suffix=suffix)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(src)
            return read_workspace_image(tmp)
        finally:
            os.unlink(tmp)
    return read_workspace_image(src)


def run_pair_task(task: PairTask) -> dict:
    """Reconstruct one pair with its known poses; the points come back in world coordinates.

    Returns a dict with ``status``: ``"ok"`` (with ``uv1 uv2 score xyz rgb
    normals counts timings tri_angle_deg``), ``"skipped"`` (``reason``: no
    baseline, no matches, ...) or ``"error"`` (``message``: an input error that
    concerns the whole run, such as an unreadable image or a camera whose size
    does not match its image).
    """
    from .pipeline import reconstruct_pair

    t0 = time.perf_counter()
    base = {"index": task.index, "images": [task.name1, task.name2]}
    if task.numba_threads > 0:
        _limit_threads(task.numba_threads)
    try:
        img1 = _load_image(task.image1, task.name1)
        img2 = _load_image(task.image2, task.name2)
        for img, cam, name in ((img1, task.camera1, task.name1), (img2, task.camera2, task.name2)):
            if (img.shape[1], img.shape[0]) != (cam.width, cam.height):
                raise InputError(f"image {name} is {img.shape[1]}x{img.shape[0]} but its camera in the model "
                                 f"is {cam.width}x{cam.height}")
    except InputError as err:
        return {**base, "status": "error", "message": str(err)}
    R = task.R2 @ task.R1.T
    t = task.t2 - R @ task.t1
    cfg = copy.deepcopy(task.cfg)
    cfg.output.mesh = "none"  # one mesh per pair would be wasted work
    try:
        res = reconstruct_pair(img1, img2, task.camera1, task.camera2, cfg, pose=(R, t), progress=False,
                               names=(task.name1, task.name2))
    except (InputError, ValueError) as err:
        # a skipped pair's time is reported too: on weakly textured sets it can be most of the run's
        return {**base, "status": "skipped", "reason": str(err).splitlines()[0] if str(err) else type(err).__name__,
                "timings": {"total": round(time.perf_counter() - t0, 4)}}
    C2 = -R.T @ t  # camera 2's centre in camera 1's frame
    angle = median_angle_deg(np.zeros(3), C2, res.xyz)
    base["timings"] = {"total": round(time.perf_counter() - t0, 4)}
    if len(res.xyz) == 0:
        return {**base, "status": "skipped", "reason": "no matches", "counts": res.counts}
    if not angle >= cfg.geometry.min_tri_angle_deg:
        return {**base, "status": "skipped", "counts": res.counts,
                "reason": f"baseline too small: median triangulation angle of the matches is {angle:.2f} deg "
                          f"(geometry.min_tri_angle_deg = {cfg.geometry.min_tri_angle_deg})"}
    # camera 1 -> world: X_w = R1^T (X_c1 - t1)
    xyz = (res.xyz - task.t1) @ task.R1
    normals = None if res.normals is None else res.normals @ task.R1
    res.timings["total"] = time.perf_counter() - t0
    return {
        **base,
        "status": "ok",
        "uv1": res.uv1.astype(np.float32),
        "uv2": res.uv2.astype(np.float32),
        "score": res.score.astype(np.float32),
        "xyz": xyz,
        "rgb": res.rgb,
        "normals": normals,
        "counts": res.counts,
        "timings": {k: round(v, 4) for k, v in res.timings.items()},
        "tri_angle_deg": round(angle, 3),
        "image_size": res.image_size,
    }


def _limit_threads(n: int) -> None:
    try:
        import numba

        numba.set_num_threads(max(1, min(int(n), numba.config.NUMBA_NUM_THREADS)))
    except Exception:  # noqa: BLE001 - a hint only
        pass
    try:
        import cv2

        cv2.setNumThreads(int(n))
    except Exception:  # noqa: BLE001
        pass


def _init_worker(threads: int, level: int) -> None:
    logging.basicConfig(level=max(level, logging.WARNING), format="%(levelname).1s %(name)s: %(message)s")
    _limit_threads(threads)


def _run_local(tasks: list, workers: int, fn=None) -> Iterator:
    """``fn(task)`` (default :func:`run_pair_task`) for each task, inline or in a process pool, as they finish."""
    fn = fn or run_pair_task
    if workers <= 1 or len(tasks) <= 1:
        for t in tasks:
            yield fn(t)
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    methods = mp.get_all_start_methods()
    # forkserver: workers fork from a clean server (no threads of ours), yet skip spawn's re-imports
    ctx = mp.get_context("forkserver" if "forkserver" in methods else "spawn")
    if ctx.get_start_method() == "forkserver":
        ctx.set_forkserver_preload(["sefm_recon.pipeline"])
    n = min(workers, len(tasks))
    threads = max(1, (os.cpu_count() or 1) // n)
    ex = ProcessPoolExecutor(max_workers=n, mp_context=ctx, initializer=_init_worker,
                             initargs=(threads, logging.getLogger().level))
    finished = False
    try:
        # A finished future keeps its result (a pair's arrays, tens of MB) while anything refers to it:
        # each one is let go as soon as it is read, or the run holds every pair's arrays to the end.
        pending = {ex.submit(fn, t) for t in tasks}
        for f in as_completed(pending):
            pending.discard(f)
            yield f.result()
            del f
        finished = True
    finally:
        if not finished:  # an error, Ctrl-C or SIGTERM: stop the running pairs now, not after they finish
            for proc in list(getattr(ex, "_processes", {}).values()):
                proc.terminate()
        ex.shutdown(wait=finished, cancel_futures=True)


def _run_dask(tasks: list[PairTask], address: str) -> Iterator[dict]:
    try:
        from dask.distributed import Client, as_completed
    except ImportError:
        raise InputError("--scheduler needs Dask: pip install 'sefm-recon[dask]' "
                         "(or pip install 'dask[distributed]')") from None
    try:
        client = Client(address, timeout=30)
    except Exception as err:  # noqa: BLE001 - OSError/TimeoutError/ValueError from Dask
        raise InputError(f"cannot connect to the Dask scheduler at {address}: {err}".splitlines()[0]) from None
    try:
        logger.info("Dask: %d workers at %s", len(client.scheduler_info().get("workers", {})), address)
        pending = set(client.map(run_pair_task, tasks, pure=False))
        try:
            for fut in as_completed(pending):
                pending.discard(fut)  # let go of each result as soon as it is read (see _run_local)
                yield fut.result()
                del fut
        finally:
            client.cancel(list(pending))
    finally:
        client.close()


def iter_pair_results(tasks: list[PairTask], workers: int | None = None, scheduler: str | None = None
                      ) -> Iterator[dict]:
    """Run the tasks on a Dask cluster (``scheduler``), a process pool, or inline; results as they finish."""
    if scheduler:
        return _run_dask(tasks, scheduler)
    return _run_local(tasks, workers if workers else (os.cpu_count() or 1))


# -------------------------------------------------------------------------- orchestration


@dataclass
class _PairState:
    a: int
    b: int
    folder: str
    entry: dict = field(default_factory=dict)


def _sum_counts(entries: Iterable[dict]) -> dict:
    total: dict[str, int] = {}
    for e in entries:
        for k, v in e.get("counts", {}).items():
            if isinstance(v, (int, np.integer)):
                total[k] = total.get(k, 0) + int(v)
    return total


def _collect(r: dict, states: list[_PairState], staged, results: dict[int, dict]) -> None:
    """Record one pair's result; a successful pair's matches.npz and points.ply go into ``stage/pairs``.

    ``staged``: the :class:`~sefm_recon.io.output.StagedOutput` (its free space is checked first).
    """
    from .io.ply import write_point_cloud

    if r["status"] == "error":
        raise InputError(r["message"])
    st = states[r["index"]]
    if r["status"] == "skipped":
        st.entry.update(status="skipped", reason=r["reason"], counts=r.get("counts", {}),
                        timings_s=r.get("timings", {}))
        logger.warning("skipping %s %s: %s", *st.entry["images"], r["reason"])
        return
    staged.require(len(r["uv1"]) * (20 + 27))  # matches.npz (at most), points.ply
    folder = staged.stage / "pairs" / st.folder
    folder.mkdir(parents=True)
    np.savez_compressed(folder / "matches.npz", uv1=r["uv1"], uv2=r["uv2"], score=r["score"])
    write_point_cloud(folder / "points.ply", r["xyz"], r["rgb"], r["normals"])
    st.entry.update(status="ok", image_size=r["image_size"], counts=r["counts"], timings_s=r["timings"],
                    tri_angle_deg=r["tri_angle_deg"])
    # the pair's arrays live on disk from here on: fusion and the database read them back
    results[r["index"]] = {"folder": folder, "matches": len(r["uv1"])}
    logger.debug("pair %s %s: %d matches", *st.entry["images"], len(r["uv1"]))


def triangulate(rec, database: Path, image_dir: Path, out_dir: Path, cfg: Config):
    """``pycolmap.triangulate_points`` with the given poses, without bundle adjustment; two-view tracks are kept."""
    import pycolmap

    opts = pycolmap.IncrementalPipelineOptions()
    opts.triangulation.ignore_two_view_tracks = False
    opts.triangulation.min_angle = float(cfg.colmap.tri_min_angle_deg)
    opts.mapper.filter_min_tri_angle = float(cfg.colmap.tri_min_angle_deg)
    opts.extract_colors = True
    # the poses and cameras are given and stay fixed, so COLMAP's bundle adjustment would only move the points:
    # on 8 photos of 1.5 MP it took 1.4 GB and 40 s to bring their mean reprojection error from 0.55 to 0.25 px
    opts.ba_global_max_refinements = 0
    out_dir.mkdir(parents=True, exist_ok=True)
    model = pycolmap.Reconstruction(rec)  # a copy: the caller's model keeps its points
    return pycolmap.triangulate_points(model, str(database), str(image_dir), str(out_dir), clear_points=True,
                                       options=opts, refine_intrinsics=False)


def run_colmap(
    workspace: str | os.PathLike,
    out: str | os.PathLike,
    cfg: Config,
    pairs_file: str | os.PathLike | None = None,
    image_dir: str | os.PathLike | None = None,
    sparse_dir: str | os.PathLike | None = None,
    overwrite: bool = False,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = False,
) -> dict:
    """``sefm-recon colmap``: reconstruct a COLMAP workspace densely into ``out``; returns the report."""
    from .io.colmap_database import StoredPairMatches, quantise_matches, write_database
    from .io.colmap_model import check_model_written, write_poses_model
    from .io.output import StagedOutput, check_output_dir
    from .memory import release_freed_memory
    from .io.ply import iter_point_cloud, write_point_cloud
    from .reconstruct.fuse import BLOCK_POINTS as FUSE_BLOCK
    from .reconstruct.fuse import FusionView, fuse_pairs

    if workers is not None and workers < 1:
        raise InputError(f"--workers must be at least 1, got {workers}")
    check_output_dir(out, overwrite)  # fail before the long work
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    ws = open_workspace(workspace, image_dir, sparse_dir)
    rec = ws.rec
    candidates_dropped: list[dict] = []  # pairs from the poses: the candidates not chosen, and why
    if pairs_file is not None:
        pairs, how = read_pairs_file(pairs_file, rec), "file"
        unposed = sorted({rec.images[i].name for p in pairs for i in p if not rec.images[i].has_pose})
        if unposed:
            raise InputError(f"pairs file {pairs_file} names image(s) without a pose in the model: "
                             f"{', '.join(unposed[:5])}")
    else:
        pairs, how = select_pairs(rec, cfg, candidates_dropped)
    needed = sorted({rec.images[i].name for p in pairs for i in p})
    missing = [n for n in needed if not ws.image_path(n).is_file()]
    if missing:
        shown = ", ".join(missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
        raise InputError(f"{len(missing)} image(s) of the model are missing from {ws.image_dir}: {shown}")

    points = image_points(rec) if rec.num_points3D() else None
    states: list[_PairState] = []
    used_folders: Counter = Counter()
    tasks: list[PairTask] = []
    for a, b in pairs:
        ia, ib = rec.images[a], rec.images[b]
        folder = pair_folder_name(ia.name, ib.name)
        used_folders[folder] += 1
        if used_folders[folder] > 1:
            folder = f"{folder}__{used_folders[folder]}"
        st = _PairState(a, b, folder, {"images": [ia.name, ib.name], "folder": f"pairs/{folder}"})
        states.append(st)
        why = baseline_problem(rec, a, b, cfg, points)
        if why:
            st.entry.update(status="skipped", reason=why)
            logger.warning("skipping %s %s: %s", ia.name, ib.name, why)
            continue
        R1, t1 = pose_of(ia)
        R2, t2 = pose_of(ib)
        src1, src2 = str(ws.image_path(ia.name)), str(ws.image_path(ib.name))
        if scheduler:
            src1, src2 = Path(src1).read_bytes(), Path(src2).read_bytes()
        tasks.append(PairTask(len(states) - 1, ia.name, ib.name, src1, src2, ia.camera, ib.camera,
                              R1, t1, R2, t2, cfg))
    if not tasks:
        raise InputError(f"none of the {len(pairs)} pairs can be reconstructed (see the reasons above)")
    n_workers = 1 if scheduler else min(workers or (os.cpu_count() or 1), len(tasks))
    logger.info("%s: %d images, %d sparse points; matching %d pairs (%s) %s", ws.sparse_dir, rec.num_images(),
                rec.num_points3D(), len(tasks), how,
                f"on the Dask cluster at {scheduler}" if scheduler else f"with {n_workers} worker(s)")

    staged = StagedOutput(out, overwrite, results=COLMAP_RESULTS, owned=COLMAP_OWNED)
    with staged as stage:
        (stage / "pairs").mkdir()
        t0 = time.perf_counter()
        results: dict[int, dict] = {}
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=len(tasks), unit="pair", desc="pairs", leave=False)
        try:
            with contextlib.closing(iter_pair_results(tasks, workers, scheduler)) as pair_results:
                for r in pair_results:
                    _collect(r, states, staged, results)
                    del r
                    release_freed_memory()  # the CLI keeps freed memory for speed; between stages it goes back
                    if bar is not None:
                        bar.update(1)
        finally:
            if bar is not None:
                bar.close()
        timings["pairs"] = time.perf_counter() - t0
        if not results:
            raise InputError(f"no pair gave matches ({len(states)} pairs, every one skipped: see the reasons above)")

        # fusion: every posed image judges the pairs' points; the points are read back from pairs/ in blocks
        t0 = time.perf_counter()
        posed = sorted(iid for iid, im in rec.images.items() if im.has_pose)
        view_of = {iid: k for k, iid in enumerate(posed)}
        views = [FusionView(rec.images[i].camera, *pose_of(rec.images[i])) for i in posed]
        done_idx = sorted(results)
        fused = fuse_pairs(
            views, [(view_of[states[i].a], view_of[states[i].b]) for i in done_idx],
            lambda k: iter_point_cloud(results[done_idx[k]]["folder"] / "points.ply", FUSE_BLOCK),
            # two posed images have no third view to agree: their points stand where none contradicts them
            min_views=min(cfg.colmap.fuse_min_views, len(posed)), max_depth_error=cfg.colmap.fuse_max_depth_error)
        if len(fused.xyz) == 0:
            raise InputError("fusion kept no point: every view contradicts every pair's points (check the poses)")
        staged.require(27 * len(fused.xyz))
        write_point_cloud(stage / "fused.ply", fused.xyz, fused.rgb, fused.normals)
        del fused.xyz, fused.rgb, fused.normals, fused.tracks
        release_freed_memory()
        timings["fuse"] = time.perf_counter() - t0

        # database
        t0 = time.perf_counter()
        pm = [StoredPairMatches(states[i].a, states[i].b, r["folder"] / "matches.npz") for i, r in sorted(results.items())]
        q = quantise_matches(pm, cfg.colmap.cell_size, cfg.colmap.max_error)
        n_kp, n_m = sum(map(len, q.keypoints.values())), sum(map(len, q.matches.values()))
        # database.db: keypoints, matches and inliers (sqlite pages on top); sparse/: every keypoint, a point a
        # match; sparse_poses/: every keypoint again
        staged.require(12 * n_kp + 20 * n_m + (256 << 10) + 24 * n_kp + 67 * n_m + 24 * n_kp)
        db_counts = write_database(stage / "database.db", rec, q, cfg.colmap.max_epipolar_error)
        del pm
        q.matches.clear()
        release_freed_memory()
        timings["database"] = time.perf_counter() - t0

        # triangulation with the given poses
        t0 = time.perf_counter()
        tri = triangulate(rec, stage / "database.db", ws.image_dir, stage / "sparse", cfg)
        check_model_written(stage / "sparse", tri)
        write_poses_model(stage / "sparse_poses", rec, q.keypoints)
        timings["triangulate"] = time.perf_counter() - t0
        sparse = {
            "points": int(tri.num_points3D()),
            "mean_reprojection_error_px": round(float(tri.compute_mean_reprojection_error()), 4),
            "mean_track_length": round(float(tri.compute_mean_track_length()), 3),
            "observations": int(tri.compute_num_observations()),
        }
        timings["total"] = time.perf_counter() - t_start

        entries = [st.entry for st in states]
        done = [e for e in entries if e.get("status") == "ok"]
        counts = _sum_counts(done)
        counts.update(pairs=len(states), pairs_done=len(done), pairs_skipped=len(states) - len(done),
                      fused_points=fused.stats["points"], sparse_points=sparse["points"], **db_counts,
                      db_dropped_matches=int(q.dropped))
        report = {
            "version": __version__,
            "libraries": library_versions(),
            "workspace": str(Path(workspace).resolve()),
            "image_dir": str(ws.image_dir.resolve()),
            "sparse_dir": str(ws.sparse_dir.resolve()),
            "pair_selection": how,
            "pair_candidates_dropped": candidates_dropped,
            "image_size": {im.name: [im.camera.width, im.camera.height] for im in rec.images.values()},
            "config": cfg.to_dict(),
            "timings_s": {k: round(v, 4) for k, v in timings.items()},
            "counts": counts,
            "fusion": fused.stats,
            "sparse": sparse,
            "execution": {"scheduler": scheduler, "workers": n_workers},
            "pairs": entries,
        }
        (stage / "report.json").write_text(json.dumps(report, indent=2))
    return report
