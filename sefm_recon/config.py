"""Configuration: typed dataclasses, TOML presets in ``configs/``, ``--set`` overrides.

A config file holds any subset of the user settings (:data:`USER_KEYS`); the rest keep
their defaults. ``--set output.max_size=2000`` overrides one key; unknown keys, wrong
types and values out of range are input errors. Each user setting is declared with
:func:`_setting`: its default, meaning, unit and allowed range sit in one place, and
``scripts/write_default_config.py`` writes them out as ``configs/default.toml`` and
``docs/configuration.md``.

The other fields are internal: the ``sgm`` section switches the default matcher's
stages for the ablation; the ``lines``, ``rough``, ``pyramid`` and ``validity`` sections
and most of ``dense`` are the constants of the sequential DP matcher
(``dense.method = "sefm"``; ``"paper"`` sets them as the paper has them,
:data:`PAPER`). They are not settings: only the evaluation and the tests change them
(``load_config(..., internal=True)``), to measure what each stage adds.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import InputError

#: ``output.max_size`` and ``sift.max_image_size`` in pixels: the largest sensors have
#: about 20 000 px on their long side, so a larger value would only be a typo (it would
#: mean full size, like 0).
MAX_SIDE = 100_000
#: ``output.max_size`` is 0 (never downscale) or at least this many pixels: a smaller
#: working copy keeps under 65 000 pixels, too few for a dense cloud worth a mesh.
MIN_MAX_SIZE = 256
#: ``output.mesh_max_points`` and ``output.sparse_max_points``: more than a pair at the
#: default working size can give (3200 x 2400 = 7.7 million pixels, one match each).
MAX_POINTS = 10_000_000


@dataclass(frozen=True)
class Range:
    """The values a numeric setting accepts: ``low``..``high`` (``None`` = open-ended),
    either end excluded when ``low_open``/``high_open``, plus an optional ``special``
    value outside it with a meaning of its own (``(0, "full size")``). Floats must be finite."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    special: tuple[float, str] | None = None

    def holds(self, value: float) -> bool:
        if self.special is not None and value == self.special[0]:
            return True
        if self.low is not None and (value < self.low or (self.low_open and value == self.low)):
            return False
        return self.high is None or value < self.high or (not self.high_open and value == self.high)

    def text(self) -> str:
        """``"> 0 and <= 1"``, ``"0 (full size) or >= 64 and <= 100000"``."""
        def num(v: float) -> str:
            return str(int(v)) if float(v).is_integer() else f"{v:g}"

        ends = []
        if self.low is not None:
            ends.append(f"{'>' if self.low_open else '>='} {num(self.low)}")
        if self.high is not None:
            ends.append(f"{'<' if self.high_open else '<='} {num(self.high)}")
        text = " and ".join(ends)
        if self.special is not None:
            text = f"{num(self.special[0])} ({self.special[1]}) or {text}"
        return text


def _setting(default: Any, doc: str, *, unit: str = "", range: Range | None = None,
             choices: tuple[str, ...] = (), why: str = "") -> Any:
    """A user setting: a dataclass field whose metadata carries its documentation.

    ``doc`` says what it does, ``unit`` what its numbers count, ``range`` (numbers) or
    ``choices`` (strings) what it accepts, and ``why`` why the range ends where it does.
    """
    return field(default=default, metadata={"doc": doc, "unit": unit, "range": range, "choices": choices,
                                            "why": why})


