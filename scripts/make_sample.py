"""Regenerate data_samples/scene, the bundled demo pair (a generated scene with true poses).

    .venv/bin/python scripts/make_sample.py            # writes data_samples/scene

The images are JPEG (as a phone would give) so the sample stays a few hundred KB;
sparse/ holds the true cameras and poses (a COLMAP text model) and camera.txt the
camera string for --camera. Depth maps are left out (1.2 MB each); tests that need
ground truth render their own scenes.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from sefm_recon.io.cameras import camera_to_string
from sefm_recon.synthetic import render_scene, write_workspace

SEED, WIDTH, HEIGHT = 1, 640, 480


def main(out: Path = Path("data_samples/scene")) -> None:
    scene = render_scene(seed=SEED, width=WIDTH, height=HEIGHT, style="classic")
    for i, view in enumerate(scene.views):
        view.name = f"view_{i:03d}.jpg"
    if out.exists():
        shutil.rmtree(out)
    write_workspace(scene, out)
    for f in (out / "gt").glob("*.npy"):
        f.unlink()
    import pycolmap

    cam = pycolmap.Reconstruction(str(out / "sparse")).cameras[1]
    (out / "camera.txt").write_text(camera_to_string(cam) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
