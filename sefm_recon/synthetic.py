"""Synthetic multi-view scenes with exact ground truth, ray-cast in vectorised numpy.

A scene is a room corner (floor, back wall, two side walls; all one-sided planes, so a
camera is always enclosed) holding several boxes (some rotated about the vertical
axis), spheres and a vertical cylinder.  Every primitive carries its own procedural
colour texture defined on surface coordinates in metres (multi-octave value noise,
blobs, stripes, dots, planks, veins), so the appearance of a surface point is the same
in every view.  Shading is Lambertian with one directional light plus ambient (view
independent).  Images are anti-aliased by ``supersample x supersample`` sub-pixel
samples (box filter); texture octaves finer than the pixel footprint are faded out.

World frame: ``+Y`` is up, the floor is ``y = 0``, the back wall is at ``+z``, the
cameras look roughly along ``+z``.  Conventions are those of ``docs/CONVENTIONS.md``:
COLMAP pixel coordinates (centre of the top-left pixel at (0.5, 0.5)), poses
``x_cam = R @ X + t``, depth maps are float32 z-depth at pixel centres (``inf`` where
nothing is hit).

``python -m sefm_recon.synthetic OUT_DIR --seed 3`` writes a COLMAP workspace.
"""

from __future__ import annotations

import argparse
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

    def to_json(self) -> dict:
        return {
            "pattern": self.pattern,
            "palette": np.round(self.pal, 4).tolist(),
            "lo_lambda": self.lo_lam,
            "hi_lambda": self.hi_lam,
            "persistence": self.pers,
            "detail": self.detail,
        }


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
    # low-frequency colour variation
    lo = _fbm(tab, u, v, fp, tx.lo_lam, 3, 0.5, tx.rot[0], tx.off[0])
    s = np.clip(0.5 + 2.2 * lo, 0.0, 1.0)[:, None]
    col = tx.pal[0] + (tx.pal[1] - tx.pal[0]) * s
    # multi-octave luminance detail
    hi = _fbm(tab, u, v, fp, tx.hi_lam, 9, tx.pers, tx.rot[1], tx.off[1])
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
    return np.clip(col, 0.0, 1.0).astype(np.float32, copy=False)


# ----------------------------------------------------------------------- primitives

_EPS = 1e-7


class _Prim:
    kind = "prim"
    tex: _Tex

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


def _make_world(seed: int) -> tuple[_World, np.random.Generator]:
    ss = np.random.SeedSequence([int(seed), 0x5EF3])
    r_lay, r_tex, r_tab, r_cam = (np.random.default_rng(s) for s in ss.spawn(4))
    tab = _make_table(r_tab)

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
    prims: list[_Prim] = [
        _Plane("floor", [0, 1, 0], 0.0, [1, 0, 0], [0, 0, 1], _make_tex(r_tex, str(r_tex.choice(["planks", "blobs", "dots"])), False)),
        _Plane("back_wall", [0, 0, -1], zw, [1, 0, 0], [0, 1, 0], _make_tex(r_tex, str(r_tex.choice(["blobs", "veins", "dots"])), bool(smooth_flags[-1]))),
        _Plane("left_wall", [-1, 0, 0], xl, [0, 0, 1], [0, 1, 0], _make_tex(r_tex, str(r_tex.choice(["blobs", "veins", "dots"])), bool(smooth_flags[-2]))),
        _Plane("right_wall", [1, 0, 0], xr, [0, 0, 1], [0, 1, 0], _make_tex(r_tex, str(r_tex.choice(["blobs", "veins", "dots"])), bool(smooth_flags[-3]))),
    ]
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
        b = _Box([pos[0], half[1], pos[1]], half, yaw, _make_tex(r_tex, obj_patterns[k], bool(smooth_flags[k])))
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
        prims.append(_Sphere(c, r, _make_tex(r_tex, obj_patterns[k], bool(smooth_flags[k]))))
        k += 1
    for i in range(n_cyl):
        r = float(r_lay.uniform(0.2, 0.45))
        pos = place(r)
        if pos is None:
            continue
        prims.append(
            _Cylinder(pos[0], pos[1], r, 0.0, float(r_lay.uniform(0.6, 1.9)), _make_tex(r_tex, obj_patterns[k], bool(smooth_flags[k])))
        )
        k += 1

    light = np.array([r_lay.uniform(-0.7, 0.3), 1.0, r_lay.uniform(-0.9, -0.4)])
    light /= np.linalg.norm(light)
    target = np.array([r_lay.uniform(-0.3, 0.3), r_lay.uniform(0.5, 0.8), r_lay.uniform(0.0, 0.6)])
    return _World(prims, tab, light, float(r_lay.uniform(0.3, 0.4)), target), r_cam


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
        lam = world.ambient + (1.0 - world.ambient) * np.maximum(n @ world.light, 0.0)
        col[sel] = alb * lam[:, None].astype(np.float32)
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


