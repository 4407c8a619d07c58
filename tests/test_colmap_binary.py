"""The README's COLMAP steps, run verbatim with the real ``colmap`` binary (COLMAP 3.8 on Debian 12).

The workspace is the issue's case: a model made by COLMAP's own SfM (SIFT points,
so its images hold other 2-D points than ``database.db``). Skips where no
``colmap`` binary is installed (``make test`` installs it when root on Debian).
"""

from __future__ import annotations

import re
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np  # before pycolmap (see test_colmap_plugin)
import pycolmap
import pytest

from sefm_recon.evaluate import surface_distances
from sefm_recon.io.colmap_database import LEGACY_IMAGE_COLUMNS, add_legacy_columns
from sefm_recon.synthetic import align_to_truth, colmap_sfm, render_scene, write_workspace

ROOT = Path(__file__).resolve().parents[1]
COLMAP = shutil.which("colmap")
needs_colmap = pytest.mark.skipif(COLMAP is None, reason="no colmap binary on PATH (apt-get install colmap)")


def readme_colmap_steps() -> list[str]:
    """The README's commands after ``sefm-recon colmap`` on ``dense/``, continuation lines joined."""
    text = (ROOT / "README.md").read_text()
    block = text.split("### A COLMAP workspace", 1)[1].split("\n\n")[2]  # the indented command block
    lines = block.replace("\\\n", " ").splitlines()
    cmds = [re.sub(r"\s+#.*$", "", ln).strip() for ln in lines]
    return [c for c in cmds if (c.startswith("mkdir") or c.startswith("colmap "))
            and "automatic_reconstructor" not in c and "colmap gui" not in c]


def _colmap_version() -> str:
    r = subprocess.run([COLMAP, "-h"], capture_output=True, text=True)
    m = re.search(r"COLMAP (\S+)", r.stdout + r.stderr)
    return m.group(1) if m else "?"


def _analyzer(out: str) -> dict[str, float]:
    """``colmap model_analyzer``'s figures (its log goes to stderr or stdout, by version)."""
    figures = {}
    for key, name in (("Registered images", "images"), ("Points", "points"), ("Mean track length", "track"),
                      ("Mean reprojection error", "error")):
        m = re.search(rf"{key}:\s*([0-9.]+)", out)
        if m:
            figures[name] = float(m.group(1))
    return figures


def test_readme_lists_the_steps():
    steps = readme_colmap_steps()
    assert any("point_triangulator" in s and "dense/sparse_poses" in s for s in steps)
    assert any(s.startswith("colmap model_analyzer") for s in steps)
    assert any("colmap mapper" in s for s in steps)


@pytest.fixture(scope="module")
def scene():
    return render_scene(seed=33, width=320, height=240, n_views=3, style="classic")


