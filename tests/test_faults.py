"""Faults a user meets (issue 21): a signal inside a kernel, OUT on another file system, a full disk, an
implausible camera, bytes that are not UTF-8 in a path, an elongated photo, ``-o ""`` and ``--overwrite``.

Each runs the real command line where the user meets it. Tests that mount a
tmpfs need root and ``mount``; they skip elsewhere.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "GLOG_minloglevel": "2", "PYTHONUNBUFFERED": "1"}


def cli(*args, timeout=300, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sefm_recon", *args], capture_output=True, text=True,
                          timeout=timeout, env=ENV, cwd=cwd)


def _arg(x) -> str | bytes:
    return x if isinstance(x, (str, bytes)) else str(x)


def hidden(folder: Path) -> list[str]:
    """Hidden entries (staging folders, temporary files) in ``folder``."""
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(".")) if folder.is_dir() else []


@pytest.fixture(scope="module")
def pair(tmp_path_factory, small_scene):
    """The 320x240 pair with ground truth as PNGs, and its camera string."""
    d = tmp_path_factory.mktemp("faults")
    v1, v2 = small_scene.views
    for name, v in (("a.png", v1), ("b.png", v2)):
        assert cv2.imwrite(str(d / name), cv2.cvtColor(v.image, cv2.COLOR_RGB2BGR))
    K = v1.K
    cam = f"PINHOLE 320 240 {K[0, 0]:.9g} {K[1, 1]:.9g} {K[0, 2]:.9g} {K[1, 2]:.9g}"
    return {"a": d / "a.png", "b": d / "b.png", "cam": cam, "dir": d}


def pair_args(pair, out, *extra) -> list:
    return ["pair", str(pair["a"]), str(pair["b"]), "-o", _arg(out), "--camera", pair["cam"], "-q",
            "--set", "output.poisson_depth=6", *extra]


# ------------------------------------------------------ 1. signals inside a numba kernel

#: The CLI with a numba kernel that runs for about a second and returns a tuple (so numba calls back into
#: Python to box it) in front of the output writer, when the staging folder exists.
_SLOW_KERNEL = textwrap.dedent("""
    import sys
    import numpy as np
    from numba import njit, prange
    from sefm_recon import cli, pipeline

    @njit(parallel=True)
    def spin(n, steps):
        a = np.zeros(n)
        b = np.zeros(n)
        for i in prange(n):
            x = 0.0
            for j in range(steps):
                x += np.sin(i + j * 1e-3)
            a[i] = x
        return a, b

    spin(2, 2)
    write = pipeline.write_pair_outputs

    def slow_write(*args, **kwargs):
        print("kernel starts", file=sys.stderr, flush=True)
        spin(64, 1_000_000)
        return write(*args, **kwargs)

    pipeline.write_pair_outputs = slow_write
    sys.exit(cli.main(sys.argv[1:]))
""")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_during_a_numba_kernel_exits_130_and_leaves_nothing(pair, tmp_path, sig):
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-c", _SLOW_KERNEL, *pair_args(pair, out, "--set", "output.mesh=false")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    lines = []
    for line in proc.stderr:
        lines.append(line)
        if line.startswith("kernel starts"):
            proc.send_signal(sig)
            break
    lines.extend(proc.stderr)
    rc = proc.wait(timeout=120)
    err = "".join(lines)
    assert any(x.startswith("kernel starts") for x in lines), err
    assert rc == 130, err
    assert err.strip().splitlines()[-1] == "sefm-recon: interrupted", err
    assert "SystemError" not in err and "Traceback" not in err
    assert not out.exists() and hidden(tmp_path) == []


# ------------------------------------------------------ 2. OUT on another file system


@pytest.fixture
def tmpfs(tmp_path):
    """Mount a tmpfs of the given size in MB at a new folder under tmp_path; unmounted afterwards."""
    mounted = []

    def mount(size_mb: float, name: str = "mnt") -> Path:
        if os.geteuid() != 0 or shutil.which("mount") is None:
            pytest.skip("mounting a tmpfs needs root and mount(8)")
        point = tmp_path / name
        point.mkdir()
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={int(size_mb * 1024)}k", "tmpfs", str(point)],
                           capture_output=True, text=True)
        if r.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
        mounted.append(point)
        return point

    yield mount
    for point in mounted:
        subprocess.run(["umount", "-l", str(point)], capture_output=True)


def test_pair_into_a_mounted_out(pair, tmpfs):
    """OUT is a mount point (a Docker volume, a tmpfs): the staging folder lives on OUT's file system."""
    out = tmpfs(64)
    r = cli(*pair_args(pair, out, "--set", "output.mesh=false"))
    assert r.returncode == 0, r.stderr
    assert {"matches.npz", "points.ply", "sparse", "report.json"} <= {p.name for p in out.iterdir()}
    assert hidden(out) == [] and hidden(out.parent) == []
    # again with --overwrite: the old results are replaced in place, the user's file is kept
    (out / "mine.txt").write_text("mine")
    r = cli(*pair_args(pair, out, "--set", "output.mesh=false", "--overwrite"))
    assert r.returncode == 0, r.stderr
    assert (out / "mine.txt").read_text() == "mine" and (out / "report.json").is_file()
    assert hidden(out) == [] and hidden(out.parent) == []


