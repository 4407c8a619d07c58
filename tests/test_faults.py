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
