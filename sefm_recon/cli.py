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


class _Parser(argparse.ArgumentParser):
    """Usage errors as one line on stderr (exit 2), like every other input error."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _max_size(text: str) -> int:
    from .config import check_value

    try:
        return check_value("output.max_size", int(text))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number of pixels, got {text!r}") from None
    except InputError as err:  # the range of output.max_size, which --max-size sets
        raise argparse.ArgumentTypeError(str(err).replace("config key output.max_size: ", "")) from None


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", required=True, metavar="OUT", help="output folder")
    p.add_argument("--config", metavar="FILE", help="TOML config (presets in configs/)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override one config key, e.g. --set rough.jump_threshold=4 (repeatable)")
    p.add_argument("--overwrite", action="store_true", help="replace results in a non-empty OUT")
    p.add_argument("-q", "--quiet", action="store_true", help="only errors")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
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
    pair.add_argument("--max-size", type=_max_size, metavar="PX",
                      help="work on copies downscaled to this longest side (0 = full size); results are in the "
                           "original pixels. Default 3200 (output.max_size): a 24-megapixel pair stays under 4 GB")
    _common(pair)

    colmap = sub.add_parser("colmap", help="dense reconstruction of a COLMAP workspace (images/ and sparse/)",
                            description="Dense SeFM matches for a COLMAP workspace with known poses: writes "
                                        "pairs/, fused.ply, database.db, sparse/ and report.json into OUT.")
    colmap.add_argument("workspace", metavar="WORKSPACE", help="COLMAP workspace: images/ and sparse/ or sparse/0")
    colmap.add_argument("--pairs", metavar="FILE", help="pairs to match, one 'name1 name2' a line (names as in the "
                                                         "model); default: pairs that share sparse points, or every "
                                                         "pair when the model has none")
    colmap.add_argument("--image-dir", metavar="DIR", help="image folder (default: WORKSPACE/images)")
    colmap.add_argument("--sparse-dir", metavar="DIR", help="model folder (default: WORKSPACE/sparse or sparse/0)")
    colmap.add_argument("--workers", type=int, metavar="N", help="pairs matched in parallel (default: all cores)")
    colmap.add_argument("--scheduler", metavar="ADDRESS",
                        help="run the pairs on a Dask distributed cluster, e.g. tcp://host:8786 "
                             "(needs pip install 'sefm-recon[dask]')")
    _common(colmap)

    ev = sub.add_parser("eval", help="SeFM beside StereoSGBM and DIS optical flow, on real pairs with ground truth "
                                     "(--real) or on generated scenes",
                        description="Match every pair with SeFM (true pose and its own pose), OpenCV StereoSGBM "
                                    "(true rectification) and OpenCV DIS optical flow, score them against the ground "
                                    "truth and print Markdown tables: the means per variant (real) or motion "
                                    "(generated), then every pair. --real reads Middlebury pairs (e.g. "
                                    "../shared/data/real_gt) in three variants: rect, unrect (camera 2 turned 13 deg) "
                                    "and conv (cameras turned towards each other, 14 deg).")
    ev.add_argument("--real", nargs="?", const="", metavar="DIR",
                    help="real pairs with ground truth (default folder: ../shared/data/real_gt beside the project)")
    ev.add_argument("--pairs", nargs="+", metavar="NAME", help="with --real: only these pairs (e.g. Cloth1 tsukuba)")
    ev.add_argument("--variants", nargs="+", choices=["rect", "unrect", "conv"], help="with --real: only these")
    ev.add_argument("--seeds", type=int, nargs="+", default=list(range(20)), metavar="SEED",
                    help="generated scenes (default 0..19); the motions lateral, converging, forward and zoom "
                         "in turn by the seed's number (seed mod 4)")
    ev.add_argument("--size", default="1000x750", metavar="WxH", help="generated image size")
    ev.add_argument("--style", choices=["random", "classic"], default="random",
                    help="generated scenes: randomised textures, photometry and motion, or the old textured "
                         "noise-free family")
    ev.add_argument("--ablation", action="store_true",
                    help="instead: the matcher with each stage switched off in turn (the DP's with --set "
                         "dense.method=sefm), with StereoSGBM and DIS, on the generated scenes or with --real "
                         "on the real pairs")
    ev.add_argument("--pose", choices=["true", "estimated"], default="true", help="with --ablation: the pose used")
    ev.add_argument("--json", metavar="FILE", help="write the rows as JSON")
    ev.add_argument("--results", nargs="+", metavar="MARKDOWN",
                    help="also replace the tables' sections (between '<!-- eval:NAME begin/end -->' markers) in these "
                         "Markdown files, e.g. docs/results.md README.md")
    ev.add_argument("--section", metavar="NAME",
                    help="with --results: write the main table between '<!-- eval:NAME ...' markers instead of the "
                         "default real, generated or ablation (e.g. a table made with --set)")
    ev.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ev.add_argument("-q", "--quiet", action="store_true")
    ev.add_argument("-v", "--verbose", action="store_true")

    be = sub.add_parser("bench", help="time SeFM against StereoSGBM on a generated 2000x1500 pair",
                        description="Render a pair with ground truth and run SeFM (as 'pair --camera') and "
                                    "StereoSGBM (true rectification) in one process; print wall time, SeFM's "
                                    "stages, matches, precision/coverage at 1 and 3 px, peak memory and the "
                                    "time ratio. The last of --repeat runs is reported (warm caches).")
    be.add_argument("--size", default="2000x1500", metavar="WxH")
    be.add_argument("--seed", type=int, default=7)
    be.add_argument("--repeat", type=int, default=2)
    be.add_argument("--scaling", nargs="*", metavar="WxH",
                    help="instead: SeFM's per-stage time and memory at these sizes "
                         "(default 500x375 1000x750 2000x1500 4000x3000), no downscaling")
    be.add_argument("--json", metavar="FILE", help="also write the report as JSON")
    be.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    be.add_argument("-q", "--quiet", action="store_true")
    be.add_argument("-v", "--verbose", action="store_true")
    return parser


def _setup_logging(quiet: bool, verbose: bool) -> None:
    level = logging.ERROR if quiet else logging.DEBUG if verbose else logging.INFO
    logging.basicConfig(level=level, format="%(levelname).1s %(name)s: %(message)s" if verbose else "%(message)s")
    if not verbose:
        # pycolmap's own glog lines are noise for a user.
        import os

        os.environ.setdefault("GLOG_minloglevel", "2")
        # The matcher's diagnostics (epipoles, line counts, depth bands, once per pyramid level) are for -v;
        # a user acts on the cameras, the pose's inliers, warnings and the summary line.
        for name in ("sefm_recon.geometry.epipolar", "sefm_recon.matching"):
            logging.getLogger(name).setLevel(logging.WARNING)


def _say_if_compiling(method: str, mesh: str = "none", fusion: bool = False) -> None:
    """One line before a first run compiles the numba kernels, which it otherwise does in silence."""
    from .io.kernel_cache import cold_kernels, kernel_sources

    # the semi-global matcher (OpenCV) uses no kernel of matching/; the sequential DP is mostly kernels there;
    # the mesh's kernels run only for the grid mesh, the fusion's only for a workspace's pairs
    skip = {"mesh.py"} if mesh != "grid" else set()
    if not fusion:
        skip.add("fuse.py")
    sources = [s for s in kernel_sources() if (method != "sgm" or s.parent.name != "matching")
               and (s.parent.name != "reconstruct" or s.name not in skip)]
    cold = cold_kernels(sources)
    if cold:
        dp = any(s.parent.name == "matching" for s in cold)
        logger.info("first run: compiling the numerical kernels once (%s); later runs reuse them",
                    "about a minute" if dp else "a few seconds")


def _cmd_pair(args) -> int:
    from .config import load_config
    from .pipeline import run_pair

    cfg = load_config(args.config, args.overrides)
    if args.max_size is not None:
        cfg.output.max_size = args.max_size
    _say_if_compiling(cfg.dense.method, cfg.output.mesh)
    report = run_pair(args.image1, args.image2, args.output, cfg, camera=args.camera, camera2=args.camera2,
                      overwrite=args.overwrite, progress=not args.quiet and cfg.output.progress)
    c = report["counts"]
    if not args.quiet:
        print(f"{c['valid_matches']} matches, {c['points']} points "
              f"({c['sift_matches']} SIFT matches) in {report['timings_s']['total']:.1f} s -> {args.output}")
    return 0


def _cmd_colmap(args) -> int:
    from .colmap_plugin import run_colmap
    from .config import load_config

    cfg = load_config(args.config, args.overrides)
    _say_if_compiling(cfg.dense.method, fusion=True)
    report = run_colmap(args.workspace, args.output, cfg, pairs_file=args.pairs, image_dir=args.image_dir,
                        sparse_dir=args.sparse_dir, overwrite=args.overwrite, workers=args.workers,
                        scheduler=args.scheduler, progress=not args.quiet and cfg.output.progress)
    c, s = report["counts"], report["sparse"]
    if not args.quiet:
        skipped = f" ({c['pairs_skipped']} skipped)" if c["pairs_skipped"] else ""
        print(f"{c['pairs_done']} of {c['pairs']} pairs{skipped}: {c.get('valid_matches', 0)} matches, "
              f"fused.ply {c['fused_points']} points, sparse/ {s['points']} points "
              f"(mean reprojection error {s['mean_reprojection_error_px']:.2f} px) "
              f"in {report['timings_s']['total']:.1f} s -> {args.output}")
    return 0


def _cmd_eval(args) -> int:
    import json

    from . import eval_tables as et
    from .config import load_config
    from .versions import format_versions

    load_config(None, args.overrides, internal=True)  # bad keys fail before any work (eval may set internal ones)
    if not args.verbose:  # one progress line per pair, not the pipeline's own lines
        logging.getLogger("sefm_recon").setLevel(logging.WARNING)
        logging.getLogger("sefm_recon.eval_tables").setLevel(logging.ERROR if args.quiet else logging.INFO)
    if args.ablation and args.real is not None:
        from .io.real_gt import DEFAULT_REAL_GT
        from .realgt import VARIANTS

        et.warm_up()
        root = args.real or DEFAULT_REAL_GT
        rows = et.ablation_table(et.real_cases(root, args.variants, args.pairs), args.pose, args.overrides)
        main, extra = "ablation-real", {}
        text = (f"SeFM ablation, mean over the real pairs in {', '.join(args.variants or VARIANTS)} "
                f"({args.pose} pose), with the peers on the same pairs:\n\n" + et.format_ablation_table(rows))
    elif args.ablation:
        w, h = _size(args.size)
        rows = et.ablation_table(et.generated_cases(args.seeds, (w, h), args.style), args.pose, args.overrides)
        main, extra = "ablation", {}
        text = (f"SeFM ablation, mean over generated seeds {' '.join(map(str, args.seeds))} ({args.style}, "
                f"{w}x{h}, {args.pose} pose), with the peers on the same scenes:\n\n"
                + et.format_ablation_table(rows))
    elif args.real is not None:
        from .io.real_gt import DEFAULT_REAL_GT

        root = args.real or DEFAULT_REAL_GT
        et.warm_up()
        rows = et.real_table(root, args.variants, args.pairs, overrides=args.overrides)
        text = ("Means per variant (a failed run scores 0):\n\n" + et.format_means(rows) +
                "\n\nEvery pair:\n\n" + et.format_rows(rows))
        main, extra = "real", {"readme": et.format_summary(rows)}
    else:
        w, h = _size(args.size)
        et.warm_up()
        rows = et.generated_table(args.seeds, (w, h), overrides=args.overrides, style=args.style)
        main, extra = "generated", {}
        text = (f"Generated scenes ({args.style}, {w}x{h}), means per motion (a failed run scores 0):\n\n"
                + et.format_means(rows, "motion") + "\n\nEvery scene:\n\n" + et.format_rows(rows, "seed"))
    text += "\n\nLibraries: " + format_versions()  # (the figures depend on them)
    print(text)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    if args.results:
        from .io.results import replace_sections

        # a table made with --section (a variant's) gets its own section and leaves the README's summary alone
        sections = {args.section: text} if args.section else {main: text, **extra}
        for path in args.results:
            replace_sections(path, sections)
    return 0


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"bad size {text!r}: expected WIDTHxHEIGHT, e.g. 2000x1500") from None
    if w < 64 or h < 64:
        raise InputError(f"bad size {text!r}: at least 64x64")
    return w, h


def _cmd_bench(args) -> int:
    from .bench import bench, dump, format_report, format_scaling, scaling
    from .config import load_config

    load_config(None, args.overrides, internal=True)  # bench may set internal keys, as eval does
    if args.scaling is not None:
        sizes = [_size(s) for s in (args.scaling or ["500x375", "1000x750", "2000x1500", "4000x3000"])]
        rows = scaling(sizes, args.seed, args.overrides)
        print(format_scaling(rows))
        if args.json:
            dump(rows, args.json)
        return 0
    report = bench(_size(args.size), args.seed, max(1, args.repeat), args.overrides)
    print(format_report(report))
    if args.json:
        dump(report, args.json)
    return 0


def _terminate_as_interrupt() -> None:
    """Ctrl-C and SIGTERM (``kill``, a batch system's time limit) end the run alike: no partial output, exit 130."""
    import pycolmap  # noqa: F401 - its glog installs a SIGTERM stack dumper on import: ours must come after

    from . import interrupt

    interrupt.install()


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    for stream in (sys.stdout, sys.stderr):  # a path with bytes that are not UTF-8 is printed, not a crash
        if hasattr(stream, "reconfigure"):
            stream.reconfigure(errors="backslashreplace")
    _setup_logging(args.quiet, args.verbose)
    _terminate_as_interrupt()
    from .memory import keep_freed_memory

    keep_freed_memory()
    try:
        return {"pair": _cmd_pair, "colmap": _cmd_colmap, "eval": _cmd_eval, "bench": _cmd_bench}[args.command](args)
    except InputError as err:
        print(f"sefm-recon: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("sefm-recon: interrupted", file=sys.stderr)
        return 130
    except Exception as err:  # noqa: BLE001 - the last line of defence: one line, exit 1
        from .interrupt import caused_by_interrupt

        if caused_by_interrupt(err):  # e.g. numba's SystemError around a Ctrl-C that came during a kernel
            print("sefm-recon: interrupted", file=sys.stderr)
            return 130
        if args.verbose:
            raise
        print(f"sefm-recon: unexpected error: {type(err).__name__}: {err} (run with -v for details)",
              file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
