"""``sefm-recon colmap``: COLMAP workspaces in, dense points, a database and a model out.

Generated scenes with known geometry: a text model with true poses (the "done
when" figures), a binary model in sparse/0 with lens distortion, a workspace made
by pycolmap's own SfM, and the Dask path on a LocalCluster.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np  # before pycolmap: imported the other way round, cv2 cannot write PNGs
import cv2
import pycolmap
import pytest

from sefm_recon.colmap_plugin import (
    COLMAP_RESULTS,
    PairTask,
    _run_local,
    open_workspace,
    pair_folder_name,
    read_pairs_file,
    read_workspace_image,
    run_colmap,
    run_pair_task,
    select_pairs,
)
from sefm_recon.config import load_config
from sefm_recon.errors import InputError
from sefm_recon.evaluate import surface_distances
from sefm_recon.io.colmap_database import PairMatches, quantise_matches
from sefm_recon.io.ply import read_ply_header, read_point_cloud
from sefm_recon.synthetic import align_to_truth, colmap_sfm, render_scene, write_workspace


def run_cli(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "sefm_recon", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)


def _cfg(*overrides):
    return load_config(None, ["output.progress=false", *overrides])


def _accuracy(xyz, scene, share=0.01):
    d = surface_distances(xyz, scene.views)
    return float(np.mean(d <= share * scene.meta["scene_size"]))


def _nearest_distances(a, b):
    """Distance from each point of ``a`` to its nearest point of ``b``."""
    import open3d as o3d

    pa = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(a, np.float64)))
    pb = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(b, np.float64)))
    return np.asarray(pa.compute_point_cloud_distance(pb))


# ------------------------------------------------------------------ workspaces


def _distorted_workspace(scene, root: Path, k: float = 0.04) -> Path:
    """The scene seen through SIMPLE_RADIAL lenses (k > 0: no black borders), as a binary model in sparse/0."""
    (root / "images").mkdir(parents=True)
    rec = pycolmap.Reconstruction()
    for i, v in enumerate(scene.views, start=1):
        h, w = v.depth.shape
        K = v.K
        cam = pycolmap.Camera(camera_id=i, model="SIMPLE_RADIAL", width=w, height=h,
                              params=[K[0, 0], K[0, 2], K[1, 2], k])
        jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
        rays = np.asarray(cam.cam_from_img(np.c_[jj.ravel(), ii.ravel()]), np.float64)
        src = np.c_[rays, np.ones(len(rays))] @ K.T
        mapx = (src[:, 0] - 0.5).reshape(h, w).astype(np.float32)
        mapy = (src[:, 1] - 0.5).reshape(h, w).astype(np.float32)
        img = cv2.remap(v.image, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        cv2.imwrite(str(root / "images" / v.name), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        rec.add_camera_with_trivial_rig(cam)
        rec.add_image_with_trivial_frame(pycolmap.Image(name=v.name, camera_id=i, image_id=i),
                                         pycolmap.Rigid3d(np.hstack([v.R, v.t.reshape(3, 1)])))
    (root / "sparse" / "0").mkdir(parents=True)
    rec.write_binary(str(root / "sparse" / "0"))
    return root


def _sfm_workspace(scene, root: Path) -> Path:
    """COLMAP's own pipeline on the rendered images: SIFT, exhaustive matching, incremental mapping."""
    write_workspace(scene, root)
    rec = colmap_sfm(root)
    assert rec.num_reg_images() == len(scene.views), "pycolmap's SfM did not register every view"
    return root


# ------------------------------------------------------------ the main workspace


@pytest.fixture(scope="module")
def scene3():
    return render_scene(seed=21, width=480, height=360, n_views=3, style="classic")


@pytest.fixture(scope="module")
def text_run(scene3, tmp_path_factory):
    """The CLI on a 3-view text workspace with true poses and no sparse points, on a pool of 2 workers."""
    root = tmp_path_factory.mktemp("colmap_text")
    ws = write_workspace(scene3, root / "ws")
    out = root / "out"
    r = run_cli("colmap", ws, "-o", out, "--workers", 2, "-q")
    assert r.returncode == 0, r.stderr
    return ws, out, r


