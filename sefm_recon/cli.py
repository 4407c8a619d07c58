"""Command line: argument parsing only; the work is in :mod:`sefm_recon.pipeline`.

Exit codes: 0 success, 2 usage or input error (one line on stderr), 1 an
unexpected failure, 130 interrupted.
"""

from __future__ import annotations

import argparse
import logging
import sys

from . import __version__
from .errors import InputError

logger = logging.getLogger("sefm_recon")


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", required=True, metavar="OUT", help="output folder")
    p.add_argument("--config", metavar="FILE", help="TOML config (presets in configs/)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override one config key, e.g. --set rough.jump_threshold=4 (repeatable)")
    p.add_argument("--overwrite", action="store_true", help="replace results in a non-empty OUT")
    p.add_argument("-q", "--quiet", action="store_true", help="only errors")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sefm-recon",
        description="Dense two-view 3D reconstruction with SeFM, a sequential epipolar-line matcher.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    pair = sub.add_parser("pair", help="reconstruct an object from two photos",
                          description="Reconstruct from two photos: writes matches.npz, points.ply, mesh.ply, "
                                      "sparse/, matches.png and report.json into OUT.")
    pair.add_argument("image1")
    pair.add_argument("image2")
    pair.add_argument("--camera", metavar="'MODEL W H PARAMS...'",
                      help="COLMAP camera of both images (or image 1), e.g. 'PINHOLE 1000 750 850 850 500 375'; "
                           "default: from EXIF, else SIMPLE_RADIAL with f = 1.2 * max(W, H)")
    pair.add_argument("--camera2", metavar="'MODEL W H PARAMS...'", help="camera of image 2 when it differs")
    _common(pair)
    return parser


def _setup_logging(quiet: bool, verbose: bool) -> None:
    level = logging.ERROR if quiet else logging.DEBUG if verbose else logging.INFO
    logging.basicConfig(level=level, format="%(levelname).1s %(name)s: %(message)s" if verbose else "%(message)s")
    if not verbose:
        # pycolmap's own glog lines are noise for a user.
        import os

        os.environ.setdefault("GLOG_minloglevel", "2")


def _cmd_pair(args) -> int:
    from .config import load_config
    from .pipeline import run_pair

    cfg = load_config(args.config, args.overrides)
    report = run_pair(args.image1, args.image2, args.output, cfg, camera=args.camera, camera2=args.camera2,
                      overwrite=args.overwrite, progress=not args.quiet and cfg.output.progress)
    c = report["counts"]
    if not args.quiet:
        print(f"{c['valid_matches']} matches, {c['points']} points "
              f"({c['sift_matches']} SIFT matches) in {report['timings_s']['total']:.1f} s -> {args.output}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    _setup_logging(args.quiet, args.verbose)
    try:
        return {"pair": _cmd_pair}[args.command](args)
    except InputError as err:
        print(f"sefm-recon: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("sefm-recon: interrupted", file=sys.stderr)
        return 130
    except Exception as err:  # noqa: BLE001 - the last line of defence: one line, exit 1
        if args.verbose:
            raise
        print(f"sefm-recon: unexpected error: {type(err).__name__}: {err} (run with -v for details)",
              file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
