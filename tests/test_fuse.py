"""Multi-view consistent fusion (sefm_recon.reconstruct.fuse) on exact synthetic geometry."""

from __future__ import annotations

import numpy as np
import pycolmap

from sefm_recon.io.ply import iter_point_cloud, write_point_cloud
from sefm_recon.reconstruct.fuse import FusionView, fuse_pairs, project

W, H, F = 160, 120, 160.0
PLANE_Z = 5.0


def _view(x: float) -> FusionView:
    cam = pycolmap.Camera(model="PINHOLE", width=W, height=H, params=[F, F, W / 2, H / 2])
    return FusionView(cam, np.eye(3), np.array([-x, 0.0, 0.0]))  # centre at (x, 0, 0), looking along +z


def _plane_points(view: FusionView, step: int = 1, z: float = PLANE_Z) -> np.ndarray:
    """The plane z = ``z`` seen through the pixel centres of a view (every ``step``-th pixel)."""
    u, v = np.meshgrid(np.arange(0.5, W, step), np.arange(0.5, H, step))
    rays = np.c_[(u.ravel() - W / 2) / F, (v.ravel() - H / 2) / F, np.ones(u.size)]
    return view.centre + rays * (z / rays[:, 2:3])


def _cloud(xyz: np.ndarray):
    return (xyz, np.full((len(xyz), 3), 100, np.uint8), np.tile([0.0, 0.0, -1.0], (len(xyz), 1)))


def _fuse(views, pairs, clouds, **kw):
    return fuse_pairs(views, pairs, lambda k: iter([clouds[k]]), **kw)


def test_consistent_points_are_kept_and_merged_into_tracks():
    views = [_view(x) for x in (0.0, 0.3, 0.6, 0.9)]
    # three pairs along the row of cameras, each seeing the same plane: every pair is confirmed by the others
    pairs = [(0, 1), (1, 2), (2, 3)]
    clouds = [_cloud(_plane_points(views[a])) for a, _ in pairs]
    f = _fuse(views, pairs, clouds)
    assert f.stats["input_points"] == 3 * W * H
    # nothing contradicts a plane; only its rims, which no third view sees, lack a confirmation
    assert f.stats["dropped_free_space"] + f.stats["dropped_background"] + f.stats["dropped_hidden"] == 0
    assert f.stats["kept"] + f.stats["dropped_unconfirmed"] == f.stats["input_points"]
    assert f.stats["kept"] > 0.85 * f.stats["input_points"]
    # the plane's middle is seen by all four views: those points have four-view tracks ...
    inner = np.abs(f.xyz[:, 0] - 0.45) < 0.5
    assert np.mean(f.support[inner] == 4) > 0.95
    i = int(np.flatnonzero(inner & (f.support == 4))[0])
    assert f.track(i) == [0, 1, 2, 3]
    # ... and observations of the same pixel by two pairs (sharing an image) are one point
    assert f.stats["merged"] > 0.8 * W * H
    assert len(f.xyz) == f.stats["kept"] - f.stats["merged"] < 2 * W * H
    assert np.all(f.observations >= 1) and f.observations.sum() == f.stats["kept"]
    assert np.mean(f.observations[inner] >= 2) > 0.9
    # merged points stay on the plane, normals face the cameras
    assert np.allclose(f.xyz[:, 2], PLANE_Z, atol=1e-9)
    assert np.all(f.normals[:, 2] < -0.99)


def test_a_point_in_free_space_seen_through_by_another_view_is_dropped():
    views = [_view(x) for x in (0.0, 0.3, 0.6, 0.9)]
    # pair (0, 1) sees the plane at 5 m and, wrongly, a patch floating at 4 m; pair (2, 3) sees the plane
    # through the place where the patch floats
    floating = _plane_points(views[0], step=8, z=4.0)
    floating = floating[np.abs(floating[:, 0] - 0.6) < 0.2]
    first = np.r_[_plane_points(views[0]), floating]
    f = _fuse(views, [(0, 1), (2, 3)], [_cloud(first), _cloud(_plane_points(views[2]))])
    assert len(floating) > 20
    assert f.stats["dropped_free_space"] == len(floating)
    assert f.stats["dropped_background"] + f.stats["dropped_hidden"] == 0  # no plane point goes
    assert not np.any(np.abs(f.xyz[:, 2] - 4.0) < 0.5)
    # with more agreeing than contradicting views required only from 2 views on, the patch still goes
    g = _fuse(views, [(0, 1), (2, 3)], [_cloud(first), _cloud(_plane_points(views[2]))], min_views=2)
    assert g.stats["dropped_free_space"] == len(floating)


