"""Bad input, faults and never a half-written output (issue 6).

Every bad input runs the real command line and must end in exit code 2 with one
line on stderr that says what is wrong, no traceback, and no output folder (nor
a staging folder) left behind. Good but unusual inputs (EXIF orientation,
16-bit, grey, TIFF, a large photo with --max-size) must work, with coordinates
in the original pixels. A run interrupted (SIGINT) or killed (SIGKILL) at any
moment leaves either nothing or a complete set of results in OUT.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import struct
import subprocess
import sys
import threading
import time
import zlib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest

from sefm_recon.errors import InputError
from sefm_recon.io import output as output_mod
from sefm_recon.io.images import MIN_SIZE, read_image
from sefm_recon.io.output import PAIR_RESULTS, StagedOutput, clean_stale_stages

ENV = {**os.environ, "GLOG_minloglevel": "2", "PYTHONUNBUFFERED": "1"}


def cli(*args, timeout=300, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sefm_recon", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=ENV, cwd=cwd)


def leftovers(out: Path) -> list[str]:
    """Staging folders (or anything else hidden) beside OUT."""
    return [p.name for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.")]


def write_rgb(path: Path, rgb: np.ndarray, *params) -> Path:
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), list(params))
    return path


def camera_string(K: np.ndarray, w: int, h: int, scale: float = 1.0) -> str:
    f = [float(K[0, 0]) * scale, float(K[1, 1]) * scale, float(K[0, 2]) * scale, float(K[1, 2]) * scale]
    return f"PINHOLE {round(w * scale)} {round(h * scale)} " + " ".join(f"{v:.9g}" for v in f)


def exif_app1(orientation: int) -> bytes:
    """A minimal EXIF APP1 segment with only the Orientation tag (big-endian TIFF)."""
    ifd = struct.pack(">H", 1) + struct.pack(">HHIHH", 0x0112, 3, 1, orientation, 0) + struct.pack(">I", 0)
    payload = b"Exif\x00\x00" + b"MM" + struct.pack(">HI", 42, 8) + ifd
    return b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload


def jpeg_with_orientation(path: Path, stored_rgb: np.ndarray, orientation: int) -> Path:
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(stored_rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    data = buf.tobytes()
    path.write_bytes(data[:2] + exif_app1(orientation) + data[2:])
    return path


#: The displayed image of a stored one, per EXIF orientation (EXIF 2.3, tag 0x0112).
ORIENT = {
    1: lambda s: s,
    2: lambda s: s[:, ::-1],
    3: lambda s: s[::-1, ::-1],
    4: lambda s: s[::-1, :],
    5: lambda s: s.transpose(1, 0, 2),
    6: lambda s: np.rot90(s, -1),
    7: lambda s: s[::-1, ::-1].transpose(1, 0, 2),
    8: lambda s: np.rot90(s, 1),
}
#: Stored pixels that display as a given upright image (the inverse of ORIENT).
UNORIENT = {
    1: lambda d: d,
    2: lambda d: d[:, ::-1],
    3: lambda d: d[::-1, ::-1],
    4: lambda d: d[::-1, :],
    5: lambda d: d.transpose(1, 0, 2),
    6: lambda d: np.rot90(d, 1),
    7: lambda d: d.transpose(1, 0, 2)[::-1, ::-1],
    8: lambda d: np.rot90(d, -1),
}


# ------------------------------------------------------------------ data


@pytest.fixture(scope="module")
def data(tmp_path_factory, small_scene):
    """A 320x240 pair with ground truth, and every kind of bad file, written once."""
    d = tmp_path_factory.mktemp("bad_input")
    v1, v2 = small_scene.views
    h, w = v1.image.shape[:2]
    a = write_rgb(d / "a.png", v1.image)
    b = write_rgb(d / "b.png", v2.image)
    files = {"a": a, "b": b, "cam": camera_string(v1.K, w, h)}
    (d / "empty.jpg").write_bytes(b"")
    (d / "text.jpg").write_text("this is not a photo\n")
    jpg = cv2.imencode(".jpg", v1.image)[1].tobytes()
    (d / "truncated.jpg").write_bytes(jpg[: len(jpg) // 2])
    (d / "folder.jpg").mkdir()
    write_rgb(d / "tiny.png", v1.image[:40, :60])
    # A PNG whose header claims 40000 x 40000 pixels (a decompression bomb).
    chunk = lambda t, x: struct.pack(">I", len(x)) + t + x + struct.pack(">I", zlib.crc32(t + x))  # noqa: E731
    ihdr = struct.pack(">IIBBBBB", 40000, 40000, 8, 2, 0, 0, 0)
    (d / "bomb.png").write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
                                 + chunk(b"IDAT", zlib.compress(b"\0" * 1000)) + chunk(b"IEND", b""))
    cv2.imwrite(str(d / "flat.png"), np.full((h, w), 128, np.uint8))
    cv2.imwrite(str(d / "ramp.png"), np.tile(np.linspace(0, 255, w), (h, 1)).astype(np.uint8))
    stripes = np.where((np.arange(w) // 16) % 2 == 0, 200, 40).astype(np.uint8)
    cv2.imwrite(str(d / "stripes.png"), cv2.GaussianBlur(np.tile(stripes, (h, 1)), (0, 0), 1.0))
    shutil.copy(a, d / "a_copy.png")
    # Another scene: unrelated to the pair.
    from sefm_recon.synthetic import render_scene

    write_rgb(d / "other.png", render_scene(seed=5, width=w, height=h, n_views=1, style="classic").views[0].image)
    # Camera 1 turned by 5 degrees about its centre: a pure rotation, H = K R K^-1.
    R = cv2.Rodrigues(np.array([0.2, 1.0, 0.1]) / np.linalg.norm([0.2, 1.0, 0.1]) * np.radians(5))[0]
    T = np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1]])  # COLMAP -> OpenCV pixel centres
    H = T @ v1.K @ R @ np.linalg.inv(v1.K) @ np.linalg.inv(T)
    write_rgb(d / "turned.png", cv2.warpPerspective(v1.image, H, (w, h), flags=cv2.INTER_LINEAR,
                                                    borderMode=cv2.BORDER_REFLECT))
    (d / "bad.toml").write_text("[rough\njump_threshold = 4\n")
    (d / "outfile").write_text("precious\n")
    files["dir"] = d
    return files


# ------------------------------------------------------------ bad inputs

# (name, arguments after "pair" with {a}, {b}, {dir}, {cam} filled in, phrases the message must hold)
CASES = [
    ("missing image", ["{dir}/nope.jpg", "{b}"], ["image not found", "nope.jpg"]),
    ("empty image", ["{dir}/empty.jpg", "{b}"], ["image is empty (0 bytes)", "empty.jpg"]),
    ("not an image", ["{a}", "{dir}/text.jpg"], ["cannot decode image", "text.jpg"]),
    ("truncated JPEG", ["{dir}/truncated.jpg", "{b}"], ["cannot decode image", "truncated"]),
    ("a folder", ["{dir}/folder.jpg", "{b}"], ["is a folder", "folder.jpg"]),
    ("too small", ["{dir}/tiny.png", "{b}"], ["too small", "60x40", f"at least {MIN_SIZE} px"]),
    ("decompression bomb", ["{dir}/bomb.png", "{b}"], ["too large", "40000x40000"]),
    ("flat grey", ["{dir}/flat.png", "{b}"], ["image 1 (flat.png) is nearly textureless", "0.00 %"]),
    ("smooth ramp", ["{a}", "{dir}/ramp.png"], ["image 2 (ramp.png) is nearly textureless"]),
    ("stripes only", ["{dir}/stripes.png", "{b}"], ["image 1 (stripes.png) has too little texture",
                                                    "SIFT features found, at least 30"]),
    ("unrelated scenes", ["{a}", "{dir}/other.png"], ["too little overlap", "geometric inliers found",
                                                      "at least 30 are needed"]),
    ("the same photo twice", ["{a}", "{dir}/a_copy.png"], ["are the same photo", "no depth can be recovered"]),
    ("pure rotation, true camera", ["{a}", "{dir}/turned.png", "--camera", "{cam}"],
     ["no baseline", "median triangulation angle", "pure rotation", "no depth can be recovered"]),
    ("pure rotation, default camera", ["{a}", "{dir}/turned.png"],
     ["no baseline", "pure rotation of the camera (by about 5.0 deg)", "no depth can be recovered"]),
    ("camera: too few fields", ["{a}", "{b}", "--camera", "PINHOLE 320"], ["expected 'MODEL WIDTH HEIGHT PARAMS"]),
    ("camera: not numbers", ["{a}", "{b}", "--camera", "PINHOLE 320 240 f f c c"], ["must be numbers"]),
    ("camera: unknown model", ["{a}", "{b}", "--camera", "FISHEYE9 320 240 1 2 3"], ["unknown camera model"]),
    ("camera: parameter count", ["{a}", "{b}", "--camera", "PINHOLE 320 240 300 160 120"],
     ["PINHOLE takes 4 parameters", "got 3"]),
    ("camera: zero focal length", ["{a}", "{b}", "--camera", "SIMPLE_PINHOLE 320 240 0 160 120"],
     ["implausible parameters"]),
    ("camera: negative size", ["{a}", "{b}", "--camera", "SIMPLE_PINHOLE -320 240 300 160 120"],
     ["must be positive"]),
    ("camera: other image size", ["{a}", "{b}", "--camera", "SIMPLE_PINHOLE 640 480 600 320 240"],
     ["--camera is for a 640x480 image", "is 320x240"]),
    ("camera2: other image size", ["{a}", "{b}", "--camera", "{cam}", "--camera2", "SIMPLE_PINHOLE 32 24 30 16 12"],
     ["--camera2 is for a 32x24 image"]),
    ("--set without '='", ["{a}", "{b}", "--set", "rough.jump_threshold"], ["expected SECTION.KEY=VALUE"]),
    ("--set unknown section", ["{a}", "{b}", "--set", "magic.level=3"], ["unknown config section 'magic'"]),
    ("--set unknown key", ["{a}", "{b}", "--set", "rough.speed=3"], ["unknown config key rough.speed"]),
    ("--set wrong type (int)", ["{a}", "{b}", "--set", "output.mesh_max_points=wide"],
     ["output.mesh_max_points: expected int"]),
    ("--set wrong choice", ["{a}", "{b}", "--set", "output.mesh=maybe"], ["output.mesh: one of grid, poisson, none"]),
    ("--set not finite", ["{a}", "{b}", "--set", "geometry.ransac_max_error=nan"], ["expected a finite number"]),
    ("--set out of range", ["{a}", "{b}", "--set", "output.poisson_depth=0"], ["output.poisson_depth: must be >= 5"]),
    ("--set out of range (float)", ["{a}", "{b}", "--set", "sift.max_ratio=1.5"], ["sift.max_ratio: must be"]),
    ("--config missing", ["{a}", "{b}", "--config", "{dir}/nope.toml"], ["config file not found"]),
    ("--config not TOML", ["{a}", "{b}", "--config", "{dir}/bad.toml"], ["is not valid TOML"]),
    ("--config a folder", ["{a}", "{b}", "--config", "{dir}"], ["cannot read config file"]),
    ("--max-size too small", ["{a}", "{b}", "--max-size", "100"], ["--max-size", ">= 256"]),
    ("--max-size not a number", ["{a}", "{b}", "--max-size", "big"], ["--max-size", "whole number"]),
    ("unknown option", ["{a}", "{b}", "--fast"], ["unrecognized arguments: --fast"]),
    ("OUT is a file", ["{a}", "{b}", "-o", "{dir}/outfile"], ["output path exists and is not a folder"]),
    ("OUT inside a file", ["{a}", "{b}", "-o", "{dir}/outfile/sub"], ["is not a folder"]),
]


@pytest.fixture(scope="module")
def case_results(data, tmp_path_factory):
    """Run every bad-input case once, a few at a time (each is a separate CLI process)."""
    root = tmp_path_factory.mktemp("bad_runs")

    def run(case):
        name, args, _ = case
        args = [x.format(a=data["a"], b=data["b"], dir=data["dir"], cam=data["cam"]) for x in args]
        if "-o" in args:
            out = Path(args[args.index("-o") + 1])
        else:
            folder = root / "".join(c if c.isalnum() else "_" for c in name)
            folder.mkdir()
            out = folder / "out"
            args += ["-o", out]
        return name, (cli("pair", *args, "-q"), out)

    with ThreadPoolExecutor(3) as ex:
        return dict(ex.map(run, CASES))


@pytest.mark.parametrize("name, args, phrases", CASES, ids=[c[0] for c in CASES])
def test_bad_input_is_refused_with_one_line(case_results, data, name, args, phrases):
    r, out = case_results[name]
    assert r.returncode == 2, (r.returncode, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith("sefm-recon")
    assert "error" in lines[0] and "Traceback" not in r.stderr
    for phrase in phrases:
        assert phrase in lines[0], (phrase, lines[0])
    assert r.stdout == ""
    if out.name == "outfile":
        assert out.read_text() == "precious\n"  # untouched
    else:
        assert not out.exists()
    if out.parent.is_dir():
        assert leftovers(out) == []


def test_without_quiet_the_error_is_the_last_line(data, tmp_path):
    r = cli("pair", data["a"], data["dir"] / "other.png", "-o", tmp_path / "out")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("sefm-recon: error: too little overlap")
    assert not (tmp_path / "out").exists() and leftovers(tmp_path / "out") == []


# ------------------------------------------------------- readable inputs


def _pattern(h=120, w=160):
    """Colour blocks large enough to survive JPEG, distinct in every quadrant and channel."""
    img = np.zeros((h, w, 3), np.uint8)
    img[: h // 2, : w // 2] = (250, 30, 30)
    img[: h // 2, w // 2:] = (30, 250, 30)
    img[h // 2:, : w // 2] = (30, 30, 250)
    img[h // 2:, w // 2:] = (240, 240, 40)
    img[10:30, 10:50] = (0, 0, 0)
    return img


@pytest.mark.parametrize("orientation", range(1, 9))
def test_exif_orientation_is_applied(tmp_path, orientation):
    stored = _pattern()
    img = read_image(jpeg_with_orientation(tmp_path / "o.jpg", stored, orientation))
    expected = np.ascontiguousarray(ORIENT[orientation](stored))
    assert img.shape == expected.shape
    assert np.abs(img.astype(int) - expected).mean() < 4
    # and UNORIENT is its inverse (used below to write photos that display upright)
    np.testing.assert_array_equal(ORIENT[orientation](UNORIENT[orientation](stored)), stored)


@pytest.mark.parametrize("ext", ["png", "tif", "jpg"])
@pytest.mark.parametrize("depth", [8, 16])
@pytest.mark.parametrize("grey", [False, True])
def test_formats_depths_and_grey(tmp_path, ext, depth, grey):
    if ext == "jpg" and depth == 16:
        pytest.skip("JPEG has no 16-bit")
    rgb = _pattern()
    src = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    if grey:
        src = cv2.cvtColor(src, cv2.COLOR_BGR2GRAY)
    if depth == 16:
        src = src.astype(np.uint16) * 257
    path = tmp_path / f"im.{ext}"
    assert cv2.imwrite(str(path), src)
    img = read_image(path)
    assert img.shape == (120, 160, 3) and img.dtype == np.uint8
    expected = np.repeat(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)[:, :, None], 3, 2) if grey else rgb
    assert np.abs(img.astype(int) - expected).mean() < (4 if ext == "jpg" else 0.5)


def test_float_alpha_and_corrupt_files_are_read(tmp_path, caplog):
    rgb = _pattern()
    cv2.imwrite(str(tmp_path / "f.tif"), cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255)
    assert np.abs(read_image(tmp_path / "f.tif")[..., 0].astype(int)
                  - cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)).max() <= 1
    bgra = np.dstack([cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), np.full(rgb.shape[:2], 7, np.uint8)])
    cv2.imwrite(str(tmp_path / "a.png"), bgra)
    np.testing.assert_array_equal(read_image(tmp_path / "a.png"), rgb)
    # A JPEG with damaged entropy data decodes with a libjpeg warning: logged, not printed.
    data = bytearray(cv2.imencode(".jpg", rgb)[1].tobytes())
    data[-60:-10] = b"\x55" * 50
    (tmp_path / "c.jpg").write_bytes(bytes(data))
    with caplog.at_level("WARNING"):
        assert read_image(tmp_path / "c.jpg").shape == rgb.shape
    assert any("decoder reported" in m for m in caplog.messages)
    with pytest.raises(InputError, match="too small"):
        cv2.imwrite(str(tmp_path / "t.png"), np.zeros((MIN_SIZE - 1, 500), np.uint8))
        read_image(tmp_path / "t.png")


def test_grey_16bit_tiff_and_rotated_jpeg_reconstruct(data, small_scene, tmp_path):
    """Image 1: 16-bit grey TIFF; image 2: a JPEG stored turned, upright only through EXIF orientation 6."""
    from sefm_recon.evaluate import evaluate_matches

    v1, v2 = small_scene.views
    grey16 = cv2.cvtColor(v1.image, cv2.COLOR_RGB2GRAY).astype(np.uint16) * 257
    assert cv2.imwrite(str(tmp_path / "one.tif"), grey16)
    jpeg_with_orientation(tmp_path / "two.jpg", np.ascontiguousarray(UNORIENT[6](v2.image)), 6)
    stored = cv2.imread(str(tmp_path / "two.jpg"), cv2.IMREAD_IGNORE_ORIENTATION | cv2.IMREAD_COLOR)
    assert stored.shape == (320, 240, 3)  # stored turned: only EXIF makes it 320x240
    out = tmp_path / "out"
    r = cli("pair", tmp_path / "one.tif", tmp_path / "two.jpg", "-o", out, "--camera", data["cam"], "-q",
            "--set", "output.mesh=false")
    assert r.returncode == 0, r.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["image_size"] == [[320, 240], [320, 240]]
    m = np.load(out / "matches.npz")
    ev = evaluate_matches(m["uv1"], m["uv2"], v1, v2)
    assert ev["matches"] > 20_000 and ev["precision@3"] > 0.85, ev


def test_max_size_reports_original_pixels(data, small_scene, tmp_path):
    """A pair upscaled 2x, worked on at 1x (--max-size 320): matches agree with the truth in 2x pixels."""
    from sefm_recon.evaluate import evaluate_matches

    v1, v2 = small_scene.views
    h, w = v1.image.shape[:2]
    for name, v in (("one.png", v1), ("two.png", v2)):
        write_rgb(tmp_path / name, cv2.resize(v.image, (2 * w, 2 * h), interpolation=cv2.INTER_CUBIC))
    out = tmp_path / "out"
    r = cli("pair", tmp_path / "one.png", tmp_path / "two.png", "-o", out, "-q", "--max-size", "320",
            "--camera", camera_string(v1.K, w, h, scale=2.0), "--set", "output.mesh=false")
    assert r.returncode == 0, r.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["image_size"] == [[2 * w, 2 * h], [2 * w, 2 * h]]
    assert report["config"]["output"]["max_size"] == 320
    m = np.load(out / "matches.npz")
    uv1, uv2 = m["uv1"].astype(float), m["uv2"].astype(float)
    assert uv1[:, 0].max() > 1.5 * w and uv1[:, 1].max() > 1.5 * h  # original (2x) pixels, not working ones
    assert uv1.min() >= 0 and uv1[:, 0].max() <= 2 * w and uv1[:, 1].max() <= 2 * h
    # COLMAP convention: pixel edges scale exactly, so 2x pixels / 2 are the 1x scene's pixels.
    ev = evaluate_matches(uv1 / 2, uv2 / 2, v1, v2, thresholds=(0.5, 1.0))
    assert ev["matches"] > 20_000 and ev["precision@1"] > 0.85, ev


# ------------------------------------------------------------- atomicity


def _complete(out: Path) -> bool:
    """OUT holds a complete, consistent result set (what a reader may rely on)."""
    names = {p.name for p in out.iterdir()}
    if not set(PAIR_RESULTS) <= names:
        return False
    from sefm_recon.io.ply import read_ply_header

    report = json.loads((out / "report.json").read_text())
    n = report["counts"]["points"]
    m = np.load(out / "matches.npz")
    assert len(m["uv1"]) == len(m["uv2"]) == n
    assert read_ply_header(out / "points.ply")["elements"]["vertex"]["count"] == n
    assert (out / "sparse" / "points3D.bin").is_file()
    return True


def _run_and_signal(args, out: Path, sig, when):
    """Start the CLI, wait for ``when(stage_entries)`` to hold, send ``sig``; returns (rc, stderr, note)."""
    proc = subprocess.Popen([sys.executable, "-m", "sefm_recon", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=ENV)
    err_lines: list[str] = []
    reader = threading.Thread(target=lambda: err_lines.extend(proc.stderr), daemon=True)
    reader.start()
    note = "finished before the signal"
    t0 = time.monotonic()
    while proc.poll() is None and time.monotonic() - t0 < 120:
        stages = [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.partial-")]
        entries = sum(len(os.listdir(s)) for s in stages if s.is_dir()) if stages else -1
        if when(entries, err_lines):
            proc.send_signal(sig)
            note = f"signalled with {entries} staged entries"
            break
        time.sleep(0.002)
    proc.wait(timeout=120)
    reader.join(timeout=5)
    return proc.returncode, "".join(err_lines), note


@pytest.fixture(scope="module")
def quick_args(data):
    def args(out):
        return ["pair", data["a"], data["b"], "-o", out, "--camera", data["cam"], "--set", "output.poisson_depth=6"]

    return args


@pytest.mark.parametrize("moment", ["during matching", "while writing"])
def test_ctrl_c_leaves_nothing(quick_args, tmp_path, moment):
    out = tmp_path / "out"
    if moment == "during matching":
        when = lambda n, err: any("SIFT:" in line for line in err)  # noqa: E731
    else:
        when = lambda n, err: n >= 1  # noqa: E731
    rc, err, note = _run_and_signal(quick_args(out), out, signal.SIGINT, when)
    assert rc == 130, (note, err)
    assert err.strip().splitlines()[-1] == "sefm-recon: interrupted" and "Traceback" not in err
    assert not out.exists(), note
    assert leftovers(out) == [], note


def test_sigterm_cleans_up_like_ctrl_c(quick_args, tmp_path):
    out = tmp_path / "out"
    rc, err, note = _run_and_signal(quick_args(out), out, signal.SIGTERM, lambda n, err: n >= 2)
    assert rc == 130 and not out.exists() and leftovers(out) == [], (note, err)


@pytest.mark.parametrize("staged", [-2, 0, 1, 2, 3, 4, 5])
def test_sigkill_leaves_nothing_or_a_complete_result(quick_args, tmp_path, staged):
    """SIGKILL once the staging folder holds ``staged`` entries (-2: during matching, before any writing)."""
    out = tmp_path / "out"
    if staged == -2:
        when = lambda n, err: any("SIFT:" in line for line in err)  # noqa: E731
    else:
        when = lambda n, err: n >= staged  # noqa: E731
    rc, err, note = _run_and_signal(quick_args(out), out, signal.SIGKILL, when)
    assert rc in (-signal.SIGKILL, 0), (rc, err)
    if out.exists():
        assert _complete(out), (note, sorted(p.name for p in out.iterdir()))
    # No visible partial file anywhere beside OUT; a killed run's hidden staging folder is
    # removed by the next run (here called directly: its process is gone).
    visible = [p.name for p in tmp_path.iterdir() if not p.name.startswith(".")]
    assert visible in ([], ["out"]), visible
    clean_stale_stages(out)
    assert leftovers(out) == []


def test_overwrite_replaces_results_and_keeps_other_files(quick_args, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "mesh.ply").write_text("an old mesh")  # a result the new run does not write (mesh off)
    (out / "report.json").write_text("{}")
    (out / "notes.txt").write_text("mine")
    (out / "extra").mkdir()
    (out / "extra" / "x.txt").write_text("also mine")
    args = [*quick_args(out), "--set", "output.mesh=false", "-q"]
    r = cli(*args)
    assert r.returncode == 2 and "not empty" in r.stderr  # without --overwrite: refused, untouched
    assert (out / "report.json").read_text() == "{}"
    r = cli(*args, "--overwrite")
    assert r.returncode == 0, r.stderr
    names = {p.name for p in out.iterdir()}
    assert names == (set(PAIR_RESULTS) - {"mesh.ply"}) | {"notes.txt", "extra"}
    assert (out / "notes.txt").read_text() == "mine" and (out / "extra" / "x.txt").read_text() == "also mine"
    assert json.loads((out / "report.json").read_text())["counts"]["points"] > 0
    assert leftovers(out) == []


# ------------------------------------------------- StagedOutput in-process


def _fill(stage: Path, tag: str):
    for name in ("matches.npz", "points.ply", "report.json"):
        (stage / name).write_text(tag)
    (stage / "sparse").mkdir()
    (stage / "sparse" / "cameras.bin").write_text(tag)


def test_staged_output_fresh_and_failed(tmp_path):
    out = tmp_path / "new" / "out"
    with pytest.raises(RuntimeError):
        with StagedOutput(out) as stage:
            _fill(stage, "x")
            raise RuntimeError("a stage failed")
    assert not out.exists() and leftovers(out) == []
    with StagedOutput(out) as stage:
        _fill(stage, "v1")
        assert not out.exists()  # nothing visible before the end
    assert (out / "report.json").read_text() == "v1" and leftovers(out) == []


@pytest.mark.parametrize("swap", ["exchange", "two renames", "per item"])
def test_staged_output_overwrite_paths(tmp_path, monkeypatch, swap):
    out = tmp_path / "out"
    with StagedOutput(out) as stage:
        _fill(stage, "v1")
        (stage / "mesh.ply").write_text("v1")
    (out / "keep.txt").write_text("mine")
    os.link(out / "keep.txt", tmp_path / "keep.link")
    if swap == "two renames":
        monkeypatch.setattr(output_mod, "_exchange", lambda a, b: False)
    if swap == "per item":
        monkeypatch.chdir(out)  # never rename the current folder
    with StagedOutput(out, overwrite=True, results=PAIR_RESULTS) as stage:
        _fill(stage, "v2")
    assert {p.name for p in out.iterdir()} == {"matches.npz", "points.ply", "report.json", "sparse", "keep.txt"}
    assert (out / "report.json").read_text() == "v2" and (out / "sparse" / "cameras.bin").read_text() == "v2"
    assert (out / "keep.txt").read_text() == "mine"
    assert os.path.samefile(out / "keep.txt", tmp_path / "keep.link")  # linked, not copied
    assert leftovers(out) == []


def test_stale_staging_folders_of_dead_runs_are_removed(tmp_path):
    out = tmp_path / "out"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(dead.stdout)
    host = output_mod._host_tag()
    stale = tmp_path / f".out.partial-{host}-{dead_pid}-deadbeef"
    live = tmp_path / f".out.partial-{host}-{os.getppid()}-cafe0001"
    foreign = tmp_path / f".out.partial-zzzzzz-{dead_pid}-cafe0002"
    other = tmp_path / f".other.partial-{host}-{dead_pid}-cafe0003"
    for p in (stale, live, foreign, other):
        p.mkdir()
        (p / "points.ply").write_text("half")
    r = cli("pair", "nope.jpg", "nope2.jpg", "-o", out, "-q")  # the check at the start cleans up
    assert r.returncode == 2
    assert not stale.exists()
    assert live.exists() and foreign.exists() and other.exists()


def test_a_signal_while_held_is_raised_as_the_block_ends(monkeypatch):
    """interrupt.held(): a Ctrl-C inside the block is recorded, the block runs to its end, and
    the interrupt comes out of it; outside any block the handler raises at once."""
    import os

    from sefm_recon import interrupt

    monkeypatch.setattr(interrupt, "_received", [])
    old = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        interrupt.install()
        steps = []
        with pytest.raises(KeyboardInterrupt):
            with interrupt.held():
                os.kill(os.getpid(), signal.SIGINT)
                for _ in range(1000):  # the handler runs at one of these bytecodes: it must not raise
                    steps.append(1)
        assert len(steps) == 1000 and interrupt.received() == signal.SIGINT
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(1000):
                steps.append(2)
        assert len(steps) < 2000
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