@dataclass
class SiftConfig:
    """SIFT features for the two-view pose (``sefm-recon pair``)."""

    max_features: int = _setting(
        8192, "SIFT features kept per image (the strongest); 8192 is COLMAP's default", unit="features",
        range=Range(5, 100_000),
        why="the five-point pose needs 5 matches (and at least geometry.min_inliers are needed); beyond 100 000, "
            "12 times the default, SIFT and its matching only get slower: a pose needs tens of well spread inliers")
    max_ratio: float = _setting(
        0.8, "Lowe's ratio test: a match's descriptor distance over the second-best one's must be below this",
        range=Range(0, 1, low_open=True),
        why="a ratio of two distances, the best one first: at 1 every mutual nearest neighbour passes, at 0 none")
    max_image_size: int = _setting(
        3200, "SIFT runs on copies downscaled to this longest side (photos longer than 2:1: to this "
              "size squared over 2 pixels); 3200 is COLMAP's default", unit="px",
        range=Range(64, MAX_SIDE, special=(0, "full size")),
        why="images under 64 px on a side are refused as too small to match; above 100 000 px (beyond any "
            "camera's sensor) the value would mean full size, like 0")
    #: SIFT starts at octave -1 (the photo upsampled 2x, as COLMAP always does) when the photo
    #: SIFT sees has a longest side of at most this (px): small photos gain their finest
    #: features, large ones have enough and would pay 4 times the pixels. At 1600 the
    #: upsampled copy is at most 3200 px, COLMAP's own largest SIFT image (0 = never).
    #: Internal: the user settings are capped at 25.
    upsample_max_size: int = 1600
    #: Photos longer than this (px), with known cameras, are first posed from SIFT on
    #: copies this long at octave 0 (a quarter of the pixels of a 2000 px photo, a
    #: sixteenth of a 1600 px one's upsampled copy); only where that pose is refused does
    #: the full front end above run. Its pose need not be the best SIFT can give: the dense
    #: matches refine it (geometry.refine_pose). An unknown focal length is estimated from
    #: the SIFT matches and needs the full front end (fountain-P11 at 1536 px without a
    #: camera: focal errors up to 7 % instead of 3 %, one pair's left undetermined). 1024
    #: px, the front end's size before COLMAP's defaults were adopted, still finds
    #: thousands of inliers on a textured photo (0 = always the full front end). Internal.
    quick_max_size: int = 1024