def render_scene(
    seed: int = 0,
    width: int = 1000,
    height: int = 750,
    n_views: int = 2,
    noise_sigma: float = 0.0,
    gain=None,
    supersample: int = 2,
) -> SyntheticScene:
    """Render ``n_views`` views of the random scene ``seed`` with exact ground truth.

    ``noise_sigma``: Gaussian sensor noise (8-bit levels) added before quantisation.
    ``gain``: per-view multiplicative gains (scalar or sequence of length ``n_views``).
    ``supersample``: sub-pixel samples per axis (area average).
    """
    if n_views < 1:
        raise ValueError("n_views must be >= 1")
    if width < 2 or height < 2:
        raise ValueError("image too small")
    if gain is None:
        gains = [1.0] * n_views
    elif np.isscalar(gain):
        gains = [float(gain)] * n_views
    else:
        gains = [float(g) for g in gain]
        if len(gains) != n_views:
            raise ValueError(f"gain has {len(gains)} entries, expected n_views={n_views}")
    t0 = time.perf_counter()
    world, r_cam = _make_world(seed)
    cams, cam_meta = _make_cameras(r_cam, world, n_views, width, height)
    noise_rngs = [np.random.default_rng(s) for s in np.random.SeedSequence([int(seed), 0xA015E]).spawn(n_views)]
    views = []
    for k, (K, R, t) in enumerate(cams):
        lin, depth = _render_view(world, K, R, t, width, height, supersample)
        img = lin * np.float32(255.0 * gains[k])
        if noise_sigma > 0:
            img += noise_rngs[k].normal(0.0, noise_sigma, img.shape).astype(np.float32)
        img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        views.append(SyntheticView(f"view_{k:03d}.png", img, depth, K, R, t))
    lo, hi = _bbox_from_depths(views)
    meta = {
        "seed": int(seed),
        "width": int(width),
        "height": int(height),
        "n_views": int(n_views),
        "noise_sigma": float(noise_sigma),
        "gain": gains,
        "supersample": int(supersample),
        "scene_bbox": [lo.tolist(), hi.tolist()],
        "scene_size": float(np.linalg.norm(hi - lo)),
        "target": world.target.tolist(),
        "light": world.light.tolist(),
        "ambient": world.ambient,
        "primitives": [p.describe() for p in world.prims],
        **cam_meta,
    }
    log.debug("rendered seed %d (%dx%d, %d views) in %.2fs", seed, width, height, n_views, time.perf_counter() - t0)
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
    ap.add_argument("-v", "--verbose", action="store_true")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if a.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    t0 = time.perf_counter()
    scene = render_scene(a.seed, a.width, a.height, a.views, a.noise, a.gain, a.supersample)
    log.info("rendered seed %d, %dx%d, %d views in %.2fs", a.seed, a.width, a.height, a.views, time.perf_counter() - t0)
    out = write_workspace(scene, a.out_dir)
    print(out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
