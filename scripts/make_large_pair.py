"""A large photo pair with ground truth, for the memory bound of ``--max-size``.

Renders a synthetic pair and upscales it (default 1500x1000 x4 = 6000x4000, a
24-megapixel phone photo) as JPEGs, with the true camera in ``camera.txt``.
With ``--check RESULT`` it instead scores a run's ``matches.npz`` against the
truth, in the original (upscaled) pixels.

    .venv/bin/python scripts/make_large_pair.py /tmp/big
    /usr/bin/time -v .venv/bin/sefm-recon pair /tmp/big/view_000.jpg /tmp/big/view_001.jpg -o /tmp/big/out -q
    .venv/bin/python scripts/make_large_pair.py /tmp/big --check /tmp/big/out
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from sefm_recon.evaluate import evaluate_matches
from sefm_recon.synthetic import SyntheticView, render_scene


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--seed", type=int, default=201)
    ap.add_argument("--width", type=int, default=1500)
    ap.add_argument("--height", type=int, default=1000)
    ap.add_argument("--scale", type=int, default=4)
    ap.add_argument("--check", type=Path, metavar="RESULT", help="score RESULT/matches.npz against the truth")
    args = ap.parse_args()
    if args.check:
        g = np.load(args.out / "gt.npz")
        views = [SyntheticView(str(i), None, g[f"d{i}"], g["K"], g[f"R{i}"], g[f"t{i}"]) for i in (1, 2)]
        m = np.load(args.check / "matches.npz")
        s = float(g["scale"])
        ev = evaluate_matches(m["uv1"] / s, m["uv2"] / s, *views, thresholds=(0.5, 1.0))
        print(f"{ev['matches']} matches; uv1 spans x {m['uv1'][:, 0].min():.0f}..{m['uv1'][:, 0].max():.0f}, "
              f"y {m['uv1'][:, 1].min():.0f}..{m['uv1'][:, 1].max():.0f}; within {s * 0.5:g} / {s:g} original px "
              f"of the truth: {ev['precision@0.5']:.3f} / {ev['precision@1']:.3f}")
        return
    args.out.mkdir(parents=True, exist_ok=True)
    scene = render_scene(seed=args.seed, width=args.width, height=args.height, style="classic")
    W, H = args.width * args.scale, args.height * args.scale
    for v in scene.views:
        big = cv2.resize(cv2.cvtColor(v.image, cv2.COLOR_RGB2BGR), (W, H), interpolation=cv2.INTER_CUBIC)
        cv2.imwrite(str(args.out / v.name.replace(".png", ".jpg")), big, [cv2.IMWRITE_JPEG_QUALITY, 92])
    K = scene.views[0].K * args.scale  # COLMAP convention: pixel edges scale exactly
    K[2, 2] = 1.0
    (args.out / "camera.txt").write_text(f"PINHOLE {W} {H} {K[0, 0]:.6f} {K[1, 1]:.6f} {K[0, 2]:.6f} {K[1, 2]:.6f}\n")
    v1, v2 = scene.views
    np.savez(args.out / "gt.npz", K=v1.K, R1=v1.R, t1=v1.t, R2=v2.R, t2=v2.t, d1=v1.depth, d2=v2.depth,
             scale=args.scale)
    print(f"wrote {W}x{H} pair to {args.out}")


if __name__ == "__main__":
    main()