@pytest.fixture(scope="module")
def colmap_run(scene, tmp_path_factory):
    """SfM workspace ``ws`` (pycolmap's SIFT + mapping), then ``sefm-recon colmap ws -o dense``, then the README steps."""
    if COLMAP is None:
        pytest.skip("no colmap binary on PATH (apt-get install colmap)")
    root = tmp_path_factory.mktemp("colmap_binary")
    write_workspace(scene, root / "ws")
    rec = colmap_sfm(root / "ws")
    assert rec.num_reg_images() == 3
    r = subprocess.run([sys.executable, "-m", "sefm_recon", "colmap", "ws", "-o", "dense", "--workers", "1", "-q"],
                       cwd=root, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    logs = {}
    for step in readme_colmap_steps():
        p = subprocess.run(["bash", "-c", step], cwd=root, capture_output=True, text=True, timeout=600)
        assert p.returncode == 0, f"{step}\n{p.stderr[-3000:]}"
        logs[step] = p.stdout + p.stderr
    return root, logs


@needs_colmap
@pytest.mark.slow
def test_colmap_triangulates_the_database(colmap_run, scene):
    root, logs = colmap_run
    analyzed = _analyzer(next(v for k, v in logs.items() if k.startswith("colmap model_analyzer")))
    tri = pycolmap.Reconstruction(str(root / "dense" / "tri"))
    ours = pycolmap.Reconstruction(str(root / "dense" / "sparse"))
    assert analyzed["images"] == 3 and analyzed["points"] == tri.num_points3D()
    # as many points as pycolmap's triangulation of the same database (the same options): 3.8 finds the same tracks
    assert tri.num_points3D() >= 0.9 * ours.num_points3D() > 3000
    assert analyzed["error"] < 1.0 and analyzed["track"] >= 2.0
    # the points lie on the true surface (up to the SfM model's own error, as in test_colmap_plugin)
    user = pycolmap.Reconstruction(str(root / "ws" / "sparse" / "0"))
    s, R, t = align_to_truth(user, scene)
    P = np.array([p.xyz for p in tri.points3D.values()])
    d = surface_distances(s * P @ R.T + t, scene.views)
    assert np.mean(d <= 0.03 * scene.meta["scene_size"]) >= 0.9


@needs_colmap
@pytest.mark.slow
def test_sparse_poses_agrees_with_the_database_not_the_user_model(colmap_run):
    root, _ = colmap_run
    poses = pycolmap.Reconstruction(str(root / "dense" / "sparse_poses"))
    user = pycolmap.Reconstruction(str(root / "ws" / "sparse" / "0"))
    assert poses.num_points3D() == 0 and poses.num_reg_images() == 3
    db = pycolmap.Database.open(str(root / "dense" / "database.db"))
    try:
        for iid, im in poses.images.items():
            assert im.num_points2D() == db.num_keypoints_for_image(iid) > 1000
            assert np.allclose([p.xy for p in im.points2D], db.read_keypoints(iid)[:, :2], atol=1e-3)
            # the user's model holds its SIFT points: a different count (what made COLMAP stop before)
            assert user.images[iid].num_points2D() != im.num_points2D()
            assert np.allclose(im.cam_from_world().matrix(), user.images[iid].cam_from_world().matrix())
    finally:
        db.close()


@needs_colmap
@pytest.mark.slow
def test_colmap_mapper_registers_every_image(colmap_run):
    root, _ = colmap_run
    models = [pycolmap.Reconstruction(str(p)) for p in sorted((root / "dense" / "mapped").iterdir()) if p.is_dir()]
    assert models and max(m.num_reg_images() for m in models) == 3


@needs_colmap
def test_colmap_version_is_reported():
    """The README names the binary's version the suite runs; say which one ran."""
    v = _colmap_version()
    assert re.match(r"\d+\.\d+", v), v
    if v.startswith("3.8"):
        assert "3.8" in (ROOT / "README.md").read_text()


def test_legacy_image_columns(tmp_path):
    """pycolmap 4's images table gains COLMAP 3.8's prior columns, after camera_id, NULL; pycolmap still reads it."""
    path = tmp_path / "db.db"
    db = pycolmap.Database.open(str(path))
    cam = pycolmap.Camera(camera_id=1, model="PINHOLE", width=10, height=10, params=[10, 10, 5, 5])
    db.write_camera(cam, use_camera_id=True)
    db.write_image(pycolmap.Image(name="a.png", camera_id=1, image_id=7), use_image_id=True)
    db.close()
    assert add_legacy_columns(path) == list(LEGACY_IMAGE_COLUMNS)
    assert add_legacy_columns(path) == []  # idempotent
    con = sqlite3.connect(str(path))
    cols = [r[1] for r in con.execute("PRAGMA table_info(images)")]
    assert cols == ["image_id", "name", "camera_id", *LEGACY_IMAGE_COLUMNS]
    assert con.execute("SELECT * FROM images").fetchall() == [(7, "a.png", 1, *[None] * 7)]
    con.close()
    db = pycolmap.Database.open(str(path))
    try:
        assert [(im.image_id, im.name, im.camera_id) for im in db.read_all_images()] == [(7, "a.png", 1)]
        db.write_image(pycolmap.Image(name="b.png", camera_id=1, image_id=8), use_image_id=True)
        assert db.num_images() == 2
    finally:
        db.close()
