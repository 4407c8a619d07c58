"""Configuration: typed dataclasses, TOML presets in ``configs/``, ``--set`` overrides.

A config file holds any subset of the user settings (:data:`USER_KEYS`, written out in
``configs/default.toml``); the rest keep their defaults. ``--set output.max_size=2000``
overrides one key; unknown keys, wrong types and values out of range are input errors.

The other fields (the ``lines``, ``rough``, ``pyramid`` and ``validity`` sections and
most of ``dense``) are the internal constants of the sequential DP matcher
(``dense.method = "sefm"``; ``"paper"`` sets them as the paper has them,
:data:`PAPER`). They are not settings: only the evaluation and the tests change them
(``load_config(..., internal=True)``), to measure what each stage adds.
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import InputError


@dataclass
class SiftConfig:
    max_features: int = 4096  #: SIFT features per image
    max_ratio: float = 0.8  #: Lowe's ratio test
    max_image_size: int = 1024  #: SIFT runs on copies downscaled to this longest side, or its square / 2 pixels if longer than 2:1 (0 = full size)


@dataclass
class GeometryConfig:
    min_inliers: int = 30  #: geometric inliers needed to trust the pose
    ransac_max_error: float = 2.0  #: px
    min_tri_angle_deg: float = 0.5  #: median triangulation angle below which there is no baseline
    depth_margin: float = 2.0  #: search depths from p1/margin to p99*margin of the SIFT points' depths


@dataclass
class LinesConfig:
    line_spacing: float = 1.0  #: px between neighbouring epipolar lines at the far border
    sample_spacing: float = 1.0  #: px between samples along a line
    blur_sigma: float = 0.7  #: Gaussian pre-filter (px) against aliasing along the lines
    max_lines: int = 20000
    color: bool = False  #: match on the three colour channels instead of grey
    neighbours: int = 2  #: aligned neighbour lines on each side stacked as channels (0 = the paper's 1-D)
    neighbour_step: float = 1.0  #: spacing of the neighbour lines, in line steps


@dataclass
class RoughConfig:
    jump_threshold: float = 2.0  #: da_i above this (0-255 intensity) makes a key point
    #: images with a longer side than this get ``jump_threshold`` scaled by size / side (0 = never)
    jump_reference_size: int = 1000
    descriptor_radius: int = 8  #: half width of the FFT window, samples
    descriptor_coefficients: int = 4  #: Fourier coefficients kept (beyond DC); 6 measured no better, and 4 are faster
    max_descriptor_distance: float = 0.8  #: pairs farther apart never match
    band_slack: int = 3  #: samples added to each side of the depth search band


@dataclass
class PyramidConfig:
    """Coarse to fine: a match at reduced size first bounds each sample's search band."""

    min_size: int = 600  #: images with a longer side than this are matched at reduced size first (0 = never)
    factor: int = 4  #: size reduction from one level to the next (a 2000 px pair: 500 px, then 2000 px)
    radius: int = 2  #: coarse pixels around a sample whose depths bound its band
    coarse_subpixel: bool = False  #: sub-pixel refinement, gap filling, propagation and the ZNCC test at the coarse levels too
    coarse_both_directions: bool = False  #: the reverse pass and left-right check at the coarse levels too
    fill_width: int = 12  #: unmatched samples whose coarse-bounded band is at most this wide are matched by ZNCC (0 = off)


