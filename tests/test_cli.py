"""The command line as a user meets it: outputs, exit codes, messages."""

import json
import subprocess
import sys

import numpy as np
import pycolmap
import pytest

from sefm_recon.geometry.two_view import TwoView, epipolar_distances
from sefm_recon.io.ply import read_mesh, read_ply_header, read_point_cloud

from .conftest import SAMPLE


def run_cli(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "sefm_recon", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)


def _sample_args(out):
    cam = (SAMPLE / "camera.txt").read_text().strip()
    return ["pair", SAMPLE / "images/view_000.jpg", SAMPLE / "images/view_001.jpg", "-o", out, "--camera", cam, "-q"]


@pytest.fixture(scope="module")
def demo_out(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "out"
    r = run_cli(*_sample_args(out))
    assert r.returncode == 0, r.stderr
    return out


def test_pair_writes_every_output(demo_out):
    names = {p.name for p in demo_out.iterdir()}
    assert {"matches.npz", "points.ply", "mesh.ply", "sparse", "matches.png", "report.json"} <= names
    assert not [p for p in demo_out.parent.iterdir() if p.name.startswith(".")]  # no staging left over
    report = json.loads((demo_out / "report.json").read_text())
    for key in ("version", "config", "timings_s", "counts", "image_size"):
        assert key in report
    assert report["libraries"]["numpy"] == np.__version__  # (what the figures were computed with)
    counts = report["counts"]
    for key in ("sift_matches", "rough_matches", "dense_matches", "valid_matches", "points"):
        assert key in counts
    assert counts["valid_matches"] >= 50_000
    # dense_matches counts the line images' cells with a disparity, valid_matches the pixels
    # of image 1 read back from them (rows about 1 px apart, as many as the pixels or fewer)
    # and the plane fill's: neither bounds the other
    assert counts["points"] <= counts["valid_matches"] and counts["dense_matches"] >= 50_000
    assert report["image_size"] == [[640, 480], [640, 480]]
    f = float((SAMPLE / "camera.txt").read_text().split()[4])  # PINHOLE W H fx fy cx cy
    assert [c["source"] for c in report["focal_length"]] == ["given", "given"]
    assert report["focal_length"][0]["px"] == pytest.approx(f, abs=1.0)
    m = np.load(demo_out / "matches.npz")
    assert m["uv1"].shape == m["uv2"].shape == (counts["points"], 2)  # one match per point of points.ply
    assert len(m["score"]) == len(m["uv1"])
    header = read_ply_header(demo_out / "points.ply")
    assert header["format"].startswith("binary")
    props = [name for _, name in header["elements"]["vertex"]["properties"]]
    assert props == ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"]
    assert header["elements"]["vertex"]["count"] == counts["points"]


def test_pair_mesh_is_the_points_surface(demo_out):
    """mesh.ply (the default grid mesh): a coloured sheet facing camera 1 (at the origin) on the points."""
    v, f, c, n = read_mesh(demo_out / "mesh.ply")
    xyz, _, _ = read_point_cloud(demo_out / "points.ply")
    assert 10_000 <= len(v) <= 150_000 and len(f) >= len(v)  # output.mesh_max_points bounds the vertices
    assert c is not None and n is not None
    facing = np.einsum("ij,ij->i", np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), -v[f[:, 0]])
    assert np.mean(facing > 0) > 0.99
    # each vertex, a mean of nearby points, lies within the points' depth range
    lo, hi = np.percentile(xyz[:, 2], [0, 100])
    assert lo <= v[:, 2].min() and v[:, 2].max() <= hi


def test_pair_recovers_the_true_pose_and_epipolar_geometry(demo_out):
    truth = pycolmap.Reconstruction(str(SAMPLE / "sparse"))
    model = pycolmap.Reconstruction(str(demo_out / "sparse"))
    assert len(model.images) == 2 and model.num_points3D() > 10_000

    def rel(rec):
        ims = sorted(rec.images.values(), key=lambda im: im.name)
        a, b = ims[0].cam_from_world(), ims[1].cam_from_world()
        rel = b * a.inverse()
        return rel.rotation.matrix(), np.asarray(rel.translation)

    R_true, t_true = rel(truth)
    R_est, t_est = rel(model)
    rot_err = np.degrees(np.arccos(np.clip((np.trace(R_true.T @ R_est) - 1) / 2, -1, 1)))
    cosang = t_true @ t_est / np.linalg.norm(t_true) / np.linalg.norm(t_est)
    assert rot_err < 0.5
    assert np.degrees(np.arccos(np.clip(cosang, -1, 1))) < 2.0
    # dense matches lie on the TRUE epipolar lines
    cam = truth.cameras[1]
    K = np.asarray(cam.calibration_matrix())
    F = TwoView(K, K, R_true, t_true).F
    m = np.load(demo_out / "matches.npz")
    d = epipolar_distances(F, m["uv1"].astype(float), m["uv2"].astype(float))
    assert np.median(d) < 0.5
    assert model.compute_mean_reprojection_error() < 1.0