@pytest.mark.slow
def test_writes_every_output(text_run):
    ws, out, r = text_run
    assert {p.name for p in out.iterdir()} == set(COLMAP_RESULTS)
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]  # no staging left over
    assert r.stdout == "" and r.stderr == ""  # -q
    report = json.loads((out / "report.json").read_text())
    for key in ("version", "libraries", "config", "timings_s", "counts", "image_size", "pairs", "sparse", "fusion"):
        assert key in report
    assert report["pair_selection"] == "poses"  # the model has no points
    assert report["pair_candidates_dropped"] == []  # three views within 50 degrees: every pair kept
    assert report["counts"]["pairs_done"] == 3
    for key in ("sift_matches", "dense_matches", "valid_matches", "points"):
        assert report["counts"][key] > 0
    assert report["counts"]["rough_matches"] == 0  # the default SGM matcher has no rough stage
    names = sorted(p.name for p in (out / "pairs").iterdir())
    assert names == ["view_000__view_001", "view_000__view_002", "view_001__view_002"]
    for entry in report["pairs"]:
        assert entry["status"] == "ok"
        m = np.load(out / entry["folder"] / "matches.npz")
        assert m["uv1"].shape == m["uv2"].shape and m["uv1"].shape[1] == 2
        assert len(m["score"]) == len(m["uv1"]) > 10_000
        assert read_ply_header(out / entry["folder"] / "points.ply")["elements"]["vertex"]["count"] > 10_000


@pytest.mark.slow
def test_done_when_figures(text_run, scene3):
    """fused.ply >= 100,000 points within 1 % of the scene size (>= 95 %); the model >= 10,000 points < 1 px."""
    _, out, _ = text_run
    xyz, rgb, normals = read_point_cloud(out / "fused.ply")
    assert len(xyz) >= 100_000
    assert rgb is not None and normals is not None
    assert _accuracy(xyz, scene3) >= 0.95
    rec = pycolmap.Reconstruction(str(out / "sparse"))
    assert rec.num_reg_images() == 3
    assert rec.num_points3D() >= 10_000
    assert rec.compute_mean_reprojection_error() < 1.0
    P = np.array([p.xyz for p in rec.points3D.values()])
    assert _accuracy(P, scene3) >= 0.9
    report = json.loads((out / "report.json").read_text())
    assert report["sparse"]["points"] == rec.num_points3D()
    assert report["counts"]["fused_points"] == len(xyz)
    # multi-view fusion: every fused point has a track of its own pair's two views and at least one other
    fusion = report["fusion"]
    assert sum(fusion["track_lengths"]) == len(xyz) and sum(fusion["track_lengths"][:3]) < 0.01 * len(xyz)
    dropped = sum(fusion[k] for k in ("dropped_free_space", "dropped_background", "dropped_hidden",
                                      "dropped_unconfirmed"))
    assert fusion["kept"] + dropped == fusion["input_points"]


@pytest.mark.slow
def test_normals_face_the_cameras(text_run, scene3):
    _, out, _ = text_run
    xyz, _, normals = read_point_cloud(out / "fused.ply")
    centres = np.stack([v.center for v in scene3.views])
    facing = (np.einsum("nk,nck->nc", normals, centres[None, :, :] - xyz[:, None, :]) > 0).any(axis=1)
    assert facing.mean() > 0.99


@pytest.mark.slow
def test_fused_cloud_opens_in_pymeshlab(text_run):
    pymeshlab = pytest.importorskip("pymeshlab")
    _, out, _ = text_run
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(out / "fused.ply"))
    assert ms.current_mesh().vertex_number() == read_ply_header(out / "fused.ply")["elements"]["vertex"]["count"] >= 100_000