@dataclass
class DenseConfig:
    #: "sgm": semi-global matching over the polar line images (matching/sgm.py); "sefm": the
    #: paper's DP along each line pair with its repairs; "paper": that DP as the paper has
    #: it (no repairs). The keys below belong to the DP.
    method: str = "sgm"
    occlusion_penalty: float = 5.0  #: DP cost of a sample without partner
    band_fraction: float = 0.5  #: DP band half width, as a share of the segment length
    band_min: int = 4
    band_max: int = 24
    occlusion_run: int = 2  #: samples sharing one partner beyond this are occluded
    open_ends: bool = True  #: also match beyond the first and last rough match of a line
    both_directions: bool = True  #: match 2->1 as well and keep the consistent matches
    reverse_max_size: int = 1200  #: ...on images (pyramid levels) up to this longest side; larger ones use the ZNCC test below (0 = always)
    single_min_zncc: float = 0.8  #: min_zncc where the reverse pass does not run: it does most of its work at half the cost
    consistency_px: float = 1.0  #: largest round-trip difference, samples
    subpixel: bool = True  #: refine partners by a parabola through the window correlation
    subpixel_half_window: int = 7  #: its ZNCC window half length, samples
    subpixel_neighbours: int = 1  #: neighbour lines on each side in its window (a surface slanted across the lines shears the outer ones)
    subpixel_iterations: int = 1
    #: line 2's window is stretched by the local slope of the matches (partners of the samples this far
    #: on either side): a slanted surface looks longer in one view (0 = off)
    subpixel_slope_radius: int = 6
    subpixel_min_stretch: float = 0.1  #: slopes closer to 1 than this keep the plain window (cheaper)
    #: the neighbour lines' windows are moved along line 2 by the shear of the matches (how far they move
    #: from one line to the next, averaged over this many samples on either side): on a surface whose
    #: depth changes across lines (a floor seen at a grazing angle) they are on the surface (0 = off)
    subpixel_shear_radius: int = 12
    subpixel_max_shear: float = 2.0  #: larger shears are across a depth edge: left out of the mean
    subpixel_min_shear: float = 0.1  #: smaller shears keep the unmoved window (cheaper)
    min_zncc: float = -1.0  #: drop matches whose window ZNCC (all channels) is below this; needs subpixel (-1 = keep all)
    fill_max_gap: int = 64  #: fill gaps up to this many samples between matches on a line (0 = off)
    fill_radius: int = 3  #: search this many samples around the interpolated partner
    fill_half_window: int = 3  #: ZNCC window half length (all neighbour-line channels)
    fill_min_zncc: float = 0.9  #: correlation a filled match needs
    #: a gap whose partners span over this many times fewer or more samples than it has is a
    #: depth edge and is not filled (0 = fill every gap)
    fill_max_scale: float = 3.0
    propagate_passes: int = 8  #: grow valid matches into unmatched neighbours this many times (0 = off)
    propagate_rounds: int = 2  #: propagation and validation, this many times (the validation drops matches that block growth)
    bridge_max_gap: int = 4  #: after propagation, interpolate gaps of up to this many samples inside a surface (0 = off)
    bridge_slope_tol: float = 0.5  #: where the partners on either side advance within this of the gap's slope
    propagate_radius: int = 1  #: px around a sample whose valid matches bound its band
    propagate_width: int = 6  #: ...when that band is at most this many samples wide
    propagate_min_zncc: float = 0.97  #: ZNCC a propagated match needs (fill_half_window)
    #: where the neighbours' depth range is wider than propagate_width (they hold two surfaces: a depth
    #: edge), the distances at its two ends are searched in turn, each widened by this many samples (-1 = off)
    propagate_split_slack: int = 1
    propagate_split_margin: float = 0.02  #: ...and the better end's ZNCC must beat the other's by this much
    #: propagation also tries the window moved this many samples to either side (0 = centred only):
    #: next to a depth edge the centred window straddles it
    propagate_window_shift: int = 4
    #: ...but not across an intensity step larger than this (levels of the channel mean between
    #: neighbouring samples at rough.jump_reference_size, less in proportion on larger photos;
    #: 0 = no limit): an occluded sample would take the other side's depth
    propagate_shift_max_step: float = 12.0


@dataclass
class ValidityConfig:
    sv_max_unmatched: int = 2  #: S_v: unmatched strong key points allowed inside a segment
    sv_strength: float = 2.0  #: ...where "strong" is a jump of this many thresholds
    sp_depth_jump: float = 0.03  #: S_p: relative depth change that breaks continuity
    sp_min_run: int = 4  #: S_p: shorter continuous runs are dropped
    neighbour_tol_px: float = 0.75  #: 2-D check: largest disparity difference from the neighbours' median, px (0 = off)
    neighbour_radius: int = 2  #: 2-D check window half size, px
    neighbour_support: int = 6  #: neighbours needed to judge a match
    drop_isolated: bool = True  #: drop matches with fewer neighbours than that (instead of keeping them)
    median_depth: bool = True  #: each kept match takes the median depth of its 2-D check window
    max_cost: float = 40.0  #: dense matches with a higher DP cost are dropped
    min_tri_angle_deg: float = 0.5  #: points seen under a smaller angle are dropped