def test_existing_output_is_refused_and_untouched(demo_out):
    before = {p.name: p.stat().st_mtime_ns for p in demo_out.iterdir()}
    r = run_cli(*_sample_args(demo_out))
    assert r.returncode == 2
    assert "not empty" in r.stderr and "--overwrite" in r.stderr
    assert "Traceback" not in r.stderr
    assert {p.name: p.stat().st_mtime_ns for p in demo_out.iterdir()} == before


@pytest.mark.parametrize(
    "args, message",
    [
        (["pair", "missing1.jpg", SAMPLE / "images/view_001.jpg"], "image not found"),
        (["pair", SAMPLE / "images/view_000.jpg", SAMPLE / "images/view_001.jpg", "--camera", "PINHOLE 640 480 1"],
         "takes 4 parameters"),
        (["pair", SAMPLE / "images/view_000.jpg", SAMPLE / "images/view_001.jpg", "--camera", "FISH 640 480 1 2"],
         "unknown camera model"),
        (["pair", SAMPLE / "images/view_000.jpg", SAMPLE / "images/view_001.jpg", "--camera",
          "PINHOLE 1000 750 800 800 500 375"], "is 640x480"),
        (["pair", SAMPLE / "images/view_000.jpg", SAMPLE / "images/view_001.jpg", "--set", "rough.nope=1"],
         "unknown config key"),
        (["pair", SAMPLE / "images/view_000.jpg", SAMPLE / "images/view_001.jpg", "--set", "output.poisson_depth=x"],
         "expected int"),
    ],
)
def test_input_errors_exit_2_with_one_line(tmp_path, args, message):
    out = tmp_path / "out"
    r = run_cli(*args, "-o", out)
    assert r.returncode == 2, r.stderr
    assert message in r.stderr
    assert "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not out.exists()


def test_unrelated_images_are_refused(tmp_path):
    rng = np.random.default_rng(0)
    import cv2

    for i in range(2):
        cv2.imwrite(str(tmp_path / f"noise{i}.png"), rng.integers(0, 255, (240, 320, 3), dtype=np.uint8))
    r = run_cli("pair", tmp_path / "noise0.png", tmp_path / "noise1.png", "-o", tmp_path / "out")
    assert r.returncode == 2
    assert "too little overlap" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "out").exists()


def test_help_lists_the_pair_command():
    r = run_cli("--help")
    assert r.returncode == 0 and "pair" in r.stdout
    r = run_cli("pair", "--help")
    assert "--camera" in r.stdout and "--overwrite" in r.stdout


def test_allocator_settings_respect_the_users_own(monkeypatch):
    from sefm_recon import memory

    monkeypatch.setenv("MALLOC_ARENA_MAX", "2")
    assert memory.keep_freed_memory() is False  # the user's MALLOC_* settings win
    monkeypatch.delenv("MALLOC_ARENA_MAX")
    monkeypatch.setattr(memory.sys, "platform", "darwin")
    assert memory.keep_freed_memory() is False


def test_allocator_settings_apply_on_glibc():
    import os
    import platform

    from sefm_recon import memory

    if not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc" or \
            "GLIBC_TUNABLES" in os.environ or any(k.startswith("MALLOC_") for k in os.environ):
        pytest.skip("needs glibc without user allocator settings")
    assert memory.keep_freed_memory() is True
    memory.release_freed_memory()  # and back, harmlessly


def test_eval_tables_name_the_libraries_they_were_made_with(tmp_path):
    import cv2

    results = tmp_path / "results.md"
    results.write_text("# Results\n<!-- eval:generated begin -->\n<!-- eval:generated end -->\n")
    r = run_cli("eval", "--seeds", 0, "--size", "200x150", "-q", "--results", results)
    assert r.returncode == 0, r.stderr
    section = results.read_text().split("<!-- eval:generated begin -->")[1].split("<!-- eval:generated end -->")[0]
    last = section.strip().splitlines()[-1]
    assert last.startswith("Libraries: sefm-recon ")
    assert f"numpy {np.__version__}," in last and f"opencv {cv2.__version__}" in last
    assert "| 0 | lateral | SeFM (true pose) |" in section  # (the table above it)