@dataclass
class GeometryConfig:
    """The relative pose from SIFT matches; the baseline test."""

    min_inliers: int = _setting(
        30, "SIFT matches consistent with the pose (RANSAC inliers) needed to trust it", unit="matches",
        range=Range(5, 100_000),
        why="the five-point essential-matrix solver needs 5; no more inliers than sift.max_features can exist")
    ransac_max_error: float = _setting(
        2.0, "RANSAC inlier threshold: largest distance of a SIFT match from its epipolar line", unit="px",
        range=Range(0, 50, low_open=True),
        why="a distance; SIFT positions are good to a pixel or two, and at 50 px (5 % of a 1000 px photo) "
            "wrong matches count as inliers")
    min_tri_angle_deg: float = _setting(
        0.5, "a pair whose SIFT inliers' median triangulation angle is below this has a narrow baseline: a "
             "warning that its depth will be noisy (sefm-recon pair; only a pure rotation is refused) or skipped "
             "(sefm-recon colmap; pairs from the poses: its rays' angle at the scene)", unit="degrees",
        range=Range(0, 90),
        why="an angle between two rays; cameras that see one surface from both sides of 90 degrees face each "
            "other and see different sides of it")
    depth_margin: float = 2.0  #: search depths from p1/margin to p99*margin of the SIFT points' depths
    #: an estimated pose is checked with free 2-D tracks of the dense matches, refined from them and the
    #: pair matched again where that moves the lines (false: the SIFT pose as it is, for the measurement)
    refine_pose: bool = True


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
    descriptor_coefficients: int = 4  #: Fourier coefficients kept (beyond DC); more cost time without matching better
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
    method: str = _setting(
        "sgm", "the dense matcher: sgm, semi-global matching over the polar line images; sefm, the paper's "
               "dynamic programming along each pair of epipolar lines, with its repairs; paper, that DP as the "
               "paper has it", choices=("sgm", "sefm", "paper"))
    # The keys below belong to the DP (internal constants).
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
class SgmConfig:
    """Switches of the default matcher's stages (``dense.method = "sgm"``), for the ablation:
    internal, only the evaluation and the tests change them (:mod:`.matching.sgm`)."""

    full_paths: bool = True  #: 4 full paths, in strips of rows where the volume does not fit (false: 3 directions)
    half_fill: bool = True  #: give the cells SGM leaves without an estimate the estimate of SGM at half size
    half_check: bool = True  #: drop the estimates SGM at half size, sure there, puts over 3 columns away
    lr_check: bool = True  #: drop the estimates a second SGM, from image 2 at half size, puts over a column away
    uniqueness: int = 10  #: best cost this many percent below the second best (0 = off)
    jump_penalty: int = 0  #: SGM's P2 in units of channels x block area (0: chosen per pair, sgm.choose_jump_penalty)
    speckle: bool = True  #: drop small islands of disparity (OpenCV's speckle filter)
    speckle_share: bool = True  #: the speckle filter's window a share of the view (false: OpenCV's 100 px alone)
    sift_range: bool = True  #: search the SIFT inliers' parallax (false: their depths x2 and /2)
    range_margin: float = 0.0  #: the parallax range widened by this share of its span on each side (0: 8 columns)
    end_check: bool = True  #: drop estimates within a column of the ends of the search (its edge, not a minimum found)
    flat_check: bool = True  #: drop estimates whose window in image 1 reaches into an area of one value (clipped, or fill)
    outside_check: bool = True  #: drop estimates whose window in image 2 reaches beyond image 2's pixels
    edge_check: bool = True  #: drop the nearer surface's cell next to each depth edge (its windows fatten it)
    collision_check: bool = True  #: of two surfaces' cells that reach one pixel of image 2, drop the one whose colour differs more
    occlusion_check: bool = True  #: drop the plain cells a nearer surface's run carries into the unmatched region on its occlusion side
    carried_check: bool = True  #: drop the plain cells of a farther surface's colour a nearer surface carries across a depth jump, up to its intensity edge
    tone_match: bool = True  #: map image 2's tones onto image 1's, fitted to the coarse pass's matches (:mod:`.matching.tone`)
    near_range: bool = True  #: extend the SIFT range towards the camera where a coarse pass finds a surface beyond it
    far_check: bool = True  #: drop far end estimates of cells image 2 sees at no nearer parallax (unseen there)
    far_surface_check: bool = True  #: drop far end estimates on surfaces image 2 sees nowhere at every parallax (ties beyond its edge)
    near_check: bool = True  #: drop estimates at the search's near end where the coarse pass found no surface that near
    coarse_check: bool = True  #: drop estimates far from the coarse pass's where that is sure (stripes a period off)
    repeat_check: bool = True  #: drop estimates on texture repeating along the lines where their surface has no other
    frame_check: bool = True  #: drop runs that match image 1's edge to image 2's across more than an occlusion's gap
    coarse_range: bool = True  #: without 8 SIFT inliers, search what a coarse pass finds (false: every depth)
    bicubic: bool = True  #: bicubic line images (false: bilinear)
    interpolate: bool = True  #: read disparities back interpolated over the surface (false: nearest cell)
    median: bool = True  #: smooth the disparities by a 5x5 median on their surface (false: as SGM leaves them)
    slanted_median: bool = True  #: on a window's sloping plane, the median about that plane (false: the plain one)
    plain_fit: bool = True  #: on plain windows, each disparity from its surface's local plane (false: the median's)
    #: plain cells 1-2 columns off their 25x25 window's plane onto it where it matches as well
    #: (:func:`.matching.surfaces.fit_wide_planes`)
    wide_fit: bool = True
    planes: bool = True  #: fill large plain regions whose matches lie on one plane (:mod:`.matching.planes`)
    plane_snap: bool = True  #: move the matches without signal of large plain regions that are one plane onto it (:mod:`.matching.planes`)
    scattered_check: bool = True  #: drop the matches of large plain regions mostly unmatched whose matches lie on no one plane, or on the ties at the search's first parallax (:mod:`.matching.planes`)
    aligned_planes: bool = True  #: align plain regions' planes by the intensities where their halves agree: kept and filled then, not dropped (:mod:`.matching.plane_align`)
    rim_planes: bool = True  #: fill and move the small plain regions' pixels onto the plane of their rim's matches (:mod:`.matching.planes`)
    #: fill the large plain regions whose matches were all dropped (on no surface, or on the
    #: ties) from another region's plane, aligned there by the intensities (:mod:`.matching.planes`)
    borrowed_planes: bool = True
    #: keep a second surface of a mostly unmatched plain region, whose matches lie on one
    #: homography that image 2 bears out better, apart from the region's aligned plane (:mod:`.matching.planes`)
    two_surfaces: bool = True
    #: drop the islands the checks leave under the speckle filter's window (but those moved onto
    #: a plain region's plane), after the plane fill (:func:`.matching.checks.speckle_islands`)
    speckle_after: bool = True
    #: move the matches over 3 px off the scene's largest planes, aligned by the intensities,
    #: onto them where image 2 under the plane agrees better (:mod:`.matching.dominant`)
    dominant_planes: bool = True
    #: give back the estimates the repeat check dropped where they lie on one of those planes,
    #: in its area where image 2 under it agrees, or move them onto it (:mod:`.matching.dominant`)
    repeat_restore: bool = True
    #: give back in the same way the estimates the left-right check dropped on texture repeating
    #: along the lines (:func:`.matching.sgm.repeating_drops`)
    lr_restore: bool = True


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
    """What is written, and the working size."""

    max_size: int = _setting(
        3200, "match on copies downscaled to this longest side (--max-size); every coordinate written is in the "
              "original pixels", unit="px", range=Range(MIN_MAX_SIZE, MAX_SIDE, special=(0, "full size")),
        why="a copy under 256 px keeps under 65 000 pixels, too few for a dense cloud worth a mesh; above "
            "100 000 px (beyond any camera's sensor) the value would mean full size, like 0")
    mesh: str = _setting(
        "grid", "mesh.ply: grid, camera 1's pixel grid joined into triangles where the surface is continuous "
                "(only what was matched; fast); poisson, open3d's screened Poisson surface of the points (smooth, "
                "closes holes; seconds more); none, no mesh.ply (true and false mean grid and none)",
        choices=("grid", "poisson", "none"))
    poisson_depth: int = _setting(
        9, "output.mesh = poisson: octree depth of the surface, at most 2^depth cells along each axis",
        unit="levels",
        range=Range(5, 12),
        why="open3d refuses depth 1 and prints hundreds of warnings at depths 2 to 4; at 12 the grid has 4096 "
            "cells a side, finer than even output.mesh_max_points' maximum of 10 million points can fill")
    density_quantile: float = _setting(
        0.05, "output.mesh = poisson: vertices whose Poisson density is below this quantile are trimmed "
              "(0 = keep all)",
        range=Range(0, 1, high_open=True),
        why="a quantile: at 1 every vertex would be trimmed")
    mesh_max_points: int = _setting(
        150000, "the grid mesh has at most this many vertices (each the mean of a cell of points); the Poisson "
                "mesh is built from at most this many points (voxel-averaged), its time grows with them",
        unit="points", range=Range(100, MAX_POINTS),
        why="Poisson needs at least 100 oriented points for a surface; 10 million is more than a pair at the "
            "default working size gives (3200 x 2400 pixels, one match each)")
    sparse_max_points: int = _setting(
        100000, "points written to the COLMAP model in sparse/ (a random subset; 0 = cameras and poses only)",
        unit="points", range=Range(0, MAX_POINTS),
        why="a count; 10 million is more than a pair at the default working size gives")
    normals: str = _setting(
        "grid", "point normals: grid, from camera 1's pixel grid (fast); knn, open3d's nearest-neighbour PCA",
        choices=("grid", "knn"))
    clean_outliers: bool = _setting(
        False, "open3d's statistical outlier removal before writing points.ply (slow; the matcher's own checks "
               "do most of its work)")
    progress: bool = _setting(True, "a progress bar on long runs (the command line's -q turns it off)")


