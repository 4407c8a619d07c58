"""Synthetic multi-view scenes with exact ground truth, ray-cast in vectorised numpy.

A scene is a room corner (floor, back wall, two side walls; all one-sided planes, so a
camera is always enclosed) holding several boxes (some rotated about the vertical
axis), spheres and a vertical cylinder.  Every primitive carries its own procedural
colour texture defined on surface coordinates in metres, so the appearance of a surface
point is the same in every view (up to specular highlights, below).  Images are
anti-aliased by ``supersample x supersample`` sub-pixel samples (box filter); texture
detail finer than the pixel footprint is faded out.  The layout (geometry, palettes,
light) of a seed never depends on the style.

Two styles (``render_scene(style=...)``):

``"classic"``
    The look the matcher was tuned on: richly textured surfaces (multi-octave value
    noise, blobs, stripes, dots, planks, veins), Lambertian shading with one
    directional light plus ambient, two to n cameras on an arc about the target,
    noise-free unless ``noise_sigma``/``gain`` are given.  Bit-identical to the
    generator before the random style existed.
``"random"`` (default)
    Each seed draws, from a stream separate from the layout's, a
    :class:`SceneOptions` (see :func:`draw_options`; every drawn value is recorded in
    ``scene.meta["options"]``):

    * a texture family per surface (:data:`TEXTURE_FAMILIES`): ``classic`` (the classic
      texture), ``detail`` (its high-detail variant), ``smooth`` (low-frequency
      noise only: long wavelengths, three octaves, no pattern), ``weak`` (the classic
      texture with its albedo contrast compressed to 0.1-0.3 about its mean),
      ``stripes`` (regular painted stripes) and ``tiles`` (a tile or checker grid with
      grout lines);
    * Blinn-Phong specular highlights that move with the viewpoint (half vector
      between a light and the direction to the camera centre; scene strength and
      shininess, per-surface gloss), from the layout's light and from a second light
      behind the objects that only adds highlights (glossy floors and box tops mirror
      it toward the cameras);
    * per view: exposure 0.75-1.25, white balance 0.9-1.1 per channel, a gamma tone
      curve 0.9-1.1; per scene: vignetting (0-0.35 fall-off at the corners), sensor
      noise sigma 1-3 (8-bit levels, before quantisation) and JPEG compression at
      quality 80-95 (on the final uint8 image);
    * the motion between consecutive views (:data:`MOTIONS`):

      - ``lateral``: parallel cameras translated sideways (baseline 6-16 % of the
        distance to the target), each turned by at most 1 degree: the epipole lies
        far outside the image;
      - ``converging``: the classic orbit about the target (baseline 10-22 %) with
        every view turned off the target by up to 3 degrees and rolled by up to 8;
      - ``forward``: camera 2 moves along camera 1's optical axis by 15-30 % of the
        distance to the target, with a sideways/vertical part of at most 25 %/10 %
        of that, so the epipole lies inside the image;
      - ``zoom``: camera 2 moves toward the target and may also lengthen its focal
        length, so that the scale at the target changes by 1.4-2x.

      The drawn magnitude is redrawn (deterministically) until the pair overlaps
      well and no surface comes close to a camera.  ``motion=`` forces the kind;
      ``"orbit"`` (never drawn) gives the classic cameras.  With ``n_views > 2``
      every consecutive pair follows the drawn kind: lateral and converging views
      repeat the drawn step, while forward and zoom split the drawn motion (view 0
      to the last view) into equal (geometric, for the scale) steps, so that a
      sequence never ends up inside the scene.

    ``render_scene(options=...)`` renders given options instead of drawn ones (e.g.
    ``dataclasses.replace(draw_options(s), noise_sigma=0.0)``);
    ``SceneOptions.classic()`` is neutral: it renders exactly the classic style.

World frame: ``+Y`` is up, the floor is ``y = 0``, the back wall is at ``+z``, the
cameras look roughly along ``+z``.  Conventions are those of ``docs/CONVENTIONS.md``:
COLMAP pixel coordinates (centre of the top-left pixel at (0.5, 0.5)), poses
``x_cam = R @ X + t``, depth maps are float32 z-depth at pixel centres (``inf`` where
nothing is hit).

``python -m sefm_recon.synthetic OUT_DIR --seed 3 [--style classic|random] [--motion
forward]`` writes a COLMAP workspace.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

log = logging.getLogger(__name__)

__all__ = [
    "SyntheticView",
    "SyntheticScene",
    "SceneOptions",
    "SurfaceLook",
    "STYLES",
    "MOTIONS",
    "TEXTURE_FAMILIES",
    "draw_options",
    "render_scene",
    "write_workspace",
    "read_workspace",
    "main",
]

# --------------------------------------------------------------------------- API types


@dataclass
class SyntheticView:
    name: str  # e.g. "view_000.png"
    image: np.ndarray  # (H, W, 3) uint8 RGB
    depth: np.ndarray  # (H, W) float32 z-depth at pixel centres, inf = no hit
    K: np.ndarray  # (3, 3) float64
    R: np.ndarray  # (3, 3) cam_from_world rotation
    t: np.ndarray  # (3,) cam_from_world translation

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        return -self.R.T @ self.t

    def camera(self, camera_id: int = 1):
        """This view's camera as a :class:`pycolmap.Camera` (PINHOLE)."""
        from .io.cameras import pinhole_camera

        return pinhole_camera(self.K, self.depth.shape[1], self.depth.shape[0], camera_id)


@dataclass
class SyntheticScene:
    views: list[SyntheticView]
    meta: dict = field(default_factory=dict)


# ------------------------------------------------------------------- scene options

STYLES = ("classic", "random")
MOTIONS = ("lateral", "converging", "forward", "zoom")  # the kinds the random style draws from
_ALL_MOTIONS = MOTIONS + ("orbit",)  # "orbit": the classic cameras (forced only, never drawn)
TEXTURE_FAMILIES = ("classic", "smooth", "weak", "stripes", "tiles", "detail")  # equal odds (but see _RICH_FAMILIES)
# A room whose large surfaces are all smooth, weak or periodic gives SIFT nothing to find a pose with (and real
# rooms have some texture): the floor or the back wall always has one of these.
_RICH_FAMILIES = ("classic", "detail")
_MAX_SURFACES = 12  # 4 room planes + at most 5 boxes, 2 spheres and 1 cylinder (see _make_world)
_OPTIONS_SALT = 0x0D7A5  # keys the options' SeedSequence, apart from the layout's (0x5EF3) and noise's (0xA015E)

# photometry
_EXPOSURE = (0.75, 1.25)  # per view: auto-exposure of consecutive hand-held shots differs by up to ~1/3 stop
_WHITE_BALANCE = (0.9, 1.1)  # per view and channel: auto-white-balance drift between shots of one scene
_GAMMA = (0.9, 1.1)  # per view: exponent of the tone curve; camera pipelines adapt it to the scene a little
_VIGNETTING = (0.0, 0.35)  # fall-off at the corners: none (corrected lens) to a cheap wide-angle lens
_NOISE = (1.0, 3.0)  # sensor noise sigma [8-bit levels]: a phone in daylight (1) to indoor light (3)
_JPEG_QUALITY = (80, 95)  # usual camera/phone settings; below ~80 block artefacts dominate the texture
_SPECULAR = (0.15, 0.45)  # peak highlight as a share of white: glossy paint and plastic, not metal or mirrors
_SHININESS = (15.0, 80.0)  # Blinn-Phong exponent: a broad sheen (15) to a tight plastic highlight (80)
# The layout's light shines from above the cameras, so its mirror direction misses them on the floor and walls;
# highlights also come from a second light behind the objects (a window or lamp facing the cameras; its diffuse
# part is left to the ambient term), which the floor and box tops mirror toward the cameras.
_HIGHLIGHT_AZIMUTH = 40.0  # max |angle| [deg] of that light from +z (the cameras' viewing direction)
_HIGHLIGHT_ELEVATION = (15.0, 45.0)  # [deg]: the floor mirrors it where the cameras' rays dip by 13-34 deg
_MATTE = 0.3  # share of surfaces with no highlight at all (plaster, cloth, raw wood)
_GLOSS = (0.3, 1.0)  # per glossy surface: share of the scene's specular strength
# texture families (lengths in metres; the scene is seen from 3-10 m with f ~ 1000 px: ~1 cm per pixel)
_SMOOTH_WAVELENGTH = (0.3, 0.8)  # longest detail octave; the finest of its 3 is 7-20 cm, 7-20 px at 7 m
_WEAK_CONTRAST = (0.1, 0.3)  # share of the albedo contrast kept: barely textured paint, plaster, fabric
_STRIPE_PERIOD = (0.04, 0.2)  # 4 px (at 10 m: near the aliasing limit) to 60 px (at 3 m: broad bands) per period
_STRIPE_DUTY = 0.3  # |offset| of the light/dark threshold (sin units): unequal stripe widths
_TILE_SIZE = (0.08, 0.4)  # mosaic to large floor tiles
_GROUT = (0.004, 0.012)  # grout line width, 4-12 mm as in real tiling
_CHECKER = 0.5  # share of tiled surfaces laid as a two-colour checker rather than one glaze
# motion (fractions of the distance from the first camera to the point it aims at)
_LATERAL_STEP = (0.06, 0.16)  # baseline: 3.5-9 degrees of triangulation angle at the target, a usual stereo pair
_CONVERGING_STEP = (0.1, 0.22)  # baseline: the classic orbit's 0.12-0.18 widened on both sides
_FORWARD_STEP = (0.15, 0.3)  # a step or two toward the scene: 1.2-1.4x scale change at the target
_FORWARD_SIDE = 0.25  # max |sideways| / forward move: epipole within 0.25 f (about half way to the edge)
_FORWARD_LIFT = 0.1  # max |vertical| / forward move: epipole within 0.1 f of the centre row
_ZOOM_SCALE = (1.4, 2.0)  # scale change at the target between the first and the last view
_ZOOM_FOCAL_SHARE = (0.0, 0.5)  # share of log(scale) from a longer focal length; the rest is a move, so a baseline stays
_TURN_MAX = {  # per view, max |yaw|, |pitch|, |roll| [deg] added to the aim of each view
    "orbit": (0.0, 0.0, 0.0),  # the classic cameras, unchanged
    "lateral": (1.0, 1.0, 1.0),  # a nearly parallel pair; the epipole stays > 50 f away
    "converging": (3.0, 3.0, 8.0),  # hand-held: off the target by a few degrees, visibly rolled
    "forward": (2.0, 2.0, 3.0),  # small enough that the epipole stays inside the image
    "zoom": (1.5, 1.5, 3.0),  # keeps the target near the centre, where the scale change is measured
}
# what a drawn motion must satisfy (checked on a 32 x 24 ray grid, redrawn otherwise)
_MOTION_TRIES = 40  # redraws of the magnitude before the best attempt is kept
_MIN_OVERLAP = 0.7  # of each consecutive pair, the better-covered view has this share of its pixels seen by the other
_MIN_OVERLAP_OTHER = 0.2  # and the other view at least this share (a 2x zoom's wide view: ~1/4)
_NEAR = 0.4  # a hit closer than this fraction of the camera's distance to the target is "near"
_MAX_NEAR = 0.05  # share of a view's pixels that may be near: no object fills the frame