@dataclass
class OutputConfig:
    max_size: int = 3200  #: work on images downscaled to this longest side (px); 0 = never
    mesh: bool = True  #: write mesh.ply
    poisson_depth: int = 9
    density_quantile: float = 0.05  #: trim mesh vertices below this Poisson density quantile
    mesh_max_points: int = 150000
    sparse_max_points: int = 100000  #: points written to the COLMAP model
    normals: str = "grid"  #: "grid": from camera 1's pixel grid (fast); "knn": open3d's KD-tree PCA
    clean_outliers: bool = False  #: open3d statistical outlier removal before writing points.ply (slow; the 2-D check does most of its work)
    progress: bool = True  #: tqdm bar on long runs (the CLI's -q turns it off)


@dataclass
class ColmapConfig:
    """``sefm-recon colmap``: pair selection, fusion and the COLMAP database."""

    min_covisible: int = 30  #: sparse points two images must share to be paired (model with points)
    pairs_per_image: int = 4  #: keep each image's best partners by shared points (0 = all)
    cell_size: float = 2.0  #: px; keypoint quantisation cell (at most one keypoint per cell), as hloc
    max_error: float = 0.75  #: px; a match endpoint farther from its keypoint is dropped
    max_epipolar_error: float = 4.0  #: px; two-view geometry inliers
    tri_min_angle_deg: float = 1.5  #: COLMAP triangulator: smallest triangulation angle
    fuse_voxel_px: float = 1.0  #: fusion voxel, in pixels of footprint at the median depth
    fuse_std_ratio: float = 2.5  #: statistical outlier removal of the fused cloud


@dataclass
class Config:
    sift: SiftConfig = field(default_factory=SiftConfig)
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    lines: LinesConfig = field(default_factory=LinesConfig)
    rough: RoughConfig = field(default_factory=RoughConfig)
    pyramid: PyramidConfig = field(default_factory=PyramidConfig)
    dense: DenseConfig = field(default_factory=DenseConfig)
    validity: ValidityConfig = field(default_factory=ValidityConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    colmap: ColmapConfig = field(default_factory=ColmapConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _coerce(value: Any, kind: type, key: str) -> Any:
    if kind is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "1", "yes", "on", "false", "0", "no", "off"):
            return value.lower() in ("true", "1", "yes", "on")
    elif kind is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, str):
            try:
                return int(value)
            except ValueError:
                pass
    elif kind is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str):
            try:
                return float(value)
            except ValueError:
                pass
    elif kind is str:
        return str(value)
    raise InputError(f"config key {key}: expected {kind.__name__}, got {value!r}")


def _apply(cfg: Config, section: str, key: str, value: Any, internal: bool = False) -> None:
    sub = getattr(cfg, section, None)
    if sub is None or not dataclasses.is_dataclass(sub):
        names = ", ".join(dict.fromkeys(k.split(".")[0] for k in USER_KEYS))
        raise InputError(f"unknown config section {section!r} (sections: {names})")
    types = {f.name: f.type for f in dataclasses.fields(sub)}
    user = [k.split(".")[1] for k in USER_KEYS if k.startswith(section + ".")]
    if key not in types or (not internal and f"{section}.{key}" not in USER_KEYS):
        known = ", ".join(user) or "none: its keys are internal constants of the sequential DP matcher"
        raise InputError(f"unknown config key {section}.{key} (keys: {known})")
    kind = {"int": int, "float": float, "bool": bool, "str": str}[types[key]] if isinstance(types[key], str) else types[key]
    setattr(sub, key, _coerce(value, kind, f"{section}.{key}"))


