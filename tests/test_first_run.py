"""The first run as a new user sees it: one line before the kernels compile, no jargon by default."""

import os
import subprocess
import sys

from sefm_recon.io.kernel_cache import PACKAGE, cache_dirs, cold_kernels, is_cached, kernel_sources

from .conftest import SAMPLE


def _module(root, rel, text):
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_kernel_modules_are_those_with_cached_njit_kernels(tmp_path):
    k = _module(tmp_path, "geometry/kernels.py", "from numba import njit\n\n@njit(parallel=True, cache=True)\ndef f():\n"
                                                 "    return 1\n")
    _module(tmp_path, "geometry/plain.py", '"""Mentions ``@njit(cache=True)`` in a docstring only."""\n')
    _module(tmp_path, "geometry/uncached.py", "@njit\ndef g():\n    return 2\n")
    assert kernel_sources(tmp_path) == [k]
    real = {p.relative_to(PACKAGE).as_posix() for p in kernel_sources()}
    assert {"arrays.py", "geometry/epipolar.py", "reconstruct/fuse.py", "reconstruct/points.py"} <= real
    assert "io/kernel_cache.py" not in real


def test_a_module_is_cached_once_numba_wrote_an_index_newer_than_it(tmp_path, monkeypatch):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "home-cache"))
    k = _module(tmp_path, "pkg/kernels.py", "@njit(cache=True)\ndef f():\n    return 1\n")
    assert cold_kernels([k]) == [k]
    pycache, user = cache_dirs(k)
    assert pycache == k.parent / "__pycache__" and user.parent == tmp_path / "home-cache" / "numba"
    pycache.mkdir()
    other = pycache / "other.f-1.py311.nbi"  # another module's index says nothing about this one
    other.write_bytes(b"")
    assert not is_cached(k)
    index = pycache / "kernels.f-1.py311.nbi"
    index.write_bytes(b"")
    assert is_cached(k) and cold_kernels([k]) == []
    os.utime(k, (index.stat().st_mtime + 10,) * 2)  # the source changed after the cache was written
    assert not is_cached(k)
    user.mkdir(parents=True)  # numba's fallback when __pycache__ is not writable
    (user / "kernels.f-1.py311.nbi").write_bytes(b"")
    os.utime(user / "kernels.f-1.py311.nbi", (k.stat().st_mtime + 1,) * 2)
    assert is_cached(k)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "numba-cache"))  # then numba looks only there
    assert cache_dirs(k)[0].parent == tmp_path / "numba-cache" and not is_cached(k)


def _pair(out, cache, *extra):
    cam = (SAMPLE / "camera.txt").read_text().strip()
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "GLOG_minloglevel": "2"}
    return subprocess.run([sys.executable, "-m", "sefm_recon", "pair", SAMPLE / "images/view_000.jpg",
                           SAMPLE / "images/view_001.jpg", "--camera", cam, "-o", out, "--overwrite",
                           "--set", "output.mesh=false", *extra],
                          capture_output=True, text=True, timeout=600, env=env)


def test_the_first_run_says_it_compiles_and_the_default_output_has_no_jargon(tmp_path):
    first = _pair(tmp_path / "out", tmp_path / "cache")
    assert first.returncode == 0, first.stderr
    lines = first.stderr.strip().splitlines()
    assert lines[0].startswith("first run: compiling the numerical kernels once (a few seconds)"), lines
    assert sum("compiling" in line for line in lines) == 1
    assert not any("epipole" in line or "Poisson" in line or "line images" in line for line in lines), lines
    assert any(line.startswith("camera 1: focal length 667.0 px given with --camera") for line in lines), lines
    assert "matches" in first.stdout and str(tmp_path / "out") in first.stdout
    again = _pair(tmp_path / "out", tmp_path / "cache", "-v")  # warm now; -v shows the diagnostics
    assert again.returncode == 0, again.stderr
    assert "compiling" not in again.stderr and "epipoles" in again.stderr