def test_colmap_into_a_mounted_out(tmpfs):
    out = tmpfs(64)
    r = cli("colmap", str(ROOT / "data_samples" / "scene"), "-o", str(out), "-q")
    assert r.returncode == 0, r.stderr
    assert {"pairs", "fused.ply", "database.db", "sparse", "report.json"} <= {p.name for p in out.iterdir()}
    assert hidden(out) == [] and hidden(out.parent) == []


# ------------------------------------------------------ 8. -o "" and --overwrite


def test_empty_output_name_is_refused(pair, tmp_path):
    r = cli(*pair_args(pair, ""), cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines() == [r.stderr.strip()] and "output folder is an empty name" in r.stderr
    assert list(tmp_path.iterdir()) == []
    r = cli("colmap", str(ROOT / "data_samples" / "scene"), "-o", "", "-q", cwd=tmp_path)
    assert r.returncode == 2 and "output folder is an empty name" in r.stderr, r.stderr


def test_overwrite_keeps_the_users_files_inside_sparse(pair, tmp_path):
    out = tmp_path / "out"
    assert cli(*pair_args(pair, out, "--set", "output.mesh=false")).returncode == 0
    old_points = (out / "sparse" / "points3D.bin").read_bytes()
    (out / "sparse" / "notes.txt").write_text("mine")
    (out / "sparse" / "0").mkdir()
    (out / "sparse" / "0" / "cameras.txt").write_text("my own model")
    (out / "sparse" / "empty").mkdir()
    r = cli(*pair_args(pair, out, "--set", "output.mesh=false", "--set", "output.sparse_max_points=500",
                       "--overwrite"))
    assert r.returncode == 0, r.stderr
    assert (out / "sparse" / "points3D.bin").read_bytes() != old_points  # the model is the new one
    assert (out / "sparse" / "notes.txt").read_text() == "mine"
    assert (out / "sparse" / "0" / "cameras.txt").read_text() == "my own model"
    assert (out / "sparse" / "empty").is_dir()
    assert hidden(out) == [] and hidden(tmp_path) == []


@pytest.mark.parametrize("swap", ["exchange", "per item"])
def test_overwrite_keeps_the_users_files_inside_colmap_pairs(tmp_path, monkeypatch, swap):
    """``colmap``'s result folders: a pair folder the new run does not write loses only the tool's files."""
    from sefm_recon.colmap_plugin import COLMAP_OWNED, COLMAP_RESULTS
    from sefm_recon.io.output import StagedOutput

    out = tmp_path / "out"
    for rel in ("pairs/a__b/matches.npz", "pairs/a__b/points.ply", "pairs/a__b/notes.txt",
                "pairs/old__pair/matches.npz", "pairs/old__pair/points.ply", "pairs/old__pair/mine/x.txt",
                "sparse/cameras.bin", "sparse/mine.db", "fused.ply", "report.json", "keep.txt"):
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_text("old")
    if swap == "per item":
        monkeypatch.chdir(out)  # the current folder is never renamed: results are moved one by one
    with StagedOutput(out, overwrite=True, results=COLMAP_RESULTS, owned=COLMAP_OWNED) as stage:
        for rel in ("pairs/a__b/matches.npz", "pairs/a__b/points.ply", "sparse/cameras.bin", "report.json"):
            (stage / rel).parent.mkdir(parents=True, exist_ok=True)
            (stage / rel).write_text("new")
    files = {str(p.relative_to(out)): p.read_text() for p in out.rglob("*") if p.is_file()}
    assert files == {"pairs/a__b/matches.npz": "new", "pairs/a__b/points.ply": "new", "pairs/a__b/notes.txt": "old",
                     "pairs/old__pair/mine/x.txt": "old", "sparse/cameras.bin": "new", "sparse/mine.db": "old",
                     "report.json": "new", "keep.txt": "old"}
    assert hidden(out) == [] and hidden(tmp_path) == []


# ------------------------------------------------------ 6. bytes that are not UTF-8 in paths

SAMPLE = ROOT / "data_samples" / "scene"


def test_paths_with_bytes_that_are_not_utf8(tmp_path):
    """``-o $'out\\xe9'`` crashed OpenCV's writer (exit 139); an image named so failed after the run (exit 1)."""
    base = os.fsencode(tmp_path)
    image2 = base + b"/view\xe9.jpg"
    shutil.copy(SAMPLE / "images" / "view_001.jpg", os.fsdecode(image2))
    out = base + b"/out\xe9"
    r = subprocess.run([sys.executable, "-m", "sefm_recon", "pair", os.fsencode(SAMPLE / "images" / "view_000.jpg"),
                        image2, "-o", out, "--camera", (SAMPLE / "camera.txt").read_text().strip(), "--max-size", "320",
                        "--set", "output.poisson_depth=6"], capture_output=True, env=ENV, timeout=300)
    assert r.returncode == 0, r.stderr.decode(errors="replace")
    assert b"Traceback" not in r.stderr and b"matches" in r.stdout
    folder = Path(os.fsdecode(out))
    assert {p.name for p in folder.iterdir()} == {"matches.npz", "points.ply", "mesh.ply", "sparse", "matches.png",
                                                  "report.json"}
    assert hidden(tmp_path) == []
    report = json.loads((folder / "report.json").read_text())
    assert os.fsencode(report["images"][1]) == b"view\xe9.jpg"
    assert b"view\xe9.jpg\x00" in (folder / "sparse" / "images.bin").read_bytes()  # COLMAP's name: the file's bytes
    png = cv2.imdecode(np.fromfile(folder / "matches.png", np.uint8), cv2.IMREAD_COLOR)
    assert png is not None and png.shape[0] > 100
    assert len(np.load(folder / "matches.npz")["uv1"]) == report["counts"]["valid_matches"] > 10_000


# ------------------------------------------------------ 4. implausible cameras


def _exif_focal_35mm(f35: int) -> bytes:
    """An EXIF APP1 segment holding only FocalLengthIn35mmFilm (0xA405) in its Exif sub-IFD (big-endian TIFF)."""
    import struct

    ifd0 = struct.pack(">H", 1) + struct.pack(">HHII", 0x8769, 4, 1, 8 + 2 + 12 + 4) + struct.pack(">I", 0)
    sub = struct.pack(">H", 1) + struct.pack(">HHIHH", 0xA405, 3, 1, f35, 0) + struct.pack(">I", 0)
    payload = b"Exif\x00\x00MM" + struct.pack(">HI", 42, 8) + ifd0 + sub
    return b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload


@pytest.mark.parametrize("source", ["--camera", "EXIF"])
@pytest.mark.parametrize("fov", ["wide", "narrow"])
def test_implausible_field_of_view_is_refused(pair, tmp_path, source, fov):
    """f = 9.2 px on a 320x240 photo sees 173 deg (in EXIF: a 1 mm lens on 35 mm film); f = 20000 px sees 0.9 deg."""
    out = tmp_path / "out"
    f = {"wide": 9.245, "narrow": 20000}[fov]
    if source == "--camera":
        args = ["pair", str(pair["a"]), str(pair["b"]), "-o", str(out), "-q", "--set", "output.mesh=false",
                "--camera", f"SIMPLE_RADIAL 320 240 {f} 160 120 0"]
        expected = [f"bad camera 'SIMPLE_RADIAL 320 240 {f} 160 120 0'"]
    else:
        jpg = cv2.imencode(".jpg", cv2.imread(str(pair["a"])), [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
        f35 = {"wide": 1, "narrow": 2200}[fov]  # f = f35 * 400 px / 43.27 mm (the diagonals)
        (tmp_path / "a.jpg").write_bytes(jpg[:2] + _exif_focal_35mm(f35) + jpg[2:])
        args = ["pair", str(tmp_path / "a.jpg"), str(pair["b"]), "-o", str(out), "-q", "--set", "output.mesh=false"]
        expected = ["implausible camera from the EXIF data of a.jpg", "SIMPLE_RADIAL 320 240", "--camera"]
    r = cli(*args, timeout=120)
    assert r.returncode == 2, r.stderr
    line = r.stderr.strip()
    assert len(line.splitlines()) == 1 and "Traceback" not in line
    for phrase in expected + ["deg across the 320 px width, a camera sees 1 to 170 deg"]:
        assert phrase in line, (phrase, line)
    assert ("sees 173.4 deg" if fov == "wide" else "sees 0.9 deg") in line
    assert not out.exists() and hidden(tmp_path) == []


# ------------------------------------------------------ 7. elongated photos


def test_sift_scale_keeps_ordinary_photos_and_spares_strips():
    from sefm_recon.geometry.two_view import sift_scale

    for w, h in ((6000, 4000), (4000, 3000), (1920, 1080), (3000, 4000), (2048, 1024)):
        assert sift_scale(w, h, 1024) == pytest.approx(1024 / max(w, h))  # up to 2:1: the longer side, as before
    assert sift_scale(4000, 100, 1024) == 1.0 and sift_scale(100, 4000, 1024) == 1.0
    assert sift_scale(8000, 1000, 1024) == pytest.approx(np.sqrt(1024 * 1024 / 2 / 8e6))
    assert sift_scale(640, 480, 1024) == 1.0 and sift_scale(6000, 4000, 0) == 1.0


def test_a_textured_4000x100_pair_reconstructs(tmp_path):
    """SIFT at 1024 px on the longer side kept 26 rows of a 4000x100 strip: 'too little overlap/texture'."""
    from sefm_recon.synthetic import render_scene

    scene = render_scene(seed=3, width=4000, height=100, style="classic")
    for v in scene.views:
        assert cv2.imwrite(str(tmp_path / v.name), cv2.cvtColor(v.image, cv2.COLOR_RGB2BGR))
    out = tmp_path / "out"
    r = cli("pair", str(tmp_path / "view_000.png"), str(tmp_path / "view_001.png"), "-o", str(out), "-q",
            "--set", "output.mesh=false")
    assert r.returncode == 0, r.stderr
    counts = json.loads((out / "report.json").read_text())["counts"]
    assert counts["sift_inliers"] >= 30 and counts["points"] > 50_000, counts


# ------------------------------------------------------ 3. a full disk

_NO_SPACE = (r"^sefm-recon: error: no space left on the device: (more than )?\d+ MB needed for the results in .+, "
             r"\d+ MB free$")

#: The CLI without the free-space check before writing, so that the writers themselves meet the full disk.
_NO_PRECHECK = textwrap.dedent("""
    import sys
    from sefm_recon import cli
    from sefm_recon.io import output
    output.require_space = lambda folder, estimate, where=None: 0
    sys.exit(cli.main(sys.argv[1:]))
""")


def _assert_no_space(r: subprocess.CompletedProcess, mount: Path) -> None:
    import re

    assert r.returncode == 2, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and re.match(_NO_SPACE, r.stderr.strip()), r.stderr
    assert list(mount.iterdir()) == []  # nothing half-written, no staging folder
    assert shutil.disk_usage(mount).used < 64 << 10


@pytest.fixture(scope="module")
def output_sizes(pair, tmp_path_factory):
    """Bytes of a complete result of the pair (``pair``) and of the sample workspace (``colmap``)."""
    d = tmp_path_factory.mktemp("sizes")
    assert cli(*pair_args(pair, d / "pair")).returncode == 0
    assert cli("colmap", str(SAMPLE), "-o", str(d / "colmap"), "-q").returncode == 0
    return {k: sum(p.stat().st_size for p in (d / k).rglob("*") if p.is_file()) for k in ("pair", "colmap")}


@pytest.mark.parametrize("command", ["pair", "colmap"])
def test_full_disk_is_refused_before_writing(pair, tmpfs, output_sizes, command):
    mount = tmpfs(output_sizes[command] / 2 / 2**20)
    args = pair_args(pair, mount / "out") if command == "pair" else ["colmap", str(SAMPLE), "-o", str(mount / "out"),
                                                                     "-q"]
    _assert_no_space(cli(*args), mount)


@pytest.mark.parametrize("command, share", [("pair", 0.1), ("pair", 0.6), ("colmap", 0.3), ("colmap", 0.85)])
def test_full_disk_while_writing(pair, tmpfs, output_sizes, command, share):
    """Without the check before writing: numpy, open3d, pycolmap and sqlite meet the full disk, at shares of
    the result's size (open3d and pycolmap report success on a truncated file; sqlite says 'No registered
    database factory succeeded')."""
    mount = tmpfs(output_sizes[command] * share / 2**20)
    args = pair_args(pair, mount / "out") if command == "pair" else ["colmap", str(SAMPLE), "-o", str(mount / "out"),
                                                                     "-q"]
    r = subprocess.run([sys.executable, "-c", _NO_PRECHECK, *args], capture_output=True, text=True, env=ENV,
                       timeout=300)
    _assert_no_space(r, mount)


def test_full_disk_simulated_before_writing(pair, tmp_path, monkeypatch):
    """No root needed: the device reports 1 MB free; run_pair refuses before writing anything."""
    from sefm_recon.config import load_config
    from sefm_recon.errors import InputError
    from sefm_recon.pipeline import run_pair

    real = shutil.disk_usage
    monkeypatch.setattr(shutil, "disk_usage", lambda p: real(p)._replace(free=1 << 20))
    out = tmp_path / "out"
    cfg = load_config(None, ["output.poisson_depth=6", "output.progress=false"])
    with pytest.raises(InputError, match=r"no space left on the device: \d+ MB needed for the results in .*, 1 MB fr"):
        run_pair(pair["a"], pair["b"], out, cfg, camera=pair["cam"])
    assert not out.exists() and hidden(tmp_path) == []


def test_full_disk_simulated_truncated_file(tmp_path, monkeypatch):
    """No root needed: a file system that takes the writes and leaves a truncated file (as a full device can
    where the writer does not check, open3d's mesh writer among them): the mesh's writer says 'no space left'
    and the staging folder is removed."""
    import errno
    import io

    from sefm_recon.io import ply
    from sefm_recon.io.output import StagedOutput
    from sefm_recon.io.ply import write_mesh
    from sefm_recon.io.space import NoSpaceError

    real_usage = shutil.disk_usage

    class Truncating(io.FileIO):
        def close(self):
            if not self.closed:
                self.flush()
                os.truncate(self.name, os.path.getsize(self.name) // 2)
            super().close()

    monkeypatch.setattr(ply, "open", lambda path, mode: Truncating(path, mode), raising=False)
    monkeypatch.setattr(shutil, "disk_usage", lambda p: real_usage(p)._replace(free=4096))
    xyz = np.random.default_rng(0).normal(size=(5000, 3))
    tri = np.arange(4998)[:, None] + np.arange(3)
    with pytest.raises(OSError) as info:
        write_mesh(tmp_path / "m.ply", xyz, tri, np.zeros((5000, 3), np.uint8))
    assert info.value.errno == errno.ENOSPC and list(tmp_path.iterdir()) == []
    out = tmp_path / "out"
    with pytest.raises(NoSpaceError, match="no space left on the device: more than 1 MB needed"):
        with StagedOutput(out) as stage:
            write_mesh(stage / "mesh.ply", xyz, tri)
    assert list(tmp_path.iterdir()) == []