@pytest.mark.slow
def test_database_holds_cameras_images_keypoints_matches_geometries(text_run):
    ws, out, _ = text_run
    model = pycolmap.Reconstruction(str(ws / "sparse"))
    db = pycolmap.Database.open(str(out / "database.db"))
    try:
        assert db.num_cameras() == 3 and db.num_images() == 3
        assert {im.name for im in db.read_all_images()} == {im.name for im in model.images.values()}
        for im in db.read_all_images():  # ids agree with the model's
            assert model.images[im.image_id].name == im.name
            assert db.num_keypoints_for_image(im.image_id) > 1000
        assert db.num_matched_image_pairs() == 3 and db.num_verified_image_pairs() == 3
        assert db.num_inlier_matches() > 10_000
        g = db.read_two_view_geometry(1, 2)
        assert int(g.config) == int(pycolmap.TwoViewGeometryConfiguration.CALIBRATED)
        # keypoints are quantised: at most one per 2x2 px cell
        kp = db.read_keypoints(1)[:, :2]
        cells = np.round(kp / 2.0).astype(np.int64)
        assert len(np.unique(cells, axis=0)) == len(kp)
        # each keypoint has at most one partner in a pair
        m = db.read_matches(1, 2)
        assert len(np.unique(m[:, 0])) == len(m) == len(np.unique(m[:, 1]))
    finally:
        db.close()


@pytest.mark.slow
def test_colmap_mapper_reconstructs_from_the_database(text_run, tmp_path):
    """The database is usable by COLMAP's own incremental mapper, not only by the triangulator."""
    ws, out, _ = text_run
    db = tmp_path / "db.db"
    db.write_bytes((out / "database.db").read_bytes())
    (tmp_path / "map").mkdir()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.random_seed = 0
    recs = pycolmap.incremental_mapping(db, ws / "images", tmp_path / "map", options=opts)
    assert recs and max(r.num_reg_images() for r in recs.values()) == 3


@pytest.mark.slow
def test_non_empty_out_is_refused_without_overwrite(text_run):
    ws, out, _ = text_run
    r = run_cli("colmap", ws, "-o", out, "-q")
    assert r.returncode == 2
    assert "not empty" in r.stderr and len(r.stderr.strip().splitlines()) == 1


# ---------------------------------------------------------------- other workspaces


@pytest.fixture(scope="module")
def small_scene3():
    return render_scene(seed=33, width=320, height=240, n_views=3, style="classic")


@pytest.mark.slow
def test_binary_model_in_sparse0_with_distortion(small_scene3, tmp_path):
    """sparse/0, binary, SIMPLE_RADIAL lenses: matches come back in the distorted photos' pixels."""
    ws = _distorted_workspace(small_scene3, tmp_path / "ws")
    report = run_colmap(ws, tmp_path / "out", _cfg(), workers=1)
    assert report["sparse_dir"].endswith("sparse/0")
    assert report["counts"]["pairs_done"] == 3
    xyz, _, _ = read_point_cloud(tmp_path / "out" / "fused.ply")
    assert len(xyz) > 30_000
    assert _accuracy(xyz, small_scene3) >= 0.9  # the same scene without distortion: 0.94 at 320x240
    # a match's two ends are the same surface point seen through the distorted lenses
    rec = pycolmap.Reconstruction(str(ws / "sparse" / "0"))
    v1, v2 = small_scene3.views[:2]
    m = np.load(tmp_path / "out" / "pairs" / "view_000__view_001" / "matches.npz")
    rays = np.asarray(rec.cameras[1].cam_from_img(m["uv1"].astype(np.float64)), np.float64)
    uv_pin = np.c_[rays, np.ones(len(rays))] @ v1.K.T
    d = v1.depth[np.clip(uv_pin[:, 1].astype(int), 0, 239), np.clip(uv_pin[:, 0].astype(int), 0, 319)]
    ok = np.isfinite(d)
    Xw = ((np.c_[rays, np.ones(len(rays))] * d[:, None])[ok] - v1.t) @ v1.R
    uv2 = np.asarray(rec.cameras[2].img_from_cam(Xw @ v2.R.T + v2.t), np.float64)
    err = np.linalg.norm(uv2 - m["uv2"][ok], axis=1)
    assert np.median(err) < 1.0
    sparse = pycolmap.Reconstruction(str(tmp_path / "out" / "sparse"))
    assert sparse.num_points3D() > 3000 and sparse.compute_mean_reprojection_error() < 1.0