def test_a_point_only_one_pair_sees_is_kept_when_no_view_contradicts_it():
    views = [_view(x) for x in (0.0, 0.3, 0.6, 0.9)]
    plane = _plane_points(views[0])
    # views 2 and 3 took part in no pair: they have no depth, and no partner of theirs saw anything
    f = _fuse(views, [(0, 1)], [_cloud(plane)], min_views=2)
    assert f.stats["kept"] == len(plane) and f.stats["kept_unconfirmed"] == len(plane)
    f = _fuse(views, [(0, 1)], [_cloud(plane)], min_views=3)
    assert f.stats["kept"] == len(plane) and f.stats["kept_unconfirmed"] == len(plane)
    assert np.all(f.support <= 2)  # its own views (one where the point leaves view 1's image)
    # by default a point needs a third view, where a third view has depth
    other = _plane_points(views[2])
    other = other[other[:, 0] > 3.0]  # pair (2, 3) saw only a strip far to the right
    g = _fuse(views, [(0, 1), (2, 3)], [_cloud(plane), _cloud(other)])
    assert g.stats["kept"] == 0 and g.stats["dropped_unconfirmed"] + g.stats["dropped_background"] >= len(plane)
    # ... unless the workspace has no third view, or no other pair gives one a depth map to agree with
    h = _fuse(views[:2], [(0, 1)], [_cloud(plane)])
    assert h.stats["kept"] == len(plane)
    g = _fuse(views, [(0, 1)], [_cloud(plane)])
    assert g.stats["kept"] == len(plane)


def test_a_point_one_pair_sees_and_another_view_would_see_in_front_of_it_is_dropped():
    views = [_view(x) for x in (0.0, 0.3, 0.6, 0.9)]
    # pair (2, 3) sees the plane at 5 m; pair (0, 1) alone puts a patch at 6 m behind it, where view 2 looks
    patch = _plane_points(views[0], step=8, z=6.0)
    patch = patch[np.abs(patch[:, 0] - 0.6) < 0.3]
    f = _fuse(views, [(0, 1), (2, 3)], [_cloud(patch), _cloud(_plane_points(views[2]))], min_views=2)
    assert len(patch) > 20 and f.stats["dropped_hidden"] == len(patch)
    assert not np.any(f.xyz[:, 2] > 5.5)


def test_a_point_on_unmatched_background_is_dropped():
    views = [_view(x) for x in (0.0, 0.3, 0.6, 0.9)]
    # an object on black: both pairs matched the plane where x < 0.3, and nothing to its right
    left = [p[p[:, 0] < 0.3] for p in (_plane_points(views[0]), _plane_points(views[2]))]
    # pair (0, 1) also puts a patch at x ~ 1.2, where views 2 and 3 (which see it) matched nothing
    patch = _plane_points(views[0], step=4)
    patch = patch[(patch[:, 0] > 1.1) & (patch[:, 0] < 1.3)]
    clouds = [_cloud(np.r_[left[0], patch]), _cloud(left[1])]
    f = _fuse(views, [(0, 1), (2, 3)], clouds)
    assert len(patch) > 20
    assert f.stats["dropped_background"] == len(patch)
    assert f.stats["kept"] + f.stats["dropped_unconfirmed"] == f.stats["input_points"] - len(patch)
    assert np.sum(f.xyz[:, 0] > 1.05) == 0
    # lower fuse_min_views changes nothing here: no view agrees with the patch
    g = _fuse(views, [(0, 1), (2, 3)], clouds, min_views=2)
    assert g.stats["dropped_background"] == len(patch)


def test_projection_and_block_reading(tmp_path):
    v = _view(0.0)
    pix, z = project(v, np.array([[0.0, 0.0, 5.0], [0.0, 0.0, -5.0], [100.0, 0.0, 5.0]]))
    assert pix[0] == (H // 2) * W + W // 2 and pix[1] == -1 and pix[2] == -1
    assert np.isclose(z[0], 5.0)
    xyz = np.random.default_rng(0).normal(size=(1000, 3))
    rgb = np.arange(3000).reshape(1000, 3).astype(np.uint8)
    write_point_cloud(tmp_path / "p.ply", xyz, rgb, xyz / np.linalg.norm(xyz, axis=1, keepdims=True))
    blocks = list(iter_point_cloud(tmp_path / "p.ply", block=300))
    assert [len(b[0]) for b in blocks] == [300, 300, 300, 100]
    assert np.allclose(np.concatenate([b[0] for b in blocks]), xyz, atol=1e-6)
    assert np.array_equal(np.concatenate([b[1] for b in blocks]), rgb)