#: Allowed ranges ``(low, high, low_open)`` of numeric keys; ``None`` = unbounded,
#: ``low_open`` = the low end itself is not allowed. Every float must be finite.
_LIMITS: dict[str, tuple[float | None, float | None, bool]] = {
    "sift.max_features": (1, None, False),
    "sift.max_ratio": (0, 1, True),
    "sift.max_image_size": (0, None, False),
    "pyramid.min_size": (0, None, False),
    "pyramid.factor": (2, 16, False),
    "dense.propagate_passes": (0, 16, False),
    "dense.propagate_rounds": (1, 8, False),
    "dense.bridge_max_gap": (0, 64, False),
    "dense.bridge_slope_tol": (0, None, False),
    "dense.propagate_radius": (1, 16, False),
    "dense.propagate_width": (1, 256, False),
    "dense.propagate_min_zncc": (-1, 1, False),
    "dense.propagate_split_slack": (-1, 64, False),
    "dense.propagate_split_margin": (0, 4, False),
    "pyramid.radius": (0, 16, False),
    "pyramid.fill_width": (0, 256, False),
    "dense.min_zncc": (-1, 1, False),
    "dense.single_min_zncc": (-1, 1, False),
    "dense.subpixel_slope_radius": (0, 64, False),
    "dense.subpixel_shear_radius": (0, 256, False),
    "dense.subpixel_max_shear": (0, None, True),
    "dense.subpixel_min_shear": (0, None, False),
    "dense.propagate_window_shift": (0, 64, False),
    "dense.propagate_shift_max_step": (0, None, False),
    "dense.fill_max_scale": (0, None, False),
    "dense.subpixel_min_stretch": (0, 1, False),
    "dense.reverse_max_size": (0, None, False),
    "geometry.min_inliers": (5, None, False),
    "geometry.ransac_max_error": (0, None, True),
    "geometry.min_tri_angle_deg": (0, 90, False),
    "geometry.depth_margin": (1, None, False),
    "lines.line_spacing": (0.1, None, False),
    "lines.sample_spacing": (0.1, None, False),
    "lines.blur_sigma": (0, 20, False),
    "lines.max_lines": (1, None, False),
    "lines.neighbours": (0, 8, False),
    "lines.neighbour_step": (0, None, True),
    "dense.subpixel_neighbours": (0, 8, False),
    "rough.jump_threshold": (0, None, False),
    "rough.jump_reference_size": (0, None, False),
    "rough.descriptor_radius": (1, 64, False),
    "rough.descriptor_coefficients": (1, 64, False),
    "rough.max_descriptor_distance": (0, None, True),
    "rough.band_slack": (0, None, False),
    "dense.occlusion_penalty": (0, None, False),
    "dense.band_fraction": (0, None, False),
    "dense.band_min": (0, None, False),
    "dense.band_max": (0, None, False),
    "dense.occlusion_run": (1, None, False),
    "validity.sv_max_unmatched": (0, None, False),
    "validity.sv_strength": (0, None, False),
    "validity.sp_depth_jump": (0, None, True),
    "validity.sp_min_run": (1, None, False),
    "validity.max_cost": (0, None, False),
    "validity.min_tri_angle_deg": (0, 90, False),
    "output.max_size": (0, None, False),
    "output.poisson_depth": (1, 12, False),
    "output.density_quantile": (0, 1, False),
    "output.mesh_max_points": (1, None, False),
    "output.sparse_max_points": (0, None, False),
    "colmap.min_covisible": (1, None, False),
    "colmap.pairs_per_image": (0, None, False),
    "colmap.cell_size": (0, None, True),
    "colmap.max_error": (0, None, True),
    "colmap.max_epipolar_error": (0, None, True),
    "colmap.tri_min_angle_deg": (0, 90, False),
    "colmap.fuse_voxel_px": (0, None, True),
    "colmap.fuse_std_ratio": (0, None, True),
}

#: ``output.max_size`` is 0 (never downscale) or at least this many pixels.
MIN_MAX_SIZE = 256


#: String keys and their allowed values.
_CHOICES: dict[str, tuple[str, ...]] = {"output.normals": ("grid", "knn"), "dense.method": ("sgm", "sefm", "paper")}

#: The settings a user sets (``--config`` files and ``--set``); everything else is internal.
USER_KEYS: tuple[str, ...] = (
    "sift.max_features", "sift.max_ratio", "sift.max_image_size",
    "geometry.min_inliers", "geometry.ransac_max_error", "geometry.min_tri_angle_deg",
    "dense.method",
    "output.max_size", "output.mesh", "output.poisson_depth", "output.density_quantile", "output.mesh_max_points",
    "output.sparse_max_points", "output.normals", "output.clean_outliers", "output.progress",
    "colmap.min_covisible", "colmap.pairs_per_image", "colmap.cell_size", "colmap.max_error",
    "colmap.max_epipolar_error", "colmap.tri_min_angle_deg", "colmap.fuse_voxel_px", "colmap.fuse_std_ratio",
)