@pytest.mark.slow
def test_workspace_from_pycolmap_sfm(small_scene3, tmp_path):
    """A workspace written by COLMAP itself (SIFT, incremental mapping): poses up to scale, distortion, points."""
    ws = _sfm_workspace(small_scene3, tmp_path / "ws")
    report = run_colmap(ws, tmp_path / "out", _cfg(), workers=1)
    assert report["pair_selection"] == "covisibility"
    assert report["counts"]["pairs_done"] >= 2
    model = pycolmap.Reconstruction(str(ws / "sparse" / "0"))
    xyz, _, _ = read_point_cloud(tmp_path / "out" / "fused.ply")
    assert len(xyz) > 30_000
    # the dense cloud agrees with COLMAP's own sparse points, in COLMAP's frame
    s, R, t = align_to_truth(model, small_scene3)
    size = small_scene3.meta["scene_size"] / s  # in the model's units
    sparse_pts = np.array([p.xyz for p in model.points3D.values()])
    assert np.mean(_nearest_distances(sparse_pts, xyz) <= 0.01 * size) >= 0.95
    # and with the true surface, up to the model's own error (its intrinsics are estimated from 320x240 photos:
    # a fifth of its own points lie within 1 % of the scene size of the truth, all within 2 %)
    assert _accuracy(s * xyz @ R.T + t, small_scene3, share=0.03) >= 0.9
    sparse = pycolmap.Reconstruction(str(tmp_path / "out" / "sparse"))
    assert sparse.num_points3D() > 3000 and sparse.compute_mean_reprojection_error() < 1.0


def test_a_pair_skipped_at_matching_reports_its_time():
    """A pair that fails in matching (here: a blank photo) is skipped with its reason and its time
    (on a weakly textured set such pairs can take most of the run)."""
    blank = cv2.imencode(".png", np.full((120, 160, 3), 128, np.uint8))[1].tobytes()
    cam = pycolmap.Camera(model="PINHOLE", width=160, height=120, params=[150.0, 150.0, 80.0, 60.0])
    task = PairTask(0, "a.png", "b.png", blank, blank, cam, cam, np.eye(3), np.zeros(3), np.eye(3),
                    np.array([-1.0, 0.0, 0.0]), load_config(None))
    r = run_pair_task(task)
    assert r["status"] == "skipped" and "texture" in r["reason"]
    assert r["timings"]["total"] > 0


def test_process_pool_lets_go_of_each_result():
    """Two workers: a result read and dropped by the caller is freed at once (a pool that kept its
    futures held every pair's arrays to the end of the pair stage: 1.2 GB on 8 photos of 1.5 MP)."""
    import gc
    import weakref

    refs = []
    for arr in _run_local([100_000] * 5, 2, fn=np.ones):
        assert arr.shape == (100_000,) and arr[-1] == 1.0
        refs.append(weakref.ref(arr))
        del arr
        gc.collect()
        # the newest one's future may still be in the pool's hands until the next is asked for
        assert [r() is None for r in refs[:-1]] == [True] * (len(refs) - 1)
    assert len(refs) == 5


@pytest.mark.slow
def test_dask_scheduler_on_a_local_cluster(small_scene3, tmp_path):
    """--scheduler: the same per-pair tasks on a Dask cluster (images travel as bytes)."""
    distributed = pytest.importorskip("distributed")
    ws = write_workspace(small_scene3, tmp_path / "ws")
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("# one pair\nview_000.png view_001.png\n\nview_001.png view_002.png\n")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=40) as cluster:
        r = run_cli("colmap", ws, "-o", tmp_path / "out", "--pairs", pairs, "--scheduler",
                    cluster.scheduler_address, "-q")
    assert r.returncode == 0, r.stderr
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["execution"]["scheduler"]
    assert report["pair_selection"] == "file" and report["counts"]["pairs_done"] == 2
    assert sorted(p.name for p in (tmp_path / "out" / "pairs").iterdir()) == [
        "view_000__view_001", "view_001__view_002"]


# ------------------------------------------------------------------------- errors


@pytest.fixture(scope="module")
def tiny_ws(tmp_path_factory):
    scene = render_scene(seed=5, width=96, height=72, n_views=3, supersample=1, style="classic")
    return write_workspace(scene, tmp_path_factory.mktemp("tiny") / "ws")