@dataclass
class ColmapConfig:
    """``sefm-recon colmap``: pair selection, fusion and the COLMAP database."""

    min_covisible: int = _setting(
        30, "sparse points two images must share to be paired (a model with points, no --pairs)",
        unit="points", range=Range(1, 100_000),
        why="one shared point is the least overlap; no two images share more points than COLMAP extracts "
            "features per image (8192 by default), so 100 000 would pair nothing")
    pairs_per_image: int = _setting(
        4, "each image keeps this many partners, those it shares the most points with, or (a model without "
           "points) those with the closest viewing direction (0 = all)", unit="images",
        range=Range(0, 10_000),
        why="a count of images; 10 000 partners is more than a workspace matched pair by pair holds, and would "
            "mean all, like 0")
    pair_max_view_angle_deg: float = _setting(
        50.0, "a model without points: images whose viewing directions differ by more than this are not "
              "paired", unit="degrees", range=Range(0, 180, low_open=True),
        why="dense matching agrees across three views at 1 px for 0.83 of points under 15 degrees but 0.38 at "
            "30-50 degrees (issue 18); hloc's pairs_from_poses and COLMAP's MVS pick partners within 45-60 "
            "degrees; 180 keeps every direction")
    cell_size: float = _setting(
        2.0, "database.db keypoints: at most one per cell of this size, placed where the matches in it agree "
             "(as hloc's match_dense)", unit="px", range=Range(0.5, 64),
        why="the matcher gives at most one match per pixel of image 1, so a cell under half a pixel holds one "
            "match end and quantises nothing; above 64 px one keypoint stands for thousands of matches")
    max_error: float = _setting(
        0.75, "a match end farther than this from its cell's keypoint loses its match", unit="px",
        range=Range(0.1, 64),
        why="below 0.1 px, finer than the matches' sub-pixel accuracy, almost every match end is dropped; no end "
            "is farther from its keypoint than its cell's diagonal, so past the largest cell nothing changes")
    max_epipolar_error: float = _setting(
        4.0, "inlier threshold of the two-view geometries in database.db: distance of a match from its "
             "epipolar line", unit="px", range=Range(0, 100, low_open=True),
        why="a distance; the dense matches lie on their epipolar lines to a fraction of a pixel before "
            "quantisation moves them by at most colmap.max_error, and at 100 px the test keeps everything")
    tri_min_angle_deg: float = _setting(
        1.5, "COLMAP's triangulator: smallest triangulation angle of a point in sparse/", unit="degrees",
        range=Range(0, 90), why="as geometry.min_tri_angle_deg")
    fuse_min_views: int = _setting(
        3, "fused.ply keeps a point that this many views agree with (its pair's two included) and fewer "
           "contradict; at 2 also a pair's point no other view confirms, where none contradicts or hides it",
        unit="views", range=Range(2, 1000),
        why="a pair's own two views confirm nothing: 3 asks for one other view, a three-view track (COLMAP's "
            "fusion asks for 5 depth maps); at 2 points only one pair sees stay; more than the workspace's "
            "views asks for all of them")
    fuse_max_depth_error: float = _setting(
        0.01, "fused.ply: relative depth difference within which a view's observation agrees with a point (and "
              "beyond which a surface seen behind it contradicts it)", unit="of the depth",
        range=Range(0, 0.5, low_open=True),
        why="COLMAP's stereo fusion uses 0.01; dense matches 0.5 px off at 100 px disparity are 0.5 % off in "
            "depth; at 0.5 a surface twice as far still agrees")