@dataclass(frozen=True)
class SurfaceLook:
    """How one surface looks in the random style; fields a family does not use stay neutral."""

    family: str = "classic"  # one of TEXTURE_FAMILIES
    scale: float = 0.0  # smooth: longest detail wavelength [m]; stripes: period [m]; tiles: tile size [m]
    contrast: float = 1.0  # weak: share of the albedo contrast kept
    angle: float = 0.0  # stripes, tiles: orientation on the surface [rad]
    width: float = 0.0  # stripes: offset of the light/dark threshold; tiles: grout width [m]
    checker: bool = False  # tiles: two alternating colours
    gloss: float = 0.0  # share of the scene's specular strength (0: matte)


@dataclass(frozen=True)
class SceneOptions:
    """Everything the random style draws for a seed (see :func:`draw_options`).

    The defaults (:meth:`classic`) are neutral and render exactly the classic style;
    an empty per-view tuple means neutral for every view, otherwise it has one entry
    per view.  ``dataclasses.replace`` switches single options off or on.
    """

    motion: str = "orbit"  # one of MOTIONS, or "orbit" (the classic cameras)
    step: float = 0.0  # lateral, converging: baseline / distance; forward: forward move / distance (view 0 to last)
    side: float = 0.0  # forward: sideways move / forward move
    lift: float = 0.0  # forward: vertical move / forward move
    zoom: float = 1.0  # zoom: scale change at the aim point, view 0 to last
    focal_share: float = 0.0  # zoom: share of log(zoom) from the focal length (the rest from moving closer)
    rotations: tuple = ()  # per view (yaw, pitch, roll) [deg] added to the aim
    exposure: tuple = ()  # per view gain
    white_balance: tuple = ()  # per view (r, g, b) gains
    gamma: tuple = ()  # per view tone-curve exponent (out = in ** gamma on [0, 1])
    vignetting: float = 0.0  # brightness lost at the image corners (1 - v r^2, r = 1 at a corner)
    noise_sigma: float = 0.0  # Gaussian sensor noise [8-bit levels], before quantisation
    jpeg_quality: int | None = None  # JPEG round trip of the final image; None: none
    specular: float = 0.0  # Blinn-Phong strength of a fully glossy surface
    shininess: float = 1.0  # Blinn-Phong exponent
    highlight: tuple = ()  # (azimuth, elevation) [deg] of the second, specular-only light; empty: none
    surfaces: tuple = ()  # SurfaceLook per primitive (scene.meta["primitives"] order); empty: all classic

    @classmethod
    def classic(cls) -> "SceneOptions":
        """Neutral options: the classic style's cameras and look."""
        return cls()

    def to_json(self) -> dict:
        return json.loads(json.dumps(dataclasses.asdict(self)))

    @classmethod
    def from_json(cls, d: dict) -> "SceneOptions":
        """Inverse of :meth:`to_json` (e.g. from ``scene.meta["options"]``)."""
        d = dict(d)
        d["surfaces"] = tuple(SurfaceLook(**s) for s in d.get("surfaces", ()))
        for k in ("rotations", "white_balance"):
            d[k] = tuple(tuple(x) for x in d.get(k, ()))
        for k in ("exposure", "gamma", "highlight"):
            d[k] = tuple(d.get(k, ()))
        return cls(**d)


def _draw_surface(rng: np.random.Generator) -> SurfaceLook:
    fam = TEXTURE_FAMILIES[int(rng.integers(len(TEXTURE_FAMILIES)))]
    gloss = 0.0 if rng.random() < _MATTE else float(rng.uniform(*_GLOSS))
    kw: dict = {}
    if fam == "smooth":
        kw = dict(scale=float(rng.uniform(*_SMOOTH_WAVELENGTH)))
    elif fam == "weak":
        kw = dict(contrast=float(rng.uniform(*_WEAK_CONTRAST)))
    elif fam == "stripes":
        kw = dict(
            scale=float(rng.uniform(*_STRIPE_PERIOD)),
            angle=float(rng.uniform(0, math.pi)),
            width=float(rng.uniform(-_STRIPE_DUTY, _STRIPE_DUTY)),
        )
    elif fam == "tiles":
        kw = dict(
            scale=float(rng.uniform(*_TILE_SIZE)),
            angle=float(rng.uniform(0, math.pi / 2)),
            width=float(rng.uniform(*_GROUT)),
            checker=bool(rng.random() < _CHECKER),
        )
    return SurfaceLook(family=fam, gloss=gloss, **kw)


def _draw_motion(rng: np.random.Generator, kind: str) -> dict:
    if kind == "lateral":
        return dict(step=float(rng.uniform(*_LATERAL_STEP)))
    if kind == "converging":
        return dict(step=float(rng.uniform(*_CONVERGING_STEP)))
    if kind == "forward":
        return dict(
            step=float(rng.uniform(*_FORWARD_STEP)),
            side=float(rng.uniform(-_FORWARD_SIDE, _FORWARD_SIDE)),
            lift=float(rng.uniform(-_FORWARD_LIFT, _FORWARD_LIFT)),
        )
    if kind == "zoom":
        return dict(zoom=float(rng.uniform(*_ZOOM_SCALE)), focal_share=float(rng.uniform(*_ZOOM_FOCAL_SHARE)))
    return {}


def draw_options(seed: int, motion: str | None = None, n_views: int = 2, aspect: float = 4 / 3) -> SceneOptions:
    """The random style's options for scene ``seed`` (deterministic).

    Drawn from a SeedSequence of their own (the layout of ``seed`` does not change),
    split into independent streams: the motion kind, its magnitude, the scene-wide
    photometry, one stream per surface and one per view, so forcing ``motion`` or
    changing ``n_views`` leaves the other draws as they are (views 0..n-1 keep their
    values).  The magnitude of the motion is redrawn until every consecutive pair of
    the ``n_views`` cameras (image aspect ``aspect`` = width / height) overlaps well
    and no surface comes close to a camera.
    """
    if n_views < 1:
        raise ValueError("n_views must be >= 1")
    s_kind, s_motion, s_scene, s_surf, s_view = np.random.SeedSequence([int(seed), _OPTIONS_SALT]).spawn(5)
    if motion is None:
        motion = MOTIONS[int(np.random.default_rng(s_kind).integers(len(MOTIONS)))]
    elif motion not in _ALL_MOTIONS:
        raise ValueError(f"unknown motion {motion!r}; expected one of {_ALL_MOTIONS}")
    r = np.random.default_rng(s_scene)
    scene_kw = dict(
        vignetting=float(r.uniform(*_VIGNETTING)),
        noise_sigma=float(r.uniform(*_NOISE)),
        jpeg_quality=int(r.integers(_JPEG_QUALITY[0], _JPEG_QUALITY[1] + 1)),
        specular=float(r.uniform(*_SPECULAR)),
        shininess=float(r.uniform(*_SHININESS)),
        highlight=(
            float(r.uniform(-_HIGHLIGHT_AZIMUTH, _HIGHLIGHT_AZIMUTH)),
            float(r.uniform(*_HIGHLIGHT_ELEVATION)),
        ),
    )
    *s_surfaces, s_rich = s_surf.spawn(_MAX_SURFACES + 1)
    surfaces = [_draw_surface(np.random.default_rng(s)) for s in s_surfaces]
    if surfaces[0].family not in _RICH_FAMILIES and surfaces[1].family not in _RICH_FAMILIES:
        # neither the floor nor the back wall carries features: the back wall takes a rich texture
        fam = _RICH_FAMILIES[int(np.random.default_rng(s_rich).integers(len(_RICH_FAMILIES)))]
        surfaces[1] = SurfaceLook(family=fam, gloss=surfaces[1].gloss)
    surfaces = tuple(surfaces)
    turn_max = np.array(_TURN_MAX[motion])
    exposure, wb, gamma, turns = [], [], [], []
    for sv in s_view.spawn(n_views):
        rv = np.random.default_rng(sv)
        exposure.append(float(rv.uniform(*_EXPOSURE)))
        wb.append(tuple(float(x) for x in rv.uniform(*_WHITE_BALANCE, 3)))
        gamma.append(float(rv.uniform(*_GAMMA)))
        turns.append(tuple(float(x) for x in rv.uniform(-1.0, 1.0, 3) * turn_max))
    base = SceneOptions(
        motion=motion,
        rotations=tuple(turns),
        exposure=tuple(exposure),
        white_balance=tuple(wb),
        gamma=tuple(gamma),
        surfaces=surfaces,
        **scene_kw,
    )
    if motion == "orbit":
        return base
    world, _ = _make_world(seed)
    h = 120.0
    w = h * float(aspect)
    rm = np.random.default_rng(s_motion)
    best, best_score = base, -math.inf
    for _ in range(_MOTION_TRIES):
        cand = dataclasses.replace(base, **_draw_motion(rm, motion))
        cams, _ = _motion_cameras(_layout_streams(seed)[3], world, cand, n_views, w, h)
        score = _motion_quality(world, cams, w, h)
        if score > best_score:
            best, best_score = cand, score
        if score >= 0:
            break
    else:
        log.warning("seed %d: no %s motion met the overlap/clearance checks; keeping the best (%.3f)", seed, motion, best_score)
    return best