def test_pairs_file_with_unknown_names_is_a_clear_error(tiny_ws, tmp_path):
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("view_000.png view_001.png\nview_000.png nope.jpg\nmissing.png view_002.png\n")
    r = run_cli("colmap", tiny_ws, "-o", tmp_path / "out", "--pairs", pairs)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr
    assert "nope.jpg" in lines[0] and "missing.png" in lines[0] and "line 2" in lines[0]
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("text, message", [
    ("view_000.png\n", "expected 'name1 name2'"),
    ("view_000.png view_000.png\n", "paired with itself"),
    ("# nothing\n", "no pairs"),
])
def test_bad_pairs_files(tiny_ws, tmp_path, text, message):
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(text)
    with pytest.raises(InputError, match=message):
        read_pairs_file(pairs, open_workspace(tiny_ws).rec)


def test_pairs_file_drops_repeats(tiny_ws, tmp_path):
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("view_000.png view_001.png\nview_001.png view_000.png  # the same\nview_000.png view_002.png\n")
    assert read_pairs_file(pairs, open_workspace(tiny_ws).rec) == [(1, 2), (1, 3)]


def test_workspace_errors(tiny_ws, tmp_path):
    with pytest.raises(InputError, match="not a folder"):
        open_workspace(tmp_path / "nowhere")
    (tmp_path / "noimages" / "sparse").mkdir(parents=True)
    with pytest.raises(InputError, match="no image folder"):
        open_workspace(tmp_path / "noimages")
    (tmp_path / "nomodel" / "images").mkdir(parents=True)
    with pytest.raises(InputError, match="no sparse model"):
        open_workspace(tmp_path / "nomodel")
    with pytest.raises(InputError, match="no COLMAP model"):
        open_workspace(tiny_ws, sparse_dir=tmp_path)
    # the CLI: exit 2, one line
    r = run_cli("colmap", tmp_path / "nomodel", "-o", tmp_path / "out")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "sparse" in r.stderr


def test_missing_image_files_are_named(tiny_ws, tmp_path):
    import shutil

    ws = tmp_path / "ws"
    shutil.copytree(tiny_ws, ws)
    (ws / "images" / "view_002.png").unlink()
    with pytest.raises(InputError, match="missing from .*view_002.png"):
        run_colmap(ws, tmp_path / "out", _cfg(), workers=1)


@pytest.mark.slow
def test_pair_without_baseline_is_skipped_with_a_reason(tmp_path, caplog):
    """Two images taken from the same centre give no depth: that pair is skipped, the others run."""
    scene = render_scene(seed=33, width=320, height=240, n_views=2, style="classic")
    ws = write_workspace(scene, tmp_path / "ws")
    rec = pycolmap.Reconstruction(str(ws / "sparse"))
    # a third image: view 0 again, from the same centre
    cam = pycolmap.Camera(rec.cameras[1].todict())
    cam.camera_id = 3
    rec.add_camera_with_trivial_rig(cam)
    rec.add_image_with_trivial_frame(pycolmap.Image(name="again.png", camera_id=3, image_id=3),
                                     rec.images[1].cam_from_world())
    rec.write_text(str(ws / "sparse"))
    (ws / "images" / "again.png").write_bytes((ws / "images" / "view_000.png").read_bytes())
    # pairs from the poses drop it before matching, with the reason
    dropped = []
    pairs, how = select_pairs(rec, _cfg(), dropped)
    assert how == "poses" and pairs == [(1, 2), (2, 3)]
    assert [(sorted(d["images"]), d["reason"][:11]) for d in dropped] == [(["again.png", "view_000.png"], "no baseline")]
    # a pairs file naming it: skipped at matching, the others run
    (tmp_path / "pairs.txt").write_text("view_000.png view_001.png\nview_000.png again.png\nview_001.png again.png\n")
    with caplog.at_level("WARNING"):
        report = run_colmap(ws, tmp_path / "out", _cfg(), pairs_file=tmp_path / "pairs.txt", workers=1)
    skipped = [e for e in report["pairs"] if e["status"] == "skipped"]
    assert [sorted(e["images"]) for e in skipped] == [["again.png", "view_000.png"]]
    assert "no baseline" in skipped[0]["reason"] and "no baseline" in caplog.text
    assert report["counts"]["pairs_done"] == 2 and report["counts"]["pairs_skipped"] == 1