@dataclass
class Config:
    sift: SiftConfig = field(default_factory=SiftConfig)
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    lines: LinesConfig = field(default_factory=LinesConfig)
    rough: RoughConfig = field(default_factory=RoughConfig)
    pyramid: PyramidConfig = field(default_factory=PyramidConfig)
    dense: DenseConfig = field(default_factory=DenseConfig)
    sgm: SgmConfig = field(default_factory=SgmConfig)
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


#: Keys that were booleans once: what ``true`` and ``false`` still mean there.
_BOOL_ALIASES: dict[str, dict[bool, str]] = {"output.mesh": {True: "grid", False: "none"}}


def _apply(cfg: Config, section: str, key: str, value: Any, internal: bool = False) -> None:
    sub = getattr(cfg, section, None)
    if sub is None or not dataclasses.is_dataclass(sub):
        names = ", ".join(dict.fromkeys(k.split(".")[0] for k in USER_KEYS))
        raise InputError(f"unknown config section {section!r} (sections: {names})")
    types = {f.name: f.type for f in dataclasses.fields(sub)}
    user = [k.split(".")[1] for k in USER_KEYS if k.startswith(section + ".")]
    if key not in types or (not internal and f"{section}.{key}" not in USER_KEYS):
        known = ", ".join(user) or "none: its keys are internal constants of the matchers"
        raise InputError(f"unknown config key {section}.{key} (keys: {known})")
    kind = {"int": int, "float": float, "bool": bool, "str": str}[types[key]] if isinstance(types[key], str) else types[key]
    aliases = _BOOL_ALIASES.get(f"{section}.{key}")
    if aliases is not None and (isinstance(value, bool) or str(value).lower() in ("true", "false")):
        value = aliases[value if isinstance(value, bool) else str(value).lower() == "true"]
    setattr(sub, key, _coerce(value, kind, f"{section}.{key}"))