def _check_options(opts: SceneOptions, n_views: int) -> None:
    if opts.motion not in _ALL_MOTIONS:
        raise ValueError(f"unknown motion {opts.motion!r}; expected one of {_ALL_MOTIONS}")
    for name in ("rotations", "exposure", "white_balance", "gamma"):
        n = len(getattr(opts, name))
        if n not in (0, n_views):
            raise ValueError(
                f"options.{name} has {n} entries for {n_views} views (draw_options(seed, n_views={n_views}) draws them)"
            )
    if opts.jpeg_quality is not None and not 1 <= opts.jpeg_quality <= 100:
        raise ValueError(f"jpeg_quality must be in 1..100 or None, not {opts.jpeg_quality}")
    for s in opts.surfaces:
        if s.family not in TEXTURE_FAMILIES:
            raise ValueError(f"unknown texture family {s.family!r}; expected one of {TEXTURE_FAMILIES}")


# ------------------------------------------------------------------- noise primitives

_TAB_BITS = 10
_TAB_N = 1 << _TAB_BITS
_TAB_MASK = _TAB_N - 1
_LACUNARITY = 2.03
_FADE_LO, _FADE_HI = 1.25, 2.5  # octave weight ramps from 0 to 1 for wavelength/footprint in this range


def _make_table(rng: np.random.Generator) -> np.ndarray:
    """Random lattice values; row ``i`` holds the 4 corners (i, i+x, i+y, i+x+y) of cell i."""
    t = rng.random((_TAB_N, _TAB_N), dtype=np.float32)
    t4 = np.stack([t, np.roll(t, -1, 1), np.roll(t, -1, 0), np.roll(t, (-1, -1), (0, 1))], axis=-1)
    return np.ascontiguousarray(t4.reshape(-1, 4))


def _hash(tab: np.ndarray, ix: np.ndarray, iy: np.ndarray, salt: int) -> np.ndarray:
    """Deterministic pseudo-random value in [0, 1) per integer lattice cell."""
    iy = (iy + 977 * salt) & _TAB_MASK
    ix = (ix + 331 * salt + 17) & _TAB_MASK
    return tab[(iy << _TAB_BITS) + ix, 0]