#: ``dense.method = "paper"``: the sequential DP as close to the paper as the pipeline
#: allows: one epipolar line at a time (no neighbour lines), one direction, matches only
#: between rough matches, S_v strict on every key point, S_p only on isolated spikes, no
#: gap filling, no sub-pixel refinement, no 2-D neighbour check, no propagation across
#: lines, no pre-blur, no coarse-to-fine pyramid.
PAPER: tuple[str, ...] = (
    "lines.blur_sigma=0.0", "lines.neighbours=0", "dense.both_directions=false", "dense.open_ends=false",
    "dense.fill_max_gap=0", "dense.subpixel=false", "dense.propagate_passes=0", "validity.sv_max_unmatched=0",
    "validity.sv_strength=1.0", "validity.sp_min_run=2", "validity.neighbour_tol_px=0.0", "validity.max_cost=1e9",
    "pyramid.min_size=0",
)


def validate(cfg: Config) -> Config:
    """Check every value's range; raises :class:`InputError` naming the key."""
    import math

    for sec in dataclasses.fields(cfg):
        sub = getattr(cfg, sec.name)
        for f in dataclasses.fields(sub):
            key = f"{sec.name}.{f.name}"
            value = getattr(sub, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                raise InputError(f"config key {key}: expected a finite number, got {value!r}")
            if key in _CHOICES and value not in _CHOICES[key]:
                raise InputError(f"config key {key}: one of {', '.join(_CHOICES[key])}, got {value!r}")
            if key not in _LIMITS or isinstance(value, bool) or not isinstance(value, (int, float)):
                continue
            low, high, low_open = _LIMITS[key]
            too_low = low is not None and (value < low or (low_open and value == low))
            if too_low or (high is not None and value > high):
                lo_txt = "" if low is None else f"{'>' if low_open else '>='} {low:g}"
                hi_txt = "" if high is None else f"<= {high:g}"
                rng = " and ".join(t for t in (lo_txt, hi_txt) if t)
                raise InputError(f"config key {key}: must be {rng}, got {value!r}")
    if 0 < cfg.output.max_size < MIN_MAX_SIZE:
        raise InputError(f"config key output.max_size: must be 0 (never downscale) or at least {MIN_MAX_SIZE} px, "
                         f"got {cfg.output.max_size}")
    return cfg


def load_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = (), *,
                internal: bool = False) -> Config:
    """Defaults, then a TOML file, then ``section.key=value`` overrides.

    Only :data:`USER_KEYS` may be set unless ``internal`` (the evaluation and the tests).
    ``dense.method = "paper"`` applies :data:`PAPER` before the overrides.
    """
    cfg = Config()
    items: list[tuple[str, str, Any]] = []
    if path is not None:
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text())
        except FileNotFoundError:
            raise InputError(f"config file not found: {path}") from None
        except tomllib.TOMLDecodeError as err:
            raise InputError(f"config file {path} is not valid TOML: {err}") from None
        except (OSError, UnicodeDecodeError) as err:
            raise InputError(f"cannot read config file {path}: {getattr(err, 'strerror', None) or err}") from None
        for section, values in data.items():
            if not isinstance(values, dict):
                raise InputError(f"config file {path}: {section!r} must be a [section]")
            items += [(section, key, value) for key, value in values.items()]
    for item in overrides:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise InputError(f"bad --set {item!r}: expected SECTION.KEY=VALUE, e.g. output.max_size=2000")
        name, value = item.split("=", 1)
        section, key = name.strip().split(".", 1)
        items.append((section, key, value.strip()))
    for section, key, value in items:
        _apply(cfg, section, key, value, internal)
    if cfg.dense.method == "paper":  # the paper's constants, then whatever was set explicitly
        for item in PAPER:
            name, value = item.split("=", 1)
            _apply(cfg, *name.split(".", 1), value, internal=True)
        for section, key, value in items:
            _apply(cfg, section, key, value, internal)
    return validate(cfg)
