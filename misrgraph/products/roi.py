"""Reference Orbit Imagery (ROI): cloud-free imagery of a path on its 275 m SOM grid, per camera,
mosaicked from several adjusted passes (seed section 2).

For each chosen block and camera, every pass's image is resampled onto the block's 275 m grid:
the grid point at SOM (block, line, sample), with the height ``h`` of the SOM DEM there, lies at
image position ``(line, sample)(h)`` of the pass by its Projection Parameters
(:meth:`misrgraph.io.products.ProjectionParameters.image_coords`), where the pass's whole-swath
strip is interpolated bilinearly. So the ROI inherits the adjustment's geolocation and the DEM's
error (a height error ``dh`` moves a point by ``dh tan(view angle)``: 0.1 pixel for 10 m in the D
cameras).

**Terrain.** A grid point that terrain nearer the camera hides from it
(:func:`misrgraph.products.terrain.terrain_obscured`, by the PP's view direction and the SOM
DEM) is imaged at the position of the terrain in front of it: resampled, it would show the wrong
ground (12-17 pixels off in the D cameras over 1.5 km of relief). Such a pass does not image the
point; where every pass is obscured there, the pixel is empty and flagged ``obscured``. The passes
of one path see the ground from nearly the same direction, so another pass rarely fills it.

**Clouds.** A pixel is cloudy when its reflectance (counts / full scale) exceeds
:data:`CLOUD_REFLECTANCE` or its 9 x 9 mean exceeds :data:`CLOUD_MEAN_REFLECTANCE` (clouds are
bright and extend over kilometres; land rarely exceeds 0.5 and its mean stays near 0.2), grown by
:data:`CLOUD_MARGIN_PX`. A radiometric screen, not MISR's stereo cloud mask: thin or dark cloud
passes it.

**Mosaic.** Per block, the passes are ranked by their clear fraction (clear pixels over the
pixels they image, all cameras); the clearest is the block's pass. Every pixel takes the
highest-ranked pass that images it clear, else (no clear pass) the highest-ranked that images it
at all, flagged ``cloudy``; ``source`` records the pass index per pixel (-1: no pass images it).

**Co-registration** (:func:`coregistration`) is measured on the resampled images themselves: at
points spread over each block, a 41 x 41 template (11 km) of one image is matched by
least-squares matching (:func:`misrgraph.match.lsm.lsm`) into another; the offset is the
misregistration of the second against the first. (The D cameras see the ground through another
blur and BRDF than An: a 21 x 21 template matched them with errors twice its own sigma, 0.36
pixel beyond noise where the simulator's truth says 0.12-0.14.) Each camera is compared with An of the same
pass (between cameras) and with itself in the block's pass (between passes); points on clouds,
water or without texture are skipped, and matches that do not converge or move more than 1 pixel
are counted as failures, not offsets; matches far from their pair's smooth (affine) field are
rejected as wrong (:func:`consistent_matches`). Per block and kind the matches of all its pairs are pooled:
the figure is the block's RMS misregistration beyond matching noise, with an interval from the
number of matches. (The worst single pair, also reported, rests on as few as 10-20 matches where
clouds and sea leave few templates.) Only the LSM's own sigma is subtracted as noise. Between
passes on the suite's block it is about right (the matching error is 0.9-1.3 of it); between
cameras there, and in both kinds in the coastal blocks of path 37, the error is 1.5-2.3 times it
(blur, BRDF and sun differ between the images), so the figure reads high (by up to 0.1 pixel
over the truth at the same points). With the simulator's truth,
:func:`misrgraph.evaluate.products.score_roi_matches` gives the truth at the matched points and
the matching error.

**What the adjustment allows** (:func:`roi_predicted_coregistration`): per block and camera, the
misregistration the PP's own 1-sigma (and the SOM DEM's error, as parallax) predicts, so the
summary says where the seed's 0.2 pixel is within reach of the navigation's knowledge and where
no resampling can reach it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from misrgraph.errors import InputError
from misrgraph.io.dem import SomDem
from misrgraph.io.imagery import ImageStrip
from misrgraph.io.products import ProjectionParameters
from misrgraph.misr.som import SomGrid
from misrgraph.model.constants import CAMERAS, VIEW_ANGLE_DEG
from misrgraph.products.terrain import terrain_obscured

__all__ = [
    "RoiPass",
    "RoiBlock",
    "PairMatches",
    "build_roi",
    "cloud_mask",
    "consistent_matches",
    "coregistration",
    "coregistration_matches",
    "coregistration_stats",
    "compare_rois",
    "roi_predicted_coregistration",
    "CLOUD_REFLECTANCE",
    "CLOUD_MEAN_REFLECTANCE",
    "CLOUD_MARGIN_PX",
    "COREG_REJECT_SIGMA",
    "MIN_ROI_PASSES",
]

Array = NDArray[np.float64]
log = logging.getLogger(__name__)

#: A pixel brighter than this reflectance is cloud.
CLOUD_REFLECTANCE = 0.55
#: A pixel whose 9 x 9 mean reflectance exceeds this is cloud.
CLOUD_MEAN_REFLECTANCE = 0.38
#: Cloud masks grow by this many pixels (cloud edges, thin margins).
CLOUD_MARGIN_PX = 4
#: The seed's ROI is built from at least this many adjusted passes.
MIN_ROI_PASSES = 4
#: Template size (px) and the search margin each side (px) of the co-registration matches.
COREG_TEMPLATE_PX = 41
COREG_MARGIN_PX = 4


@dataclass
class RoiPass:
    """One adjusted pass as the ROI sees it: its PP (1.1 km, all blocks the ROI needs) and a
    loader of its whole-swath strip ``strip(camera, (first line, one past last))`` (None where the
    pass has none there)."""

    pass_id: str
    pp: ProjectionParameters
    strip: Callable[[str, tuple[int, int]], ImageStrip | None]


@dataclass
class RoiBlock:
    """One block of ROI: ``pixels (C, nline, nsample)`` uint16 counts (0: no pass images it),
    ``source`` int8 pass index per pixel (-1: none), ``cloudy`` bool (no clear pass there),
    ``obscured`` bool (terrain hides the point in every pass that would image it),
    ``clear_fraction (P,)`` per pass and ``chosen`` (the block's clearest pass); ``resampled``
    holds every pass's image on the grid (``(P, C, nline, nsample)`` float32 counts, NaN where it
    has none or terrain hides the point), ``clouds`` their cloud masks and ``hidden`` their
    terrain masks (``(P, C, nline, nsample)``), for co-registration, scoring and views (not
    stored)."""

    block: int
    cameras: tuple[str, ...]
    pixels: NDArray[np.uint16]
    source: NDArray[np.int8]
    cloudy: NDArray[np.bool_]
    obscured: NDArray[np.bool_]
    clear_fraction: Array
    chosen: int
    resampled: NDArray[np.float32] = field(repr=False)
    clouds: NDArray[np.bool_] = field(repr=False)
    hidden: NDArray[np.bool_] = field(repr=False)


def cloud_mask(counts: NDArray[np.float32], full_scale: float) -> NDArray[np.bool_]:
    """Cloudy pixels of an image of counts (NaN: no data, never cloudy); see the module docstring."""
    refl = np.nan_to_num(np.asarray(counts, dtype=np.float32) / np.float32(full_scale), nan=0.0)
    valid = np.isfinite(counts)
    n = ndimage.uniform_filter(valid.astype(np.float32), 9, mode="nearest")
    mean = ndimage.uniform_filter(refl, 9, mode="nearest") / np.maximum(n, 1e-6)
    cloud = ((refl > CLOUD_REFLECTANCE) | ((mean > CLOUD_MEAN_REFLECTANCE) & (n > 0.25))) & valid
    if CLOUD_MARGIN_PX and cloud.any():
        cloud = ndimage.binary_dilation(cloud, iterations=CLOUD_MARGIN_PX) & valid
    return cloud


def _resample(
    p: RoiPass, camera: str, block: int, heights: NDArray[np.float32], lines: Array, samples: Array
) -> NDArray[np.float32] | None:
    """A pass's image on the block's 275 m grid (NaN where it does not image the point; None where
    it has no strip there): the PP give each point's image position at its DEM height, where
    the strip (only the lines needed) is interpolated."""
    if camera not in p.pp.cameras:
        return None
    ln, sm = p.pp.image_coords(camera, block, lines, samples, heights, resolution_m=275)
    if not np.isfinite(ln).any():
        return None
    strip = p.strip(camera, (int(np.floor(np.nanmin(ln))) - 1, int(np.ceil(np.nanmax(ln))) + 2))
    return None if strip is None else strip.sample_at(ln, sm)


def build_roi(
    passes: list[RoiPass],
    dem: SomDem,
    blocks: NDArray[np.int64],
    cameras: tuple[str, ...] = CAMERAS,
    full_scale: float = 2**14 - 1,
    progress: Callable[[str, int, int], None] | None = None,
) -> Iterator[RoiBlock]:
    """The ROI of ``blocks``, one :class:`RoiBlock` at a time (module docstring), from ``passes``
    (at least :data:`MIN_ROI_PASSES`, all of one path) resampled with the heights of ``dem``."""
    if len(passes) < MIN_ROI_PASSES:
        raise InputError("passes", len(passes), f"at least {MIN_ROI_PASSES} adjusted passes with imagery")
    paths = {int(p.pp.path) for p in passes}
    if len(paths) != 1 or int(dem.path) not in paths:
        raise InputError("passes/dem path", sorted(paths | {int(dem.path)}), "one path for every pass and the SOM DEM")
    if dem.resolution_m != 275:
        raise InputError("dem.resolution_m", dem.resolution_m, 275)
    bad = [c for c in cameras if c not in CAMERAS]
    if bad or not cameras:
        raise InputError("cameras", bad or cameras, f"names from {', '.join(CAMERAS)}")
    grid = SomGrid(paths.pop(), 275)
    li, si = np.meshgrid(np.arange(grid.nline, dtype=float), np.arange(grid.nsample, dtype=float), indexing="ij")
    n_p, n_c = len(passes), len(cameras)
    for k, block in enumerate(np.asarray(blocks, dtype=np.int64)):
        for p in passes:
            if int(block) not in p.pp.blocks:
                raise InputError(
                    "blocks", int(block), f"blocks of pass {p.pass_id}'s PP ({p.pp.blocks.min()}..{p.pp.blocks.max()})"
                )
        h = dem.block(int(block))
        imgs = np.full((n_p, n_c, grid.nline, grid.nsample), np.nan, np.float32)
        hidden = np.zeros((n_p, n_c, grid.nline, grid.nsample), bool)
        for i, p in enumerate(passes):
            if progress:
                progress(f"ROI block {block}: resampling pass {p.pass_id}", k * n_p + i, len(blocks) * n_p)
            for j, cam in enumerate(cameras):
                img = _resample(p, cam, int(block), h, li, si)
                if img is not None:
                    hidden[i, j] = terrain_obscured(p.pp, cam, dem, int(block)) & np.isfinite(img)
                    imgs[i, j] = np.where(hidden[i, j], np.nan, img)
        clouds = np.stack([[cloud_mask(imgs[i, j], full_scale) for j in range(n_c)] for i in range(n_p)])
        seen = np.isfinite(imgs)
        clear = seen & ~clouds
        n_seen = seen.reshape(n_p, -1).sum(1)
        clear_fraction = np.where(n_seen > 0, clear.reshape(n_p, -1).sum(1) / np.maximum(n_seen, 1), 0.0)
        order = np.argsort(-clear_fraction, kind="stable")
        pixels = np.zeros((n_c, grid.nline, grid.nsample), np.uint16)
        source = np.full((n_c, grid.nline, grid.nsample), -1, np.int8)
        cloudy = np.zeros((n_c, grid.nline, grid.nsample), bool)
        for mask_of in (clear, seen):  # clear pixels first, then any that some pass images
            for i in order:
                take = mask_of[i] & (source < 0)
                source[take] = i
                pixels[take] = np.clip(np.round(imgs[i][take]), 0, 65535).astype(np.uint16)
                cloudy[take] = clouds[i][take]
        obscured = hidden.any(axis=0) & (source < 0)
        log.info(
            "ROI block %d: clearest pass %s (clear %.2f), obscured by terrain %.4f",
            block,
            passes[int(order[0])].pass_id,
            clear_fraction[order[0]],
            float(obscured.mean()),
        )
        yield RoiBlock(
            int(block),
            tuple(cameras),
            pixels,
            source,
            cloudy,
            obscured,
            clear_fraction,
            int(order[0]),
            imgs,
            clouds,
            hidden,
        )


def _match_offsets(
    ref: NDArray[np.float32], img: NDArray[np.float32], bad: NDArray[np.bool_], n_points: int, min_std: float
) -> tuple[Array, Array, int]:
    """Offsets and their LSM 1-sigma ``(n, 4)`` (line, sample, sigma_line, sigma_sample px) of
    ``img`` against ``ref`` by LSM at up to ``n_points`` points spread evenly over where both images
    hold data clear of ``bad`` over the whole search window, the grid points ``(n, 2)`` (line,
    sample) they were measured at, and the number of matches that failed. ``ref`` at a point shows
    what ``img`` shows at the point plus the offset."""
    from misrgraph.match.lsm import lsm

    t2, m = COREG_TEMPLATE_PX // 2, COREG_MARGIN_PX
    w = 2 * (t2 + m) + 1
    usable = ndimage.minimum_filter(np.isfinite(ref) & np.isfinite(img) & ~bad, size=w, mode="constant", cval=0)
    usable[: t2 + m + 1] = usable[-(t2 + m + 1) :] = False
    usable[:, : t2 + m + 1] = usable[:, -(t2 + m + 1) :] = False
    cand = np.argwhere(usable[::8, ::8]) * 8  # candidates 8 px apart, then evenly thinned
    if cand.shape[0] > n_points:
        cand = cand[np.linspace(0, cand.shape[0] - 1, n_points).astype(int)]
    out, at, failed = [], [], 0
    for r, c in cand:
        tpl = ref[r - t2 : r + t2 + 1, c - t2 : c + t2 + 1]
        if tpl.std() < min_std:  # water, flat ground: nothing to match
            continue
        win = img[r - t2 - m : r + t2 + m + 1, c - t2 - m : c + t2 + m + 1]
        centre = float(t2 + m)
        res = lsm(win, tpl, centre, centre, max_shift_px=1.0)
        if not res.converged:
            failed += 1
            continue
        out.append((res.row - centre, res.col - centre, res.sigma_row, res.sigma_col))
        at.append((r, c))
    return np.array(out, dtype=float).reshape(-1, 4), np.array(at, dtype=np.int64).reshape(-1, 2), failed


def _offset_stats(d: Array) -> dict[str, float | int]:
    """Statistics of matched offsets ``d (n, 4)`` (line, sample, sigma_line, sigma_sample px):
    ``rms_px`` the radial RMS of the offsets, ``noise_px`` the radial RMS of the matches' own
    1-sigma (LSM's), ``excess_px = sqrt(rms^2 - noise^2)`` the misregistration beyond matching
    noise, ``excess_interval_px`` its 95 % interval from the sampling of ``rms^2`` (the ``2n``
    offset components taken as independent and Gaussian: ``rms^2 2n / chi2(2n)`` at 0.975 and
    0.025), ``mean_px`` the length of the offsets' mean vector (the systematic part) and
    ``matches``."""
    from scipy.stats import chi2

    n = int(d.shape[0])
    ms = float(np.mean(np.sum(d[:, :2] ** 2, 1)))
    noise2 = float(np.mean(np.sum(d[:, 2:] ** 2, 1)))
    lo, hi = (ms * 2 * n / float(chi2.ppf(q, 2 * n)) for q in (0.975, 0.025))
    return {
        "rms_px": float(np.sqrt(ms)),
        "noise_px": float(np.sqrt(noise2)),
        "excess_px": float(np.sqrt(max(ms - noise2, 0.0))),
        "excess_interval_px": [float(np.sqrt(max(lo - noise2, 0.0))), float(np.sqrt(max(hi - noise2, 0.0)))],
        "mean_px": float(np.hypot(*d[:, :2].mean(0))),
        "matches": n,
    }


#: Matches further than this many robust sigmas from their pair's affine field are rejected.
COREG_REJECT_SIGMA = 4.0


def consistent_matches(points: NDArray[np.int64], offsets: Array, k: float = COREG_REJECT_SIGMA) -> NDArray[np.bool_]:
    """``(n,)`` bool: the matches of one pair consistent with a smooth misregistration. An affine
    field in (line, sample) is fitted to the offsets ``(n, 4)`` at grid ``points (n, 2)`` by least
    squares; a match is kept while each residual component is within ``k`` times the larger of
    the kept residuals' robust sigma (1.4826 MAD) and the match's own LSM sigma; refitted on the
    kept until nothing changes (at most 5 rounds). The misregistration the adjustment leaves is
    smooth over a block (navigation) plus the DEM's parallax (0.1 px in the D cameras); what lies
    far off it is a wrong match (a cloud edge or shadow the brightness screen let through, a
    coast), which the simulator's truth confirms (``score_roi_matches``)."""
    n = offsets.shape[0]
    keep = np.ones(n, dtype=bool)
    if n < 6:
        return keep
    a = np.column_stack([np.ones(n), points[:, 0] / 512.0, points[:, 1] / 2048.0])
    for _ in range(5):
        coef, *_ = np.linalg.lstsq(a[keep], offsets[keep, :2], rcond=None)
        r = offsets[:, :2] - a @ coef
        mad = 1.4826 * np.median(np.abs(r[keep] - np.median(r[keep], axis=0)), axis=0)
        new = np.all(np.abs(r) <= k * np.maximum(mad[None, :], offsets[:, 2:]), axis=1)
        if new.sum() < 6 or np.array_equal(new, keep):
            break
        keep = new
    return keep


@dataclass(frozen=True)
class PairMatches:
    """The matches of one image pair of a block: ``kind`` (``"between_cameras"``: ``camera``
    against An of the same pass; ``"between_passes"``: ``camera`` in another pass against the
    block's pass), ``ref`` and ``other`` as ``(pass index, camera index)`` into the block,
    ``offsets (n, 4)`` and ``points (n, 2)`` as :func:`_match_offsets` gives them, ``failed``,
    the pair's ``name`` (e.g. ``"Da/P037_O0233 vs Da/P037_O0000"``) and ``kept (n,)``, the
    matches :func:`consistent_matches` keeps (the statistics use only those)."""

    kind: str
    camera: str
    ref: tuple[int, int]
    other: tuple[int, int]
    offsets: Array
    points: NDArray[np.int64]
    failed: int
    name: str
    kept: NDArray[np.bool_]

    @property
    def usable(self) -> bool:
        """Whether the pair enters the statistics: at least 3 kept matches."""
        return int(self.kept.sum()) >= 3


def coregistration_matches(
    block: RoiBlock, pass_ids: list[str], points_per_pair: int = 64, min_std_counts: float = 150.0
) -> list[PairMatches]:
    """Every pair co-registration compares on a block (module docstring), matched: per camera, it
    against An in each pass and, in each other pass, it against itself in the block's pass."""
    imgs, clouds = block.resampled, block.clouds
    an = block.cameras.index("An") if "An" in block.cameras else None
    out = []
    for j, cam in enumerate(block.cameras):
        pairs = (
            [("between_cameras", (i, an), (i, j)) for i in range(imgs.shape[0])] if an is not None and j != an else []
        )
        pairs += [("between_passes", (block.chosen, j), (i, j)) for i in range(imgs.shape[0]) if i != block.chosen]
        for kind, (pr, cr), (po, co) in pairs:
            d, at, failed = _match_offsets(
                imgs[pr, cr], imgs[po, co], clouds[pr, cr] | clouds[po, co], points_per_pair, min_std_counts
            )
            out.append(
                PairMatches(
                    kind,
                    cam,
                    (pr, cr),
                    (po, co),
                    d,
                    at,
                    failed,
                    f"{block.cameras[co]}/{pass_ids[po]} vs {block.cameras[cr]}/{pass_ids[pr]}",
                    consistent_matches(at, d),
                )
            )
    return out


def coregistration_stats(matches: list[PairMatches]) -> dict[str, dict[str, dict[str, object]]]:
    """Per camera, ``{"between_cameras": stats, "between_passes": stats}`` of a block's matches.
    Each pools the kept matches of every pair of that kind (pairs with fewer than 3 are left
    out), so that it measures the block's RMS misregistration rather than the largest of a few
    small samples: :func:`_offset_stats` of the pooled offsets, plus ``"failed"`` (matches that
    did not converge, all pairs), ``"rejected"`` (matches :func:`consistent_matches` rejected),
    ``"pairs"`` (the pairs pooled) and ``"worst_pair"`` (the pair with the largest ``excess_px``
    by itself: its :func:`_offset_stats` and ``"pair"``)."""
    out: dict[str, dict[str, dict[str, object]]] = {}
    for m in matches:
        out.setdefault(m.camera, {})
    for cam in out:
        for kind in ("between_cameras", "between_passes"):
            cand = [m for m in matches if m.camera == cam and m.kind == kind]
            good = [m for m in cand if m.usable]
            if not good:
                continue
            pairs = [{**_offset_stats(m.offsets[m.kept]), "pair": m.name} for m in good]
            out[cam][kind] = {
                **_offset_stats(np.concatenate([m.offsets[m.kept] for m in good])),
                "failed": int(sum(m.failed for m in cand)),
                "rejected": int(sum(int((~m.kept).sum()) for m in good)),
                "pairs": len(good),
                "worst_pair": max(pairs, key=lambda st: float(st["excess_px"])),
            }  # type: ignore[arg-type]
    return out


def coregistration(
    block: RoiBlock, pass_ids: list[str], points_per_pair: int = 64, min_std_counts: float = 150.0
) -> dict[str, dict[str, dict[str, object]]]:
    """Co-registration measured on a block's resampled images (module docstring):
    :func:`coregistration_stats` of :func:`coregistration_matches`."""
    return coregistration_stats(coregistration_matches(block, pass_ids, points_per_pair, min_std_counts))


def roi_predicted_coregistration(
    pps: list[ProjectionParameters],
    block: int,
    chosen: int,
    cameras: tuple[str, ...],
    dem_sigma_m: float,
    resolution_m: float,
) -> dict[str, dict[str, float]]:
    """The misregistration (px, RMS over the block) the adjustment's own uncertainty predicts for
    one ROI block, per camera: ``vs_An`` from the chosen pass's PP 1-sigma of the camera and of An
    (taken as independent: the two see a point minutes apart) and the SOM DEM's error seen as
    parallax, ``sqrt((s_dem tan|theta|/res)^2 + s_cam^2 + s_An^2)``; ``between_passes`` from the
    two least precise passes, ``sqrt(s_p^2 + s_q^2)`` (passes adjusted apart are independent).
    ``s`` is the RMS over the block's points of the PP's radial 1-sigma ``hypot(sigma_line,
    sigma_sample)`` in image pixels, taken as ROI pixels (the same 275 m scale across track).
    Where this exceeds the seed's 0.2 pixel, no resampling can co-register the block: the
    navigation there is not known better (e.g. an oblique camera imaging the pass's last land
    after its last observation)."""

    def sigma(pp: ProjectionParameters, cam: str) -> float:
        j = np.flatnonzero(np.asarray(pp.blocks) == block)
        if j.size == 0 or cam not in pp.cameras:
            return float("nan")
        c = pp.cameras.index(cam)
        s2 = pp.sigma_line[c, j[0]] ** 2 + pp.sigma_sample[c, j[0]] ** 2
        return float(np.sqrt(np.nanmean(s2))) if np.any(np.isfinite(s2)) else float("nan")

    s = {cam: np.array([sigma(pp, cam) for pp in pps]) for cam in set(cameras) | {"An"}}  # (pass,) per camera
    out: dict[str, dict[str, float]] = {}
    for cam in cameras:
        row: dict[str, float] = {}
        known = s[cam][np.isfinite(s[cam])]
        if known.size >= 2:
            row["between_passes"] = float(np.hypot(*np.sort(known)[-2:]))
        s_an, s_cam = s["An"][chosen], s[cam][chosen]
        if cam != "An" and np.isfinite(s_an) and np.isfinite(s_cam):
            parallax = dem_sigma_m * abs(np.tan(np.radians(VIEW_ANGLE_DEG[cam]))) / resolution_m
            row["vs_An"] = float(np.sqrt(parallax**2 + s_cam**2 + s_an**2))
        if row:
            out[cam] = row
    return out


def compare_rois(
    reference: Any, other: Any, points: int = 64, min_std_counts: float = 150.0
) -> dict[str, dict[int, dict[str, object]]]:
    """The misregistration of ``other`` against ``reference`` (two :class:`~misrgraph.io.roi.RoiFile`
    of one path, e.g. misrgraph's ROI and MISR's L1B2 imagery imported with ``import l1b2``), per
    camera both hold and block both hold: :func:`_offset_stats` of the consistent LSM matches of
    ``other`` against ``reference`` at up to ``points`` points clear of cloud and of empty pixels
    (offsets in 275 m pixels: where ``reference`` shows what ``other`` shows plus the offset),
    plus ``"failed"`` and ``"rejected"``; a pair with fewer than 3 kept matches gets ``None``."""
    if reference.path != other.path or reference.resolution_m != other.resolution_m:
        raise InputError("ROI files", (reference.path, other.path), "two ROIs of one path at one resolution")
    out: dict[str, dict[int, dict[str, object]]] = {}
    blocks = sorted(set(reference.blocks.tolist()) & set(other.blocks.tolist()))
    if not blocks:
        raise InputError("ROI blocks", (reference.blocks.tolist()[:3], other.blocks.tolist()[:3]), "blocks both hold")
    for cam in reference.cameras:
        if cam not in other.cameras:
            continue
        ca, cb = reference.cameras.index(cam), other.cameras.index(cam)
        out[cam] = {}
        for b in blocks:
            ka = int(np.flatnonzero(reference.blocks == b)[0])
            kb = int(np.flatnonzero(other.blocks == b)[0])
            a = np.where(reference.source[ca, ka] >= 0, reference.pixels[ca, ka], np.nan).astype(np.float32)
            o = np.where(other.source[cb, kb] >= 0, other.pixels[cb, kb], np.nan).astype(np.float32)
            bad = reference.cloudy[ca, ka] | other.cloudy[cb, kb]
            d, at, failed = _match_offsets(a, o, bad, points, min_std_counts)
            kept = consistent_matches(at, d) if d.shape[0] else np.zeros(0, bool)
            if int(kept.sum()) < 3:
                out[cam][int(b)] = None  # type: ignore[assignment]
                continue
            out[cam][int(b)] = {**_offset_stats(d[kept]), "failed": failed, "rejected": int((~kept).sum())}
    if not out:
        raise InputError("ROI cameras", (reference.cameras, other.cameras), "a camera both hold")
    return out