#: Ranges of the internal constants (the user settings carry theirs in :func:`_setting`).
_INTERNAL_RANGES: dict[str, Range] = {key: Range(low, high, low_open) for key, (low, high, low_open) in {
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
    "sgm.uniqueness": (0, 100, False),
    "sgm.jump_penalty": (0, 1000, False),
    "sift.upsample_max_size": (0, MAX_SIDE, False),
    "sift.quick_max_size": (0, MAX_SIDE, False),
    "sgm.range_margin": (0, 4, False),
}.items()}


def _user_fields(cfg: Config) -> list[tuple[str, dataclasses.Field]]:
    return [(f"{sec.name}.{f.name}", f) for sec in dataclasses.fields(cfg)
            for f in dataclasses.fields(getattr(cfg, sec.name)) if "doc" in f.metadata]


#: The settings a user sets (``--config`` files and ``--set``); everything else is internal.
USER_KEYS: tuple[str, ...] = tuple(key for key, _ in _user_fields(Config()))
#: Each user setting's field (its metadata: doc, unit, range, choices, why).
USER_FIELDS: dict[str, dataclasses.Field] = dict(_user_fields(Config()))

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


def check_value(key: str, value: Any) -> Any:
    """``value`` if ``key`` accepts it (a finite number in its range, one of its choices); else
    :class:`InputError`, one line naming the key."""
    f = USER_FIELDS.get(key)
    rng = f.metadata["range"] if f is not None else _INTERNAL_RANGES.get(key)
    choices = f.metadata["choices"] if f is not None else ()
    if isinstance(value, float) and not math.isfinite(value):
        raise InputError(f"config key {key}: expected a finite number, got {value!r}")
    if choices and value not in choices:
        raise InputError(f"config key {key}: one of {', '.join(choices)}, got {value!r}")
    if rng is not None and not isinstance(value, bool) and isinstance(value, (int, float)) and not rng.holds(value):
        raise InputError(f"config key {key}: must be {rng.text()}, got {value!r}")
    return value


def validate(cfg: Config) -> Config:
    """Check every value's range; raises :class:`InputError` naming the key."""
    for sec in dataclasses.fields(cfg):
        sub = getattr(cfg, sec.name)
        for f in dataclasses.fields(sub):
            check_value(f"{sec.name}.{f.name}", getattr(sub, f.name))
    if cfg.geometry.min_inliers > cfg.sift.max_features:
        raise InputError(f"config key geometry.min_inliers: must be <= sift.max_features ({cfg.sift.max_features}): "
                         f"no more inliers than features can be found, got {cfg.geometry.min_inliers}")
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
