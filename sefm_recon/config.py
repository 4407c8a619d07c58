"""Configuration: typed dataclasses, TOML presets in ``configs/``, ``--set`` overrides.

A config file holds any subset of the sections and keys below; the rest keep
their defaults. ``--set rough.jump_threshold=4`` overrides one key; unknown keys
and wrong types are input errors.
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
    max_features: int = 8192  #: SIFT features per image
    max_ratio: float = 0.8  #: Lowe's ratio test


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


@dataclass
class RoughConfig:
    jump_threshold: float = 4.0  #: da_i above this (0-255 intensity) makes a key point
    descriptor_radius: int = 8  #: half width of the FFT window, samples
    descriptor_coefficients: int = 6  #: Fourier coefficients kept (beyond DC)
    max_descriptor_distance: float = 0.8  #: pairs farther apart never match
    band_slack: int = 3  #: samples added to each side of the depth search band


@dataclass
class DenseConfig:
    occlusion_penalty: float = 10.0  #: DP cost of a sample without partner
    band_fraction: float = 0.3  #: DP band half width, as a share of the segment length
    band_min: int = 4
    band_max: int = 64
    occlusion_run: int = 2  #: samples sharing one partner beyond this are occluded


@dataclass
class ValidityConfig:
    sv_max_unmatched: int = 0  #: S_v: unmatched strong key points allowed inside a segment
    sv_strength: float = 2.0  #: ...where "strong" is a jump of this many thresholds
    sp_depth_jump: float = 0.03  #: S_p: relative depth change that breaks continuity
    sp_min_run: int = 4  #: S_p: shorter continuous runs are dropped
    max_cost: float = 40.0  #: dense matches with a higher DP cost are dropped
    min_tri_angle_deg: float = 0.5  #: points seen under a smaller angle are dropped


@dataclass
class OutputConfig:
    max_size: int = 3200  #: work on images downscaled to this longest side (px); 0 = never
    mesh: bool = True  #: write mesh.ply
    poisson_depth: int = 9
    density_quantile: float = 0.05  #: trim mesh vertices below this Poisson density quantile
    mesh_max_points: int = 300000
    sparse_max_points: int = 100000  #: points written to the COLMAP model
    clean_outliers: bool = True  #: statistical outlier removal before writing points.ply
    progress: bool = True  #: tqdm bar on long runs (the CLI's -q turns it off)


@dataclass
class Config:
    sift: SiftConfig = field(default_factory=SiftConfig)
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    lines: LinesConfig = field(default_factory=LinesConfig)
    rough: RoughConfig = field(default_factory=RoughConfig)
    dense: DenseConfig = field(default_factory=DenseConfig)
    validity: ValidityConfig = field(default_factory=ValidityConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

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


def _apply(cfg: Config, section: str, key: str, value: Any) -> None:
    sub = getattr(cfg, section, None)
    if sub is None or not dataclasses.is_dataclass(sub):
        names = ", ".join(f.name for f in dataclasses.fields(cfg))
        raise InputError(f"unknown config section {section!r} (sections: {names})")
    types = {f.name: f.type for f in dataclasses.fields(sub)}
    if key not in types:
        raise InputError(f"unknown config key {section}.{key} (keys: {', '.join(types)})")
    kind = {"int": int, "float": float, "bool": bool, "str": str}[types[key]] if isinstance(types[key], str) else types[key]
    setattr(sub, key, _coerce(value, kind, f"{section}.{key}"))


def load_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """Defaults, then a TOML file, then ``section.key=value`` overrides."""
    cfg = Config()
    if path is not None:
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text())
        except FileNotFoundError:
            raise InputError(f"config file not found: {path}") from None
        except tomllib.TOMLDecodeError as err:
            raise InputError(f"config file {path} is not valid TOML: {err}") from None
        for section, values in data.items():
            if not isinstance(values, dict):
                raise InputError(f"config file {path}: {section!r} must be a [section]")
            for key, value in values.items():
                _apply(cfg, section, key, value)
    for item in overrides:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise InputError(f"bad --set {item!r}: expected SECTION.KEY=VALUE, e.g. rough.jump_threshold=4")
        name, value = item.split("=", 1)
        section, key = name.strip().split(".", 1)
        _apply(cfg, section, key, value.strip())
    return cfg