# -------------------------------------------------------------------------- units


def test_pair_folder_names():
    assert pair_folder_name("a.jpg", "b.png") == "a__b"
    assert pair_folder_name("sub/dir/x.JPG", "y") == "sub_dir_x__y"


def test_covisibility_pair_selection():
    rec = pycolmap.Reconstruction()
    for i in range(1, 5):
        rec.add_camera_with_trivial_rig(pycolmap.Camera(camera_id=i, model="PINHOLE", width=100, height=100,
                                                        params=[100, 100, 50, 50]))
        im = pycolmap.Image(name=f"{i}.png", keypoints=np.full((100, 2), 50.0), camera_id=i, image_id=i)
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(np.hstack([np.eye(3), [[i], [0], [0]]])))
    # 1-2 share 40 points, 2-3 share 35, 3-4 share 10 (too few), 1-4 share 31
    k = {i: 0 for i in range(1, 5)}
    for a, b, n in ((1, 2, 40), (2, 3, 35), (3, 4, 10), (1, 4, 31)):
        for _ in range(n):
            track = pycolmap.Track()
            for i in (a, b):
                track.add_element(i, k[i])
                k[i] += 1
            rec.add_point3D(np.array([0.0, 0.0, 5.0]), track, np.zeros(3, np.uint8))
    pairs, how = select_pairs(rec, _cfg())
    assert how == "covisibility" and pairs == [(1, 2), (1, 4), (2, 3)]
    pairs, _ = select_pairs(rec, _cfg("colmap.pairs_per_image=1"))
    assert pairs == [(1, 2), (1, 4), (2, 3)]  # 4's best is 1, 3's best is 2
    with pytest.raises(InputError, match="min_covisible"):
        select_pairs(rec, _cfg("colmap.min_covisible=100"))


def _posed_model(centres, targets):
    """A model without points: PINHOLE cameras at ``centres`` looking at ``targets`` (y down)."""
    rec = pycolmap.Reconstruction()
    for i, (c, t) in enumerate(zip(centres, targets), start=1):
        z = np.asarray(t, float) - c
        z /= np.linalg.norm(z)
        x = np.cross([0.0, 1.0, 0.0], z)
        x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-9 else np.array([1.0, 0, 0])
        R = np.stack([x, np.cross(z, x), z])
        rec.add_camera_with_trivial_rig(pycolmap.Camera(camera_id=i, model="PINHOLE", width=100, height=100,
                                                        params=[100, 100, 50, 50]))
        rec.add_image_with_trivial_frame(pycolmap.Image(name=f"{i:02d}.png", camera_id=i, image_id=i),
                                         pycolmap.Rigid3d(np.hstack([R, (-R @ c).reshape(3, 1)])))
    return rec


def test_pairs_from_poses_on_a_ring():
    """16 views on a ring round an object (22.5 deg apart, like dinoSparseRing): each image's neighbours
    within 50 deg are paired, never views 67.5 deg or more apart (the all-pairs rule paired views 180 deg apart)."""
    ang = np.radians(np.arange(16) * 22.5)
    centres = np.c_[5 * np.cos(ang), np.zeros(16), 5 * np.sin(ang)]
    rec = _posed_model(centres, np.zeros((16, 3)))
    dropped = []
    pairs, how = select_pairs(rec, _cfg(), dropped)
    assert how == "poses"
    ring = lambda a, b: min((a - b) % 16, (b - a) % 16)  # noqa: E731 - steps round the ring
    assert sorted({ring(a - 1, b - 1) for a, b in pairs}) == [1, 2]
    assert len(pairs) == 32  # 16 neighbours 1 step apart + 16 at 2 steps
    assert len(dropped) == 16 * 15 // 2 - 32
    reasons = {ring(int(d["images"][0][:2]) - 1, int(d["images"][1][:2]) - 1): d["reason"] for d in dropped}
    assert reasons[3].startswith("viewing directions 67.5 deg apart") and "pair_max_view_angle_deg = 50" in reasons[3]
    assert reasons[8].startswith("viewing directions 180.0 deg apart")
    # fewer partners: the nearest only; the next ones are dropped with that reason
    dropped = []
    pairs, _ = select_pairs(rec, _cfg("colmap.pairs_per_image=1"), dropped)
    assert {ring(a - 1, b - 1) for a, b in pairs} == {1}
    assert {i for pair in pairs for i in pair} == set(range(1, 17))  # every image keeps a partner
    assert sum("nearest partners" in d["reason"] for d in dropped) == 32 - len(pairs)
    # a wider limit takes the 67.5 deg neighbours too
    pairs, _ = select_pairs(rec, _cfg("colmap.pairs_per_image=0", "colmap.pair_max_view_angle_deg=70"))
    assert sorted({ring(a - 1, b - 1) for a, b in pairs}) == [1, 2, 3]


