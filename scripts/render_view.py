"""Splat a reconstruction's points.ply into camera 1's view and a rotated one (a look at the result).

    python scripts/render_view.py OUT [--yaw 20] -o view.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from sefm_recon.io.cameras import parse_camera
from sefm_recon.io.ply import read_point_cloud
from sefm_recon.io.visualize import render_points, write_image


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path, help="a sefm-recon pair output folder")
    ap.add_argument("--yaw", type=float, default=20.0, help="degrees to turn the second view about the cloud")
    ap.add_argument("-o", "--output", type=Path, default=None)
    args = ap.parse_args()
    report = json.loads((args.out / "report.json").read_text())
    cam = parse_camera(report["cameras"][0])
    K = np.asarray(cam.calibration_matrix())
    xyz, rgb, _ = read_point_cloud(args.out / "points.ply")
    w, h = cam.width, cam.height
    front = render_points(xyz, rgb, K, np.eye(3), np.zeros(3), w, h, point_size=2)
    # Orbit about the cloud's median point so the depth structure shows.
    centre = np.median(xyz, axis=0)
    a = np.radians(args.yaw)
    Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    t = centre - Ry @ centre
    side = render_points(xyz, rgb, K, Ry, t, w, h, point_size=2)
    write_image(args.output or args.out / "views.png", np.concatenate([front, side], axis=1))


if __name__ == "__main__":
    main()