def _vnoise(tab: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """2-D value noise in [0, 1] with smoothstep interpolation (float32)."""
    xf = np.floor(x)
    yf = np.floor(y)
    fx = x - xf
    fy = y - yf
    idx = ((yf.astype(np.int32) & _TAB_MASK) << _TAB_BITS) | (xf.astype(np.int32) & _TAB_MASK)
    a, b, c, d = np.take(tab, idx, axis=0).T
    sx = fx * fx * (3.0 - 2.0 * fx)
    sy = fy * fy * (3.0 - 2.0 * fy)
    ab = a + (b - a) * sx
    cd = c + (d - c) * sx
    return ab + (cd - ab) * sy


def _fbm(tab, u, v, fp, lam0, n_oct, pers, rot, off):
    """Multi-octave value noise, zero mean, roughly in [-0.5, 0.5].

    Octave ``o`` has lattice spacing ``lam0 / 2.03**o`` (metres) and is faded to zero
    where it is finer than ~1.5 pixel footprints ``fp`` (metres per pixel at the
    sample).  Normalised by the amplitude sum of all ``n_oct`` octaves, so faded
    octaves lower the contrast instead of being renormalised away.
    """
    out = np.zeros(u.shape, np.float32)
    if u.size == 0:
        return out
    fp_min = float(fp.min())
    amp_sum = sum(pers**o for o in range(n_oct))
    lam = lam0
    amp = 1.0
    for o in range(n_oct):
        if lam < _FADE_LO * fp_min:
            break
        c, s = math.cos(rot[o]), math.sin(rot[o])
        x = (u * np.float32(c / lam) - v * np.float32(s / lam)) + np.float32(off[o, 0])
        y = (u * np.float32(s / lam) + v * np.float32(c / lam)) + np.float32(off[o, 1])
        n = _vnoise(tab, x, y) - np.float32(0.5)
        if lam < _FADE_HI * float(fp.max()):
            w = np.clip((np.float32(lam) / fp - _FADE_LO) / (_FADE_HI - _FADE_LO), 0.0, 1.0)
            n *= w
        out += np.float32(amp / amp_sum) * n
        lam /= _LACUNARITY
        amp *= pers
    return out


def _aa_weight(period: float, fp: np.ndarray) -> np.ndarray:
    """1 where a feature of size ``period`` is well resolved, 0 where it would alias."""
    return np.clip((np.float32(period) / fp - 2.0) / 2.0, 0.0, 1.0)


def _smoothstep(e0, e1, x):
    tt = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return tt * tt * (3.0 - 2.0 * tt)


def _hsv(h: float, s: float, v: float) -> np.ndarray:
    i = int(h * 6.0) % 6
    f = h * 6.0 - math.floor(h * 6.0)
    p, q, r = v * (1 - s), v * (1 - s * f), v * (1 - s * (1 - f))
    rgb = [(v, r, p), (q, v, p), (p, v, r), (p, q, v), (r, p, v), (v, p, q)][i]
    return np.array(rgb, np.float32)


# ------------------------------------------------------------------------- textures



@dataclass
class _Tex:
    pal: np.ndarray  # (4, 3) float32 albedo colours
    lo_lam: float  # wavelength of the colour-variation field
    hi_lam: float  # base wavelength of the detail (luminance) field
    pers: float  # detail persistence
    detail: float  # detail amplitude
    pattern: str
    pp: dict  # pattern parameters
    rot: np.ndarray  # (3, 12) per-field, per-octave rotations
    off: np.ndarray  # (3, 12, 2) per-field, per-octave lattice offsets
    salt: int
    family: str = "classic"  # texture family (TEXTURE_FAMILIES); only the random style changes it
    hi_oct: int = 9  # octaves of the detail field
    contrast: float = 1.0  # weak family: albedo contrast kept about ``mean``
    mean: np.ndarray | None = None  # weak family: (3,) mean albedo
    look: dict = field(default_factory=dict)  # stripes/tiles parameters

    def to_json(self) -> dict:
        out = {
            "pattern": self.pattern,
            "palette": np.round(self.pal, 4).tolist(),
            "lo_lambda": self.lo_lam,
            "hi_lambda": self.hi_lam,
            "persistence": self.pers,
            "detail": self.detail,
        }
        if self.family != "classic":
            out["family"] = self.family
            if self.mean is not None:
                out["contrast"] = self.contrast
                out["mean_albedo"] = np.round(self.mean, 4).tolist()
            out.update(self.look)
        return out


def _make_tex(rng: np.random.Generator, pattern: str, smooth: bool) -> _Tex:
    h0 = rng.random()
    pal = np.stack(
        [
            _hsv(h0, rng.uniform(0.25, 0.75), rng.uniform(0.45, 0.85)),
            _hsv((h0 + rng.uniform(-0.12, 0.12)) % 1.0, rng.uniform(0.2, 0.8), rng.uniform(0.35, 0.9)),
            _hsv((h0 + rng.uniform(0.3, 0.7)) % 1.0, rng.uniform(0.4, 0.95), rng.uniform(0.3, 0.95)),
            _hsv(rng.random(), rng.uniform(0.3, 0.9), rng.uniform(0.5, 0.95)),
        ]
    )
    if smooth:  # smoother, but never flat
        pers, detail, hi_lam = rng.uniform(0.45, 0.58), rng.uniform(0.15, 0.35), rng.uniform(0.04, 0.1)
    else:
        pers, detail, hi_lam = rng.uniform(0.62, 0.75), rng.uniform(0.6, 0.9), rng.uniform(0.08, 0.2)
    pp: dict = {}
    if pattern == "blobs":
        pp = dict(lam=rng.uniform(0.1, 0.3), th=rng.uniform(0.0, 0.06), strength=rng.uniform(0.6, 0.95))
    elif pattern == "stripes":
        pp = dict(
            period=rng.uniform(0.06, 0.16),
            angle=rng.uniform(0, math.pi),
            warp=rng.uniform(0.8, 2.0),
            bias=rng.uniform(-0.3, 0.3),
            strength=rng.uniform(0.5, 0.85),
        )
    elif pattern == "dots":
        pp = dict(cell=rng.uniform(0.06, 0.13), rmin=0.12, rmax=rng.uniform(0.28, 0.4), p=rng.uniform(0.5, 0.85))
    elif pattern == "veins":
        pp = dict(lam=rng.uniform(0.15, 0.4), width=rng.uniform(0.012, 0.03), strength=rng.uniform(0.5, 0.85))
    elif pattern == "planks":
        pp = dict(width=rng.uniform(0.12, 0.25), length=rng.uniform(0.8, 1.6), seam=0.006)
    return _Tex(
        pal=pal,
        lo_lam=float(rng.uniform(0.35, 1.0)),
        hi_lam=float(hi_lam),
        pers=float(pers),
        detail=float(detail),
        pattern=pattern,
        pp={k: float(x) for k, x in pp.items()},
        rot=rng.uniform(0, 2 * math.pi, (3, 12)),
        off=rng.uniform(0, _TAB_N, (3, 12, 2)),
        salt=int(rng.integers(1, 1000)),
    )


def _texture(tab: np.ndarray, tx: _Tex, u: np.ndarray, v: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """Albedo (N, 3) float32 of texture ``tx`` at surface coordinates (u, v) [m]."""
    u = u.astype(np.float32, copy=False)
    v = v.astype(np.float32, copy=False)
    fp = fp.astype(np.float32, copy=False)
    if tx.family in ("stripes", "tiles"):
        return _periodic_texture(tab, tx, u, v, fp)
    # low-frequency colour variation
    lo = _fbm(tab, u, v, fp, tx.lo_lam, 3, 0.5, tx.rot[0], tx.off[0])
    s = np.clip(0.5 + 2.2 * lo, 0.0, 1.0)[:, None]
    col = tx.pal[0] + (tx.pal[1] - tx.pal[0]) * s
    # multi-octave luminance detail
    hi = _fbm(tab, u, v, fp, tx.hi_lam, tx.hi_oct, tx.pers, tx.rot[1], tx.off[1])
    lum = np.clip(1.0 + (3.2 * tx.detail) * hi, 0.15, 2.0)
    pp = tx.pp
    m = None
    pcol = None
    if tx.pattern == "blobs":
        b = _fbm(tab, u, v, fp, pp["lam"], 3, 0.45, tx.rot[2], tx.off[2])
        m = _smoothstep(pp["th"] - 0.015, pp["th"] + 0.015, b) * pp["strength"]
        pcol = tx.pal[2]
    elif tx.pattern == "stripes":
        ca, sa = math.cos(pp["angle"]), math.sin(pp["angle"])
        warp = _fbm(tab, u, v, fp, 0.5, 2, 0.5, tx.rot[2], tx.off[2])
        ph = (u * ca + v * sa) / pp["period"] + pp["warp"] * warp
        k = np.floor(ph).astype(np.int64)
        m = _smoothstep(-0.25, 0.25, np.sin((2 * math.pi) * ph) - pp["bias"])
        m *= _aa_weight(pp["period"], fp) * pp["strength"]
        shade = 0.55 + 0.9 * _hash(tab, k, k * 7 + 3, tx.salt)
        pcol = tx.pal[2] * shade[:, None]
    elif tx.pattern == "dots":
        c = pp["cell"]
        gx, gy = u / c, v / c
        cx, cy = np.floor(gx), np.floor(gy)
        ix, iy = cx.astype(np.int64), cy.astype(np.int64)
        r = pp["rmin"] + (pp["rmax"] - pp["rmin"]) * _hash(tab, ix, iy, tx.salt + 1)
        jx = (0.5 - r) * (2 * _hash(tab, ix, iy, tx.salt + 2) - 1)
        jy = (0.5 - r) * (2 * _hash(tab, ix, iy, tx.salt + 3) - 1)
        d = np.hypot(gx - cx - 0.5 - jx, gy - cy - 0.5 - jy)
        e = np.maximum(0.06, 0.5 * fp / c)
        present = _hash(tab, ix, iy, tx.salt + 4) < pp["p"]
        m = (1.0 - _smoothstep(r - e, r + e, d)) * present * _aa_weight(2 * pp["rmin"] * c, fp)
        mix = _hash(tab, ix, iy, tx.salt + 5)[:, None]
        pcol = tx.pal[2] + (tx.pal[3] - tx.pal[2]) * mix
    elif tx.pattern == "veins":
        b = _fbm(tab, u, v, fp, pp["lam"], 4, 0.55, tx.rot[2], tx.off[2])
        w = np.float32(pp["width"])
        m = (1.0 - _smoothstep(0.0, w, np.abs(b))) * pp["strength"] * _aa_weight(10 * w * pp["lam"], fp)
        pcol = tx.pal[2] * 0.6
    elif tx.pattern == "planks":
        pw, pl, sw = pp["width"], pp["length"], pp["seam"]
        gv = v / pw
        kv = np.floor(gv)
        ik = kv.astype(np.int64)
        gu = u / pl + _hash(tab, ik, ik, tx.salt + 1) * 7.0
        ku = np.floor(gu)
        iu = ku.astype(np.int64)
        tint = 0.7 + 0.6 * _hash(tab, iu, ik, tx.salt + 2)
        # along-plank grain: anisotropic noise
        grain = _fbm(tab, u * 0.15 + 50.0 * (ik % 13), v * 2.0, fp * 2.0, 0.05, 4, 0.6, np.zeros(12), tx.off[2])
        lum = lum * tint * (1.0 + 1.2 * grain)
        fv = (gv - kv) * pw
        fu = (gu - ku) * pl
        seam = np.minimum(np.minimum(fv, pw - fv), np.minimum(fu, pl - fu))
        ew = np.maximum(np.float32(sw), fp * 0.5)
        m = (1.0 - _smoothstep(0.5 * ew, 1.5 * ew, seam)) * 0.75
        pcol = tx.pal[0] * 0.25
    col = col * lum[:, None]
    if m is not None:
        mm = m[:, None]
        col = col * (1.0 - mm) + (pcol * lum[:, None]) * mm
    col = np.clip(col, 0.0, 1.0).astype(np.float32, copy=False)
    if tx.mean is not None:  # weak family: the same texture at a fraction of its contrast
        col = tx.mean + np.float32(tx.contrast) * (col - tx.mean)
    return col


def _periodic_texture(tab: np.ndarray, tx: _Tex, u: np.ndarray, v: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """Albedo of the ``stripes`` and ``tiles`` families: a regular pattern whose
    repeats look alike, on a gentle large-scale shading (as paint or tiles under
    uneven light); anti-aliased by the pixel footprint ``fp``."""
    lk = tx.look
    lo = _fbm(tab, u, v, fp, tx.lo_lam, 3, 0.5, tx.rot[0], tx.off[0])
    shade = (1.0 + 0.5 * lo)[:, None]
    ca, sa = math.cos(lk["angle"]), math.sin(lk["angle"])
    a = u * np.float32(ca) + v * np.float32(sa)
    if tx.family == "stripes":
        period = lk["period"]
        # edges about one pixel footprint wide; fade to the average colour where stripes would alias
        e = np.maximum(np.float32(0.08), np.float32(math.pi / period) * fp)
        m = _smoothstep(-e, e, np.sin(np.float32(2 * math.pi / period) * a) - np.float32(lk["duty"]))
        m = 0.5 + (m - 0.5) * _aa_weight(period, fp)
        col = tx.pal[0] + (tx.pal[2] - tx.pal[0]) * m[:, None]
    else:
        size, grout = lk["size"], lk["grout"]
        b = v * np.float32(ca) - u * np.float32(sa)
        gx, gy = a / np.float32(size), b / np.float32(size)
        kx, ky = np.floor(gx), np.floor(gy)
        ix, iy = kx.astype(np.int64), ky.astype(np.int64)
        if lk["checker"]:
            c = ((ix + iy) & 1).astype(np.float32)
            c = 0.5 + (c - 0.5) * _aa_weight(size, fp)
            col = tx.pal[0] + (tx.pal[2] - tx.pal[0]) * c[:, None]
        else:  # one glaze, each tile a slightly different shade
            col = tx.pal[0] * (0.9 + 0.2 * _hash(tab, ix, iy, tx.salt))[:, None]
        fx, fy = (gx - kx) * np.float32(size), (gy - ky) * np.float32(size)
        seam = np.minimum(np.minimum(fx, size - fx), np.minimum(fy, size - fy))
        ew = np.maximum(np.float32(grout / 2), fp * 0.5)
        g = (1.0 - _smoothstep(0.5 * ew, 1.5 * ew, seam))[:, None]
        col = col * (1.0 - g) + _GROUT_RGB * g
    return np.clip(col * shade, 0.0, 1.0).astype(np.float32, copy=False)


_GROUT_RGB = np.array([0.62, 0.6, 0.57], np.float32)  # mid grey: visible against both light and dark tiles


def _mean_albedo(tab: np.ndarray, tx: _Tex) -> np.ndarray:
    """Mean albedo (3,) of a texture over a 4 m x 4 m patch seen at ~1 cm per pixel."""
    g = (np.arange(64, dtype=np.float32) + 0.5) * np.float32(4.0 / 64)
    u, v = (a.ravel() for a in np.meshgrid(g, g))
    return _texture(tab, tx, u, v, np.full(u.shape, 0.01, np.float32)).mean(axis=0).astype(np.float32)


def _restyle(tab: np.ndarray, tx: _Tex, look: "SurfaceLook") -> _Tex:
    """The texture ``tx`` (drawn as in the classic style) turned into ``look.family``."""
    fam = look.family
    if fam not in TEXTURE_FAMILIES:
        raise ValueError(f"unknown texture family {fam!r}; expected one of {TEXTURE_FAMILIES}")
    if fam in ("classic", "detail"):  # "detail" was drawn with the non-smooth parameters
        return dataclasses.replace(tx, family=fam)
    if fam == "smooth":
        # a few long octaves only: the finest is scale / 4.1, i.e. 7-20 cm (10-30 px at 7 m)
        return dataclasses.replace(
            tx, family=fam, pattern="none", pp={}, hi_lam=float(look.scale), hi_oct=3, pers=0.5, detail=0.35,
            lo_lam=2.0 * tx.lo_lam,
        )
    if fam == "weak":
        return dataclasses.replace(tx, family=fam, contrast=float(look.contrast), mean=_mean_albedo(tab, tx))
    if fam == "stripes":
        lk = {"period": float(look.scale), "angle": float(look.angle), "duty": float(look.width)}
    else:
        lk = {"size": float(look.scale), "angle": float(look.angle), "grout": float(look.width),
              "checker": bool(look.checker)}
    return dataclasses.replace(tx, family=fam, pattern="none", pp={}, look=lk)


# ----------------------------------------------------------------------- primitives

_EPS = 1e-7


class _Prim:
    kind = "prim"
    tex: _Tex
    spec = 0.0  # Blinn-Phong specular strength (0: matte, the classic style)

    def intersect(self, C: np.ndarray, D: np.ndarray) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def surface(self, tab, P, D, dist_per_px):  # -> (albedo (N,3), normal (N,3))
        raise NotImplementedError

    def describe(self) -> dict:  # pragma: no cover
        raise NotImplementedError

    def corners(self):
        """Corners of a world-space hull (for screen-space culling); None = unbounded."""
        return None


class _Plane(_Prim):
    """One-sided plane ``n . X + c = 0`` seen from the side ``n . X + c > 0``."""

    kind = "plane"

    def __init__(self, name, n, c, uaxis, vaxis, tex):
        self.name = name
        self.n = np.asarray(n, float)
        self.c = float(c)
        self.ua = np.asarray(uaxis, float)
        self.va = np.asarray(vaxis, float)
        self.tex = tex

    def intersect(self, C, D):
        nd = D @ self.n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -(self.n @ C + self.c) / nd
        return np.where((nd < 0) & (t > _EPS), t, np.inf)

    def surface(self, tab, P, D, dist_per_px):
        n = np.broadcast_to(self.n, P.shape)
        fp = _footprint(n, D, dist_per_px)
        alb = _texture(tab, self.tex, P @ self.ua, P @ self.va, fp)
        return alb, n

    def describe(self):
        return {"type": self.name, "normal": self.n.tolist(), "offset": self.c, "texture": self.tex.to_json()}


def _yaw_matrix(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


class _Box(_Prim):
    kind = "box"

    def __init__(self, center, half, yaw, tex):
        self.center = np.asarray(center, float)
        self.half = np.asarray(half, float)
        self.yaw = float(yaw)
        self.Ry = _yaw_matrix(yaw)  # world_from_local
        self.tex = tex

    def intersect(self, C, D):
        O = self.Ry.T @ (C - self.center)
        Dl = D @ self.Ry
        tn = None
        with np.errstate(divide="ignore", invalid="ignore"):
            for a in range(3):
                inv = 1.0 / Dl[..., a]
                t1 = (-self.half[a] - O[a]) * inv
                t2 = (self.half[a] - O[a]) * inv
                if tn is None:
                    tn, tf = np.minimum(t1, t2), np.maximum(t1, t2)
                else:
                    tn = np.maximum(tn, np.minimum(t1, t2))
                    tf = np.minimum(tf, np.maximum(t1, t2))
        return np.where((tn <= tf) & (tn > _EPS), tn, np.inf)

    def corners(self):
        s = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        return (s * self.half) @ self.Ry.T + self.center

    def surface(self, tab, P, D, dist_per_px):
        pl = (P - self.center) @ self.Ry
        r = np.abs(pl) / self.half
        ax = np.argmax(r, axis=1)
        sgn = np.sign(pl[np.arange(len(pl)), ax])
        nl = np.zeros_like(pl)
        nl[np.arange(len(pl)), ax] = sgn
        n = nl @ self.Ry.T
        fp = _footprint(n, D, dist_per_px)
        # per-face planar coordinates (+ an offset so that faces differ)
        face = ax * 2 + (sgn > 0)
        u = np.where(ax == 0, pl[:, 2], pl[:, 0]) + 7.3 * face
        v = np.where(ax == 1, pl[:, 2], pl[:, 1]) + 3.1 * face
        alb = _texture(tab, self.tex, u, v, fp)
        return alb, n

    def describe(self):
        return {
            "type": "box",
            "center": self.center.tolist(),
            "half_size": self.half.tolist(),
            "yaw": self.yaw,
            "texture": self.tex.to_json(),
        }


def _triplanar(tab, tex, pl, n, fp):
    w = n**4
    w /= w.sum(axis=1, keepdims=True)
    alb = np.zeros((len(pl), 3), np.float32)
    for a, (i, j) in enumerate(((1, 2), (0, 2), (0, 1))):
        sel = w[:, a] > 0.01
        if np.any(sel):
            uv = pl[sel]
            alb[sel] += w[sel, a, None].astype(np.float32) * _texture(
                tab, tex, uv[:, i] + 5.0 * a, uv[:, j] - 3.0 * a, fp[sel]
            )
    return alb


class _Sphere(_Prim):
    kind = "sphere"

    def __init__(self, center, radius, tex):
        self.center = np.asarray(center, float)
        self.r = float(radius)
        self.tex = tex

    def intersect(self, C, D):
        oc = C - self.center
        a = D[..., 0] ** 2 + D[..., 1] ** 2 + D[..., 2] ** 2
        b = D @ oc
        cc = oc @ oc - self.r**2
        disc = b * b - a * cc
        with np.errstate(invalid="ignore"):
            t = (-b - np.sqrt(disc)) / a
        return np.where((disc >= 0) & (t > _EPS), t, np.inf)

    def corners(self):
        s = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        return s * self.r + self.center

    def surface(self, tab, P, D, dist_per_px):
        pl = P - self.center
        n = pl / self.r
        fp = _footprint(n, D, dist_per_px)
        return _triplanar(tab, self.tex, pl, n, fp), n

    def describe(self):
        return {"type": "sphere", "center": self.center.tolist(), "radius": self.r, "texture": self.tex.to_json()}


class _Cylinder(_Prim):
    """Vertical cylinder standing on the floor (side + top cap)."""

    kind = "cylinder"

    def __init__(self, cx, cz, radius, y0, y1, tex):
        self.cx, self.cz, self.r, self.y0, self.y1 = map(float, (cx, cz, radius, y0, y1))
        self.tex = tex

    def intersect(self, C, D):
        ox, oz = C[0] - self.cx, C[2] - self.cz
        dx, dy, dz = D[..., 0], D[..., 1], D[..., 2]
        a = dx * dx + dz * dz
        b = dx * ox + dz * oz
        cc = ox * ox + oz * oz - self.r**2
        disc = b * b - a * cc
        with np.errstate(invalid="ignore", divide="ignore"):
            ts = (-b - np.sqrt(disc)) / a
            y = C[1] + ts * dy
            ok = (disc >= 0) & (ts > _EPS) & (y >= self.y0) & (y <= self.y1)
            t = np.where(ok, ts, np.inf)
            if C[1] > self.y1:
                tc = (self.y1 - C[1]) / dy
                xc = ox + tc * dx
                zc = oz + tc * dz
                okc = (dy < 0) & (tc > _EPS) & (xc * xc + zc * zc <= self.r**2)
                t = np.minimum(t, np.where(okc, tc, np.inf))
        return t

    def corners(self):
        return np.array(
            [[self.cx + x * self.r, y, self.cz + z * self.r] for x in (-1, 1) for y in (self.y0, self.y1) for z in (-1, 1)]
        )

    def surface(self, tab, P, D, dist_per_px):
        x = P[:, 0] - self.cx
        z = P[:, 2] - self.cz
        rad = np.hypot(x, z)
        cap = np.abs(P[:, 1] - self.y1) < np.abs(rad - self.r)
        n = np.zeros_like(P)
        with np.errstate(invalid="ignore", divide="ignore"):
            n[:, 0] = np.where(cap, 0.0, x / rad)
            n[:, 2] = np.where(cap, 0.0, z / rad)
        n[:, 1] = np.where(cap, 1.0, 0.0)
        fp = _footprint(n, D, dist_per_px)
        u = np.where(cap, x + 11.0, self.r * np.arctan2(x, -z))  # seam at the back (+z)
        v = np.where(cap, z - 4.0, P[:, 1])
        return _texture(tab, self.tex, u, v, fp), n

    def describe(self):
        return {
            "type": "cylinder",
            "center_xz": [self.cx, self.cz],
            "radius": self.r,
            "y_range": [self.y0, self.y1],
            "texture": self.tex.to_json(),
        }


def _footprint(n, D, dist_per_px):
    """Approximate pixel footprint on the surface [m] (isotropic, obliquity-capped)."""
    dn = np.abs(n[:, 0] * D[:, 0] + n[:, 1] * D[:, 1] + n[:, 2] * D[:, 2])
    dn /= np.sqrt(D[:, 0] ** 2 + D[:, 1] ** 2 + D[:, 2] ** 2)
    return (dist_per_px / np.maximum(dn, 0.25)).astype(np.float32)


# ------------------------------------------------------------------- scene layout


@dataclass
class _World:
    prims: list
    tab: np.ndarray
    light: np.ndarray
    ambient: float
    target: np.ndarray
    shininess: float = 1.0  # Blinn-Phong exponent of the surfaces with ``spec > 0``
    highlight: np.ndarray | None = None  # direction to a second light that only adds highlights


def _layout_streams(seed: int) -> list[np.random.Generator]:
    """The layout's random streams: layout, textures, noise table, cameras."""
    return [np.random.default_rng(s) for s in np.random.SeedSequence([int(seed), 0x5EF3]).spawn(4)]


def _make_world(
    seed: int,
    looks: Sequence[SurfaceLook] | None = None,
    specular: float = 0.0,
    shininess: float = 1.0,
    highlight: Sequence[float] = (),
) -> tuple[_World, np.random.Generator]:
    """The scene ``seed`` and its camera stream.

    ``looks[i]`` restyles the texture of primitive ``i`` (random style) and sets its
    gloss; ``highlight`` = (azimuth, elevation) [deg] adds a specular-only light. The
    layout, palettes and all draws of the classic style are unchanged.
    """
    r_lay, r_tex, r_tab, r_cam = _layout_streams(seed)
    tab = _make_table(r_tab)
    prims: list[_Prim] = []

    def tex(pattern: str, smooth: bool) -> _Tex:
        look = looks[len(prims)] if looks and len(prims) < len(looks) else None
        # "detail" takes the non-smooth ranges; both branches make the same number of draws
        tx = _make_tex(r_tex, pattern, smooth and not (look is not None and look.family == "detail"))
        return tx if look is None else _restyle(tab, tx, look)

    # patterns assigned without too many repeats
    n_box = int(r_lay.integers(3, 6))
    n_sph = int(r_lay.integers(1, 3))
    n_cyl = int(r_lay.integers(0, 2))
    n_obj = n_box + n_sph + n_cyl
    obj_patterns = [p for p in r_tex.permutation(["blobs", "stripes", "dots", "veins", "none", "blobs", "dots"])]
    obj_patterns = (obj_patterns * 3)[:n_obj]
    smooth_flags = r_tex.random(n_obj + 4) < 0.35

    zw = float(r_lay.uniform(2.6, 3.6))
    xl, xr = float(r_lay.uniform(5.5, 7.0)), float(r_lay.uniform(5.5, 7.0))
    # appended one by one, in the classic order of draws: tex() reads the index len(prims)
    prims.append(_Plane("floor", [0, 1, 0], 0.0, [1, 0, 0], [0, 0, 1], tex(str(r_tex.choice(["planks", "blobs", "dots"])), False)))
    prims.append(_Plane("back_wall", [0, 0, -1], zw, [1, 0, 0], [0, 1, 0], tex(str(r_tex.choice(["blobs", "veins", "dots"])), bool(smooth_flags[-1]))))
    prims.append(_Plane("left_wall", [-1, 0, 0], xl, [0, 0, 1], [0, 1, 0], tex(str(r_tex.choice(["blobs", "veins", "dots"])), bool(smooth_flags[-2]))))
    prims.append(_Plane("right_wall", [1, 0, 0], xr, [0, 0, 1], [0, 1, 0], tex(str(r_tex.choice(["blobs", "veins", "dots"])), bool(smooth_flags[-3]))))
    # inside is n.X + c >= 0; the cameras' right is world -x, so "left_wall" is x = +xl

    placed: list[tuple[float, float, float]] = []  # (x, z, footprint radius)

    def place(radius: float) -> tuple[float, float] | None:
        for _ in range(200):
            x = float(r_lay.uniform(-2.8, 2.8))
            z = float(r_lay.uniform(-2.2, zw - radius - 0.25))
            if all(math.hypot(x - px, z - pz) > radius + pr + 0.12 for px, pz, pr in placed):
                placed.append((x, z, radius))
                return x, z
        return None

    k = 0
    boxes: list[_Box] = []
    for i in range(n_box):
        half = np.array([r_lay.uniform(0.2, 0.7), r_lay.uniform(0.15, 0.8), r_lay.uniform(0.2, 0.6)])
        yaw = 0.0 if r_lay.random() < 0.35 else float(r_lay.uniform(-0.8, 0.8))
        pos = place(float(np.hypot(half[0], half[2])))
        if pos is None:
            continue
        b = _Box([pos[0], half[1], pos[1]], half, yaw, tex(obj_patterns[k], bool(smooth_flags[k])))
        k += 1
        boxes.append(b)
        prims.append(b)
    for i in range(n_sph):
        r = float(r_lay.uniform(0.3, 0.65))
        if i == 1 and boxes and r_lay.random() < 0.6:  # a small ball resting on a box
            b = boxes[int(r_lay.integers(len(boxes)))]
            r = float(min(r, 0.8 * b.half[0], 0.8 * b.half[2], 0.4))
            c = [b.center[0], 2 * b.half[1] + r, b.center[2]]
        else:
            pos = place(r)
            if pos is None:
                continue
            c = [pos[0], r, pos[1]]
        prims.append(_Sphere(c, r, tex(obj_patterns[k], bool(smooth_flags[k]))))
        k += 1
    for i in range(n_cyl):
        r = float(r_lay.uniform(0.2, 0.45))
        pos = place(r)
        if pos is None:
            continue
        prims.append(
            _Cylinder(pos[0], pos[1], r, 0.0, float(r_lay.uniform(0.6, 1.9)), tex(obj_patterns[k], bool(smooth_flags[k])))
        )
        k += 1

    light = np.array([r_lay.uniform(-0.7, 0.3), 1.0, r_lay.uniform(-0.9, -0.4)])
    light /= np.linalg.norm(light)
    target = np.array([r_lay.uniform(-0.3, 0.3), r_lay.uniform(0.5, 0.8), r_lay.uniform(0.0, 0.6)])
    if looks:
        for p, look in zip(prims, looks):
            p.spec = float(specular) * float(look.gloss)
    light2 = None
    if len(highlight):
        az, el = (math.radians(float(a)) for a in highlight)
        light2 = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
    world = _World(prims, tab, light, float(r_lay.uniform(0.3, 0.4)), target, float(shininess), light2)
    return world, r_cam


def _look_at(C: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    z = target - C
    z /= np.linalg.norm(z)
    down = np.array([0.0, -1.0, 0.0])
    x = np.cross(down, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # cam_from_world
    c, s = math.cos(roll), math.sin(roll)
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    return Rz @ R


def _make_cameras(rng, world: _World, n_views: int, width: int, height: int):
    f = float(rng.uniform(0.95, 1.15)) * width
    K = np.array([[f, 0, width / 2.0], [0, f, height / 2.0], [0, 0, 1.0]])
    dist = float(rng.uniform(6.3, 7.5))  # horizontal distance to the target
    hcam = float(rng.uniform(2.2, 3.2))
    frac = float(rng.uniform(0.12, 0.18))  # baseline / distance between neighbours
    step = 2 * math.asin(frac / 2)
    a0 = float(rng.uniform(-0.12, 0.12))
    cams = []
    for k in range(n_views):
        a = a0 + (k - (n_views - 1) / 2) * step
        # camera "right" is world -x when looking along +z: view k+1 is right of view k
        C = world.target + np.array([-dist * math.sin(a), 0.0, -dist * math.cos(a)])
        C[1] = hcam
        C = C + rng.uniform(-0.08, 0.08, 3)
        look = world.target + rng.uniform(-0.15, 0.15, 3)
        R = _look_at(C, look, float(rng.uniform(-0.01, 0.01)))
        t = -R @ C
        cams.append((K.copy(), R, t))
    return cams, {"focal": f, "distance": dist, "camera_height": hcam, "baseline_fraction": frac}


def _turn(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """cam_from_cam rotation turning a camera by yaw (about its y), pitch (x) and roll (z) [deg]."""
    cy, sy = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    cp, sp = math.cos(math.radians(pitch)), math.sin(math.radians(pitch))
    cr, sr = math.cos(math.radians(roll)), math.sin(math.radians(roll))
    Ry = np.array([[cy, 0, sy], [0, 1.0, 0], [-sy, 0, cy]])
    Rx = np.array([[1.0, 0, 0], [0, cp, -sp], [0, sp, cp]])
    Rz = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1.0]])
    return Rz @ Rx @ Ry


def _motion_cameras(rng, world: _World, opts: SceneOptions, n_views: int, width, height):
    """Cameras of the random style: the first view as the classic one, the rest by ``opts.motion``.

    The first camera takes the classic draws (focal length, distance and height,
    position on the arc, jitter, aim point ``look``), centred on the arc for
    ``converging``/``lateral``.  ``orbit`` is exactly :func:`_make_cameras`.
    """
    if opts.motion == "orbit":
        cams, meta = _make_cameras(rng, world, n_views, width, height)
    else:
        f = float(rng.uniform(0.95, 1.15)) * width
        dist = float(rng.uniform(6.3, 7.5))
        hcam = float(rng.uniform(2.2, 3.2))
        rng.uniform(0.12, 0.18)  # the classic baseline: drawn and unused, so the draws below stay those of classic
        a0 = float(rng.uniform(-0.12, 0.12))
        jitter = rng.uniform(-0.08, 0.08, 3)
        look = world.target + rng.uniform(-0.15, 0.15, 3)

        def on_arc(a: float) -> np.ndarray:
            C = world.target + np.array([-dist * math.sin(a), 0.0, -dist * math.cos(a)])
            C[1] = hcam
            return C + jitter

        C0 = on_arc(a0)
        R0 = _look_at(C0, look, 0.0)
        L = float(np.linalg.norm(look - C0))
        m = max(n_views - 1, 1)
        cams = []
        for k in range(n_views):
            c = k - (n_views - 1) / 2  # centred index: lateral/converging views straddle C0
            fk = f
            if opts.motion == "lateral":
                C, R = C0 + (c * opts.step * L) * R0[0], R0.copy()
            elif opts.motion == "converging":
                C = on_arc(a0 + c * 2 * math.asin(opts.step / 2))
                R = _look_at(C, look, 0.0)
            elif opts.motion == "forward":
                C = C0 + (k / m * opts.step * L) * (R0[2] + opts.side * R0[0] + opts.lift * R0[1])
                R = R0.copy()
            else:  # zoom
                C = look + (C0 - look) / opts.zoom ** ((1.0 - opts.focal_share) * k / m)
                fk = f * opts.zoom ** (opts.focal_share * k / m)
                R = _look_at(C, look, 0.0)
            K = np.array([[fk, 0, width / 2.0], [0, fk, height / 2.0], [0, 0, 1.0]])
            cams.append((K, R, -R @ C))
        Cs = [-R.T @ t for _, R, t in cams]
        meta = {
            "focal": f,
            "focals": [float(K[0, 0]) for K, _, _ in cams],
            "distance": dist,
            "camera_height": hcam,
            "baseline_fraction": float(np.linalg.norm(Cs[1] - Cs[0]) / L) if n_views > 1 else 0.0,
            "look_at": look.tolist(),
        }
    if any(any(a != 0 for a in rot) for rot in opts.rotations):
        turned = []
        for (K, R, t), rot in zip(cams, opts.rotations):
            C = -R.T @ t
            R = _turn(*rot) @ R
            turned.append((K, R, -R @ C))
        cams = turned
    return cams, meta


def _cast_rays(world: _World, C: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Ray parameter of the first hit along ``C + t D`` (rays (N, 3))."""
    best = np.full(len(D), np.inf)
    for p in world.prims:
        best = np.minimum(best, p.intersect(C, D))
    return best


def _seen_share(world: _World, cam, X: np.ndarray, width, height) -> float:
    """Share of the world points ``X`` inside the image of ``cam`` and not occluded."""
    K, R, t = cam
    C = -R.T @ t
    Xc = X @ R.T + t
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * Xc[:, 0] / z + K[0, 2]
        v = K[1, 1] * Xc[:, 1] / z + K[1, 2]
    inside = (z > 1e-6) & (u >= 0) & (u <= width) & (v >= 0) & (v <= height)
    hit = _cast_rays(world, C, X[inside] - C)  # the point itself is at t = 1
    return float(np.count_nonzero(hit > 0.995)) / max(len(X), 1)


def _motion_quality(world: _World, cams, width, height) -> float:
    """>= 0 when every view is clear of near surfaces and consecutive views overlap well."""
    nu, nv = 32, 24
    us = (np.arange(nu) + 0.5) * (width / nu)
    vs = (np.arange(nv) + 0.5) * (height / nv)
    score = math.inf
    pts = []
    for K, R, t in cams:
        C = -R.T @ t
        D, z, _ = _cast_grid(world, C, K, R, us, vs, [None] * len(world.prims))
        ok = np.isfinite(z)
        near = np.mean(~ok | (z < _NEAR * np.linalg.norm(world.target - C)))
        score = min(score, _MAX_NEAR - near)
        pts.append(C + z[ok][:, None] * D[ok])
    for k in range(len(cams) - 1):
        a = _seen_share(world, cams[k + 1], pts[k], width, height)
        b = _seen_share(world, cams[k], pts[k + 1], width, height)
        score = min(score, max(a, b) - _MIN_OVERLAP, min(a, b) - _MIN_OVERLAP_OTHER)
    return score


# ----------------------------------------------------------------------- rendering


def _screen_bounds(world: _World, K, R, t, width, height, margin=2.0):
    """Per primitive (u0, u1, v0, v1) pixel bounds of its projection (None = whole image)."""
    out = []
    for p in world.prims:
        cn = p.corners()
        if cn is None:
            out.append(None)
            continue
        Xc = cn @ R.T + t
        if np.any(Xc[:, 2] < 1e-3):
            out.append(None)
            continue
        u = K[0, 0] * Xc[:, 0] / Xc[:, 2] + K[0, 2]
        v = K[1, 1] * Xc[:, 1] / Xc[:, 2] + K[1, 2]
        out.append((u.min() - margin, u.max() + margin, v.min() - margin, v.max() + margin))
    return out


def _cast_grid(world: _World, C, K, R, us, vs, bounds):
    """Cast the rays of the sample grid ``vs x us`` (COLMAP pixel coords).

    Returns the unnormalised world directions (nv, nu, 3) (camera-z component 1), the
    ray parameter ``t`` (= z-depth) and the hit primitive index (-1: none).
    """
    xs = (us - K[0, 2]) / K[0, 0]
    ys = (vs - K[1, 2]) / K[1, 1]
    D = xs[None, :, None] * R[0] + ys[:, None, None] * R[1] + R[2]
    best = np.full(D.shape[:2], np.inf)
    pid = np.full(D.shape[:2], -1, np.int32)
    for i, (p, bd) in enumerate(zip(world.prims, bounds)):
        if bd is None:
            sl = (slice(None), slice(None))
        else:
            b0, b1 = np.searchsorted(us, bd[0]), np.searchsorted(us, bd[1], "right")
            a0, a1 = np.searchsorted(vs, bd[2]), np.searchsorted(vs, bd[3], "right")
            if b1 <= b0 or a1 <= a0:
                continue
            sl = (slice(a0, a1), slice(b0, b1))
        ti = p.intersect(C, D[sl])
        m = ti < best[sl]
        best[sl][m] = ti[m]
        pid[sl][m] = i
    return D, best, pid


def _shade(world: _World, C, D, t, pid, f):
    col = np.zeros((len(D), 3), np.float32)
    order = np.argsort(pid, kind="stable")
    counts = np.bincount(pid + 1, minlength=len(world.prims) + 1)
    starts = np.concatenate([[0], np.cumsum(counts)])
    for i, p in enumerate(world.prims):
        sel = order[starts[i + 1] : starts[i + 2]]
        if sel.size == 0:
            continue
        Ds = D[sel]
        ts = t[sel]
        P = C + ts[:, None] * Ds
        dist_per_px = ts * np.sqrt(Ds[:, 0] ** 2 + Ds[:, 1] ** 2 + Ds[:, 2] ** 2) / f
        alb, n = p.surface(world.tab, P, Ds, dist_per_px)
        nl = n @ world.light
        lam = world.ambient + (1.0 - world.ambient) * np.maximum(nl, 0.0)
        c = alb * lam[:, None].astype(np.float32)
        if p.spec > 0:
            # Blinn-Phong: half vector between a light and the direction to the camera
            # centre C (= -D), so the highlight moves with the viewpoint
            to_cam = -Ds / np.sqrt(np.einsum("ij,ij->i", Ds, Ds))[:, None]
            for L in (world.light,) if world.highlight is None else (world.light, world.highlight):
                hv = L + to_cam
                hv /= np.linalg.norm(hv, axis=1, keepdims=True)
                nh = np.maximum(np.einsum("ij,ij->i", n, hv), 0.0)
                c += (p.spec * np.where(n @ L > 0, nh**world.shininess, 0.0)).astype(np.float32)[:, None]
        col[sel] = c
    return col


def _render_view(world, K, R, t, width, height, ss, chunk_samples=1 << 17, workers=None):
    C = -R.T @ t
    f = float(K[0, 0])
    bounds = _screen_bounds(world, K, R, t, width, height)
    img = np.zeros((height, width, 3), np.float32)
    depth = np.full((height, width), np.inf, np.float32)
    sub = (np.arange(ss) + 0.5) / ss
    rows = max(1, chunk_samples // (width * ss * ss))
    us = (np.arange(width)[:, None] + sub[None, :]).reshape(-1)  # (W*ss,) increasing
    uc = np.arange(width) + 0.5
    inv = np.float32(1.0 / (ss * ss))

    def do_chunk(r0: int) -> None:
        r1 = min(height, r0 + rows)
        nr = r1 - r0
        vs = (np.arange(r0, r1)[:, None] + sub[None, :]).reshape(-1)
        D, tt, pid = _cast_grid(world, C, K, R, us, vs, bounds)
        col = _shade(world, C, D.reshape(-1, 3), tt.reshape(-1), pid.reshape(-1), f)
        col = col.reshape(nr, ss, width, ss, 3)
        acc = np.zeros((nr, width, 3), np.float32)
        for a in range(ss):
            for b in range(ss):
                acc += col[:, a, :, b, :]
        img[r0:r1] = acc * inv
        # exact depth at pixel centres
        _, tc, _ = _cast_grid(world, C, K, R, uc, np.arange(r0, r1) + 0.5, bounds)
        depth[r0:r1] = tc

    starts = range(0, height, rows)
    n_workers = workers or min(4, os.cpu_count() or 1)
    if n_workers > 1 and len(starts) > 1:
        # numpy releases the GIL in its inner loops; chunks write disjoint rows
        with ThreadPoolExecutor(n_workers) as ex:
            list(ex.map(do_chunk, starts))
    else:
        for r0 in starts:
            do_chunk(r0)
    return img, depth


def _bbox_from_depths(views: list[SyntheticView], step: int = 4):
    pts = []
    for vw in views:
        H, W = vw.depth.shape
        ii, jj = np.mgrid[0:H:step, 0:W:step]
        d = vw.depth[ii, jj].astype(np.float64)
        ok = np.isfinite(d)
        uv1 = np.stack([jj[ok] + 0.5, ii[ok] + 0.5, np.ones(ok.sum())])
        Xc = (np.linalg.inv(vw.K) @ uv1) * d[ok]
        pts.append((vw.R.T @ (Xc - vw.t[:, None])).T)
    P = np.concatenate(pts) if pts else np.zeros((0, 3))
    if len(P) == 0:
        return np.zeros(3), np.zeros(3)
    return P.min(axis=0), P.max(axis=0)


def _vignette(width: int, height: int, strength: float) -> np.ndarray:
    """(H, W) float32 gain ``1 - strength * r^2``, r = 1 at the image corners."""
    cx, cy = width / 2.0, height / 2.0
    x2 = ((np.arange(width) + 0.5 - cx) ** 2) / (cx * cx + cy * cy)
    y2 = ((np.arange(height) + 0.5 - cy) ** 2) / (cx * cx + cy * cy)
    return (1.0 - strength * (y2[:, None] + x2[None, :])).astype(np.float32)


def _jpeg(img: np.ndarray, quality: int) -> np.ndarray:
    """JPEG round trip of an (H, W, 3) uint8 RGB image."""
    import cv2

    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [int(cv2.IMWRITE_JPEG_QUALITY), int(quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def render_scene(
    seed: int = 0,
    width: int = 1000,
    height: int = 750,
    n_views: int = 2,
    noise_sigma: float = 0.0,
    gain=None,
    supersample: int = 2,
    *,
    style: str = "random",
    motion: str | None = None,
    options: SceneOptions | None = None,
) -> SyntheticScene:
    """Render ``n_views`` views of the random scene ``seed`` with exact ground truth.

    ``noise_sigma``: Gaussian sensor noise (8-bit levels) added before quantisation;
    in the random style it adds (in quadrature) to the drawn noise.
    ``gain``: per-view multiplicative gains (scalar or sequence of length ``n_views``);
    in the random style they multiply the drawn exposures.
    ``supersample``: sub-pixel samples per axis (area average).
    ``style``: ``"classic"`` (the look the matcher was tuned on, bit-identical to the
    generator before styles existed) or ``"random"`` (textures, photometry and motion
    drawn from the seed, see the module docstring).
    ``motion``: random style only: force the kind of motion (one of :data:`MOTIONS`,
    or ``"orbit"`` for the classic cameras); None draws it.
    ``options``: random style only: render these :class:`SceneOptions` instead of
    ``draw_options(seed, motion, n_views, width / height)``.
    The options used are in ``scene.meta["options"]``, the style in ``meta["style"]``,
    the motion in ``meta["motion"]`` and the total noise sigma in ``meta["noise_sigma"]``.
    """
    if n_views < 1:
        raise ValueError("n_views must be >= 1")
    if width < 2 or height < 2:
        raise ValueError("image too small")
    if style not in STYLES:
        raise ValueError(f"unknown style {style!r}; expected one of {STYLES}")
    if gain is None:
        gains = [1.0] * n_views
    elif np.isscalar(gain):
        gains = [float(gain)] * n_views
    else:
        gains = [float(g) for g in gain]
        if len(gains) != n_views:
            raise ValueError(f"gain has {len(gains)} entries, expected n_views={n_views}")
    if style == "classic":
        if options is not None or motion is not None:
            raise ValueError("style='classic' takes no options or motion (use style='random')")
        opts = SceneOptions.classic()
    elif options is None:
        opts = draw_options(seed, motion, n_views, width / height)
    else:
        if motion is not None and motion != options.motion:
            raise ValueError(f"motion={motion!r} contradicts options.motion={options.motion!r}")
        opts = options
    _check_options(opts, n_views)
    t0 = time.perf_counter()
    world, r_cam = _make_world(seed, opts.surfaces, opts.specular, opts.shininess, opts.highlight)
    cams, cam_meta = _motion_cameras(r_cam, world, opts, n_views, width, height)
    noise_rngs = [np.random.default_rng(s) for s in np.random.SeedSequence([int(seed), 0xA015E]).spawn(n_views)]
    sigma = float(math.hypot(noise_sigma, opts.noise_sigma)) if opts.noise_sigma else float(noise_sigma)
    vignette = _vignette(width, height, opts.vignetting) if opts.vignetting else None
    views = []
    for k, (K, R, t) in enumerate(cams):
        lin, depth = _render_view(world, K, R, t, width, height, supersample)
        img = lin * np.float32(255.0 * gains[k])
        # camera response of the random style (each step skipped when neutral: classic stays bit-identical)
        wb = np.float32(opts.exposure[k] if opts.exposure else 1.0) * np.asarray(
            opts.white_balance[k] if opts.white_balance else (1.0, 1.0, 1.0), np.float32
        )
        if np.any(wb != 1.0):
            img *= wb
        if vignette is not None:
            img *= vignette[:, :, None]
        if opts.gamma and opts.gamma[k] != 1.0:
            img = np.float32(255.0) * (np.clip(img, 0.0, 255.0) * np.float32(1 / 255.0)) ** np.float32(opts.gamma[k])
        if sigma > 0:
            img += noise_rngs[k].normal(0.0, sigma, img.shape).astype(np.float32)
        img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        if opts.jpeg_quality is not None:
            img = _jpeg(img, opts.jpeg_quality)
        views.append(SyntheticView(f"view_{k:03d}.png", img, depth, K, R, t))
    lo, hi = _bbox_from_depths(views)
    meta = {
        "seed": int(seed),
        "width": int(width),
        "height": int(height),
        "n_views": int(n_views),
        "noise_sigma": sigma,
        "gain": gains,
        "supersample": int(supersample),
        "scene_bbox": [lo.tolist(), hi.tolist()],
        "scene_size": float(np.linalg.norm(hi - lo)),
        "target": world.target.tolist(),
        "light": world.light.tolist(),
        "ambient": world.ambient,
        "primitives": [p.describe() for p in world.prims],
        **cam_meta,
        "style": style,
        "motion": opts.motion,
        "options": opts.to_json(),
    }
    log.debug(
        "rendered seed %d (%s, %s, %dx%d, %d views) in %.2fs",
        seed, style, opts.motion, width, height, n_views, time.perf_counter() - t0,
    )
    return SyntheticScene(views, meta)


# ------------------------------------------------------------------------ workspace


def write_workspace(scene: SyntheticScene, out_dir) -> Path:
    """Write ``images/``, ``sparse/`` (COLMAP text model, true poses) and ``gt/``."""
    import cv2
    import pycolmap

    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "sparse").mkdir(parents=True, exist_ok=True)
    (out / "gt").mkdir(parents=True, exist_ok=True)
    rec = pycolmap.Reconstruction()
    for i, vw in enumerate(scene.views, start=1):
        rec.add_camera_with_trivial_rig(vw.camera(i))
        im = pycolmap.Image(name=vw.name, camera_id=i, image_id=i)
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(np.hstack([vw.R, vw.t.reshape(3, 1)])))
        if not cv2.imwrite(str(out / "images" / vw.name), cv2.cvtColor(vw.image, cv2.COLOR_RGB2BGR)):
            raise OSError(f"could not write {out / 'images' / vw.name}")
        np.save(out / "gt" / f"{Path(vw.name).stem}.depth.npy", vw.depth.astype(np.float32))
    rec.write_text(str(out / "sparse"))
    meta = dict(scene.meta)
    meta["views"] = [vw.name for vw in scene.views]
    (out / "gt" / "scene.json").write_text(json.dumps(meta, indent=1))
    log.info(
        "wrote %d views (%s) to %s: images/, sparse/ (COLMAP text), gt/",
        len(scene.views),
        ", ".join(v.name for v in scene.views),
        out,
    )
    return out


def colmap_sfm(ws_dir):
    """Replace ``ws_dir/sparse`` by COLMAP's own SfM of ``ws_dir/images`` (in ``sparse/0``).

    SIFT, exhaustive matching and incremental mapping through pycolmap, so the
    workspace is what COLMAP itself writes (estimated cameras, poses up to a
    similarity, sparse points). Returns the first :class:`pycolmap.Reconstruction`.
    """
    import pycolmap

    ws = Path(ws_dir)
    for p in (ws / "sparse").iterdir():
        p.unlink()
    db = ws / "sfm.db"
    ext = pycolmap.FeatureExtractionOptions()
    ext.use_gpu = False
    pycolmap.extract_features(db, ws / "images", extraction_options=ext, device=pycolmap.Device.cpu)
    mat = pycolmap.FeatureMatchingOptions()
    mat.use_gpu = False
    pycolmap.match_exhaustive(db, matching_options=mat, device=pycolmap.Device.cpu)
    (ws / "sparse" / "0").mkdir()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.random_seed = 0
    recs = pycolmap.incremental_mapping(db, ws / "images", ws / "sparse", options=opts)
    if not recs:
        raise RuntimeError("pycolmap's incremental mapping reconstructed nothing")
    return recs[0]


def align_to_truth(rec, scene: SyntheticScene):
    """Similarity ``X_true = s R X + t`` from a model's image poses to the scene's true ones.

    Returns ``(s, R, t)``; the rotation is the chordal mean of the per-view
    rotation differences, scale and translation fit the camera centres.
    """
    by_name = {im.name: im for im in rec.images.values()}
    rots, cm, ct = [], [], []
    for v in scene.views:
        M = np.asarray(by_name[v.name].cam_from_world().matrix())
        rots.append(v.R.T @ M[:, :3])
        cm.append(-M[:, :3].T @ M[:, 3])
        ct.append(v.center)
    U, _, Vt = np.linalg.svd(sum(rots))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    cm, ct = np.array(cm), np.array(ct)
    a, b = (cm - cm.mean(0)) @ R.T, ct - ct.mean(0)
    s = float(np.sum(a * b) / np.sum(a * a))
    return s, R, ct.mean(0) - s * R @ cm.mean(0)


def read_workspace(ws_dir) -> SyntheticScene:
    """Read a workspace written by :func:`write_workspace`."""
    import cv2
    import pycolmap

    ws = Path(ws_dir)
    rec = pycolmap.Reconstruction(str(ws / "sparse"))
    meta_path = ws / "gt" / "scene.json"
    meta = json.loads(meta_path.read_text()) if meta_path.exists() else {}
    views = []
    for iid in sorted(rec.images):
        im = rec.images[iid]
        cfw = im.cam_from_world
        cfw = cfw() if callable(cfw) else cfw
        M = np.asarray(cfw.matrix(), float)
        K = np.asarray(im.camera.calibration_matrix(), float)
        bgr = cv2.imread(str(ws / "images" / im.name), cv2.IMREAD_COLOR)
        if bgr is None:
            raise FileNotFoundError(ws / "images" / im.name)
        dpath = ws / "gt" / f"{Path(im.name).stem}.depth.npy"
        depth = np.load(dpath) if dpath.exists() else np.full(bgr.shape[:2], np.inf, np.float32)
        views.append(
            SyntheticView(im.name, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), depth, K, M[:, :3].copy(), M[:, 3].copy())
        )
    order = meta.get("views")
    if order:
        views.sort(key=lambda v: order.index(v.name) if v.name in order else len(order))
    meta.pop("views", None)
    return SyntheticScene(views, meta)


# ---------------------------------------------------------------------------- CLI


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m sefm_recon.synthetic", description=__doc__.split("\n")[0])
    ap.add_argument("out_dir")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--width", type=int, default=1000)
    ap.add_argument("--height", type=int, default=750)
    ap.add_argument("--views", type=int, default=2)
    ap.add_argument("--noise", type=float, default=0.0, help="Gaussian sensor noise sigma [8-bit levels]")
    ap.add_argument("--gain", type=float, nargs="+", default=None, help="per-view gains")
    ap.add_argument("--supersample", type=int, default=2)
    ap.add_argument("--style", choices=STYLES, default="random", help="classic: the tuned look; random: drawn from the seed")
    ap.add_argument("--motion", choices=_ALL_MOTIONS, default=None, help="random style: force the motion (default: drawn)")
    ap.add_argument("-v", "--verbose", action="store_true")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if a.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    if a.style == "classic" and a.motion is not None:
        ap.error("--motion needs --style random")
    t0 = time.perf_counter()
    scene = render_scene(
        a.seed, a.width, a.height, a.views, a.noise, a.gain, a.supersample, style=a.style, motion=a.motion
    )
    log.info(
        "rendered seed %d (%s, motion %s), %dx%d, %d views in %.2fs",
        a.seed, a.style, scene.meta["motion"], a.width, a.height, a.views, time.perf_counter() - t0,
    )
    out = write_workspace(scene, a.out_dir)
    print(out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