def test_pairs_from_poses_drop_small_triangulation_angles():
    """A camera 1 cm beside another, both 5 m from the object they look at (0.11 deg): dropped with the angle."""
    centres = np.array([[0.0, 0, -5], [0.01, 0, -5], [1.0, 0, -5], [2.0, 0, -5]])
    rec = _posed_model(centres, np.zeros((4, 3)))
    dropped = []
    pairs, _ = select_pairs(rec, _cfg(), dropped)
    assert (1, 2) not in pairs and (1, 3) in pairs and (3, 4) in pairs
    (d,) = [d for d in dropped if d["images"] == ["01.png", "02.png"]]
    assert d["reason"].startswith("triangulation angle 0.11 deg")
    pairs, _ = select_pairs(rec, _cfg("geometry.min_tri_angle_deg=0"))
    assert (1, 2) in pairs


def test_pairs_file_overrides_pairs_from_poses(tiny_ws, tmp_path):
    rec = pycolmap.Reconstruction(str(tiny_ws / "sparse"))
    f = tmp_path / "p.txt"
    f.write_text("view_000.png view_002.png\n")
    assert read_pairs_file(f, rec) == [(1, 3)]


def test_quantisation_links_pairs_into_tracks():
    """Endpoints of two pairs that fall on the same spot of the shared image share one keypoint."""
    rng = np.random.default_rng(0)
    uv = rng.uniform(5, 95, (500, 2))
    shift = np.array([3.0, 0.0])
    pm = [PairMatches(1, 2, uv, uv + shift, np.ones(500)),
          PairMatches(2, 3, uv + shift + rng.normal(0, 0.05, (500, 2)), uv + 2 * shift, np.ones(500))]
    q = quantise_matches(pm, cell_size=2.0, max_error=0.75)
    for image_id, kp in q.keypoints.items():
        cells = np.round(kp / 2.0).astype(np.int64)
        assert len(np.unique(cells, axis=0)) == len(kp)
    m12, m23 = q.matches[(1, 2)], q.matches[(2, 3)]
    assert len(m12) > 300 and len(m23) > 300
    # the quantised matches stay within 2 * max_error of the true displacement
    d = q.keypoints[2][m12[:, 1]] - q.keypoints[1][m12[:, 0]]
    assert np.all(np.linalg.norm(d - shift, axis=1) <= 1.5 + 1e-6)
    # image 2's keypoints are shared by both pairs: three-view tracks
    assert len(np.intersect1d(m12[:, 1], m23[:, 0])) > 200


def test_images_are_read_without_exif_rotation(tmp_path):
    """COLMAP ignores the EXIF orientation tag, so the workspace mode must too."""
    import struct

    from sefm_recon.io.images import read_image

    img = np.zeros((80, 120, 3), np.uint8)
    img[:, :60] = (255, 0, 0)
    ok, buf = cv2.imencode(".jpg", img)
    assert ok
    tiff = b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 1) + struct.pack("<HHIHH", 0x0112, 3, 1, 6, 0)
    tiff += struct.pack("<I", 0)
    payload = b"Exif\x00\x00" + tiff
    data = buf.tobytes()
    data = data[:2] + b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload + data[2:]
    path = tmp_path / "rotated.jpg"
    path.write_bytes(data)
    assert read_image(path).shape == (120, 80, 3)  # the pair mode honours the tag
    assert read_workspace_image(path).shape == (80, 120, 3)
