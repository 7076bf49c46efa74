"""Laser ring extraction with sub-pixel Gaussian peak detection (paper Sec. III-A).

The laser channel, with the LED-lit texture suppressed (laser channel minus the
brightest other channel), is resampled along radial lines from the principal point
(one line per angle, 1 px radial steps, cv2.remap) over the valid annulus, or, when
the laser plane is known, over its radii whose rays can meet the plane (the others can
hold no ring sample that triangulates: bend's 211 of 508). On each line the strongest
peak is refined with the three-point Gaussian fit (log-parabola, Fisher & Naidu [20]).
A peak with clipped samples is also located by the centroid of its background-free
signal within ``centroid_half_px`` of it: a clipped top, lifted by the laser's crosstalk
in the other channels, is no Gaussian, and the three-point fit pulls a ring about a
pixel wide towards the scan line's samples (an oval reads low); on unclipped peaks the
centroid would only add its tails' noise. The ring keeps both: the three-point
positions (``pixels``, what camera motion uses) and each sample's move to its centroid
(``centroid_shift_px``, what the analysis's rings apply:
:func:`~omnipipe.laser.triangulate.centroid_ring`). Each sample gets a confidence (peak
height over the line's robust noise); weak, saturated-flat or ambiguous peaks (a second
separate peak of comparable height: reflections, bright texture) are rejected and left
as gaps, never filled in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from omnipipe.camera import CameraModel
from omnipipe.config import bounded
from omnipipe.image import CHANNEL_INDEX
from omnipipe.laser._kernels import line_statistics
from omnipipe.laser.ring import LaserRing
from omnipipe.laser.triangulate import intersect_plane
from omnipipe.rig import LaserPlane


@dataclass(frozen=True)
class ExtractionConfig:
    """Ring extraction settings.

    Attributes:
        angles: number of radial scan lines (evenly spaced).
        radial_step_px: sampling step along each line (px).
        min_snr: a peak must exceed the line's noise (robust sigma) this many times.
        min_peak: and this absolute height (grey levels above the line's background).
        ambiguity_ratio: reject when a second peak, more than ``separation_px`` away, is
            at least this fraction of the first.
        separation_px: minimum distance of a competing peak (px).
        saturation: grey level treated as saturated (fraction of full scale).
        tophat_px: half-width (samples) of the white top-hat that removes structures
            broader than the ring before peak search (0: off); keep it several times the
            ring's width.
        max_width_factor: reject peaks wider than this x the ring's median width (0: off).
        min_ring_fraction: a frame whose peaks cover fewer scan lines than this has no
            laser ring (measured: real rings 0.92-1.0; texture in a wrong channel 0.04-0.27).
        centroid_half_px: a peak with clipped samples is also located by the centroid of
            the background-free signal within this many px of its strongest sample (a few
            times the ring's width: the whole profile; 3 suits a ring about a pixel wide),
            for the analysis's rings (:attr:`LaserRing.centroid_shift_px`); camera motion
            keeps the three-point fit (the centroid's rings there moved steps on the
            robustness bench: benchmarks/RESULTS.md). 0: the three-point fit only.
    """

    angles: int = bounded(720, ge=8)
    radial_step_px: float = bounded(1.0, gt=0)
    min_snr: float = bounded(6.0, ge=0)
    min_peak: float = bounded(12.0, ge=0)
    ambiguity_ratio: float = bounded(0.6, ge=0, le=1)
    separation_px: float = bounded(3.0, ge=0)
    saturation: float = bounded(0.98, gt=0, le=1)
    tophat_px: int = bounded(8, ge=0)
    max_width_factor: float = bounded(0.0, ge=0)
    min_ring_fraction: float = bounded(0.4, ge=0, le=1)
    centroid_half_px: float = bounded(3.0, ge=0)


def laser_signal(image: np.ndarray, channel: str) -> tuple[np.ndarray, float]:
    """Laser channel with the LED-lit texture suppressed, as float32, and full scale."""
    img = np.asarray(image)
    full = (
        65535.0
        if img.dtype == np.uint16
        else 255.0
        if img.dtype == np.uint8
        else float(np.nanmax(img) or 1.0)
    )
    if img.ndim == 2 or channel == "gray":
        grey = img.astype(np.float32) if img.ndim == 2 else img.astype(np.float32).mean(axis=2)
        return grey, full
    idx = CHANNEL_INDEX[channel]
    others = [c for c in range(img.shape[2]) if c != idx][:2]
    if img.dtype in (np.uint8, np.uint16) and len(others) == 2:
        # The same whole numbers, without float32 copies of all channels: the two other
        # channels' maximum in their own type, then one subtraction into float32.
        planes = [cv2.extractChannel(img, c) for c in (idx, *others)]
        return cv2.subtract(planes[0], cv2.max(planes[1], planes[2]), dtype=cv2.CV_32F), full
    sig = img[..., idx].astype(np.float32) - img[..., others].astype(np.float32).max(axis=2)
    return sig, full


class RingExtractor:
    """Extracts rings from frames of one camera (the polar sampling maps are built once).

    Args:
        camera: the rig's camera.
        config: extraction settings.
        plane: the calibrated laser plane, or None (calibrating it). Given, the scan lines
            cover only the radii whose rays meet it as :func:`triangulate_ring` accepts
            (in front of the focus, not grazing) on some line, widened by the top-hat's
            half width, the competing peak's separation and the fit's step: a peak
            beyond them could not triangulate. Bend: 224 of 508 radii scanned (211 meet
            the plane), about 7 -> 3 ms per frame.
    """

    def __init__(
        self, camera: CameraModel, config: ExtractionConfig | None = None, plane: LaserPlane | None = None
    ) -> None:
        self.camera = camera
        self.config = cfg = config or ExtractionConfig()
        r0 = max(camera.radius_min, 1.0)
        self.radii = np.arange(r0, camera.radius_max, cfg.radial_step_px, dtype=np.float32)
        self.angles = np.arange(cfg.angles) * (2 * math.pi / cfg.angles)
        cos, sin = np.cos(self.angles)[:, None], np.sin(self.angles)[:, None]
        if plane is not None:
            margin = int(cfg.tophat_px) + int(math.ceil(cfg.separation_px / cfg.radial_step_px)) + 2
            self.radii = _radii_meeting(camera, plane, self.radii, cos, sin, margin)
        self.map_x = (camera.cx + self.radii[None, :] * cos).astype(np.float32)
        self.map_y = (camera.cy + self.radii[None, :] * sin).astype(np.float32)
        # Samples outside the image (mirror rim cut by the sensor) are invalid.
        self.inside = (
            (self.map_x >= 0)
            & (self.map_x <= camera.width - 1)
            & (self.map_y >= 0)
            & (self.map_y <= camera.height - 1)
        )
        self._outside = np.flatnonzero(~self.inside)  # flat indices, set to 0 in place
        # The frame's part the scan lines sample (every bilinear tap; cut by the frame's
        # edges, where the constant border begins as on the whole frame) and the maps
        # moved to it (exactly: whole numbers off float32 values at least as large).
        x0 = max(int(np.floor(self.map_x.min())) - 1, 0)
        y0 = max(int(np.floor(self.map_y.min())) - 1, 0)
        x1 = min(int(np.ceil(self.map_x.max())) + 2, camera.width)
        y1 = min(int(np.ceil(self.map_y.max())) + 2, camera.height)
        if x1 - x0 < 2 or y1 - y0 < 2:  # no scan line reaches into the frame: all of it
            x0 = y0 = 0
            x1, y1 = camera.width, camera.height
        self._window = (slice(y0, y1), slice(x0, x1))
        self._window_maps = (self.map_x - np.float32(x0), self.map_y - np.float32(y0))

    def extract(self, image: np.ndarray, channel: str) -> LaserRing:
        """The ring of one frame (never raises on odd images: returns an empty ring with a warning)."""
        cfg, cam = self.config, self.camera
        n_lines = len(self.angles)
        empty = LaserRing(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0), scanned=n_lines)
        img = np.asarray(image)
        if img.ndim not in (2, 3) or img.shape[:2] != (cam.height, cam.width):
            empty.warnings.append(
                f"frame is {img.shape[1::-1] if img.ndim >= 2 else img.shape}, expected {cam.width}x{cam.height}"
            )
            return empty
        full = 65535.0 if img.dtype == np.uint16 else 255.0
        if img.dtype not in (np.uint8, np.uint16):
            img = img.astype(np.float32)
            full = float(np.nanmax(img)) or 1.0
        polar, polar_raw = self._polar_signal(img, channel)
        peaks = self._line_peaks(polar, polar_raw, full)
        ok = peaks.ok
        cx = cam.cx + peaks.radius * np.cos(self.angles)
        cy = cam.cy + peaks.radius * np.sin(self.angles)
        pixels = np.stack([cx, cy], axis=1)[ok]
        ring = LaserRing(
            pixels=pixels,
            angle_rad=self.angles[ok],
            confidence=peaks.snr[ok],
            radius_sigma_px=peaks.radius_sigma[ok],
            peak_width_px=peaks.width[ok],
            scanned=n_lines,
            centroid_shift_px=peaks.centroid_shift[ok] if peaks.centroid_shift.size else peaks.centroid_shift,
            gap_edges=_gap_edges(polar, peaks, self.radii[0], cfg.radial_step_px),
        )
        if not ok.any():
            ring.warnings.append("no laser ring visible (no scan line with a clear peak)")
        elif ok.mean() < cfg.min_ring_fraction:
            # Scattered peaks on a few lines are texture (seams, pits), not a light ring.
            empty.warnings.append(
                f"no laser ring visible (peaks on only {100 * ok.mean():.0f} % of scan lines)"
            )
            return empty
        elif peaks.saturated.mean() > 0.25:
            ring.warnings.append(f"laser saturated on {100 * peaks.saturated.mean():.0f} % of scan lines")
        return ring

    def _polar_signal(self, img: np.ndarray, channel: str) -> tuple[np.ndarray, np.ndarray]:
        """(lines, radii) float32 laser signal (texture suppressed, top-hat filtered,
        zero outside the image) and the raw laser channel, resampled along the scan lines."""
        cfg = self.config
        # Resample first (one remap of all channels), then suppress the texture in polar.
        polar_img = self._resample(img, channel)
        polar, _ = laser_signal(polar_img, channel)  # of a 4-channel one: its first three
        if polar_img.ndim == 3 and channel in CHANNEL_INDEX:
            polar_raw = polar_img[..., CHANNEL_INDEX[channel]]
        else:
            polar_raw = polar_img if polar_img.ndim == 2 else polar_img.mean(axis=2)
        polar = np.ascontiguousarray(polar, np.float32)  # a new array: zeroed in place
        polar.reshape(-1)[self._outside] = 0.0
        if cfg.tophat_px > 0:
            # White top-hat along each line: keeps features narrower than the element (the
            # ring), removes broad ones (red rust close to the LEDs), with no overshoot at
            # their edges.
            kernel = np.ones((1, 2 * int(cfg.tophat_px) + 1), np.uint8)
            polar = cv2.morphologyEx(polar, cv2.MORPH_TOPHAT, kernel)
        return polar, polar_raw

    def _resample(self, img: np.ndarray, channel: str) -> np.ndarray:
        """(lines, radii[, C]) the frame bilinearly resampled along the scan lines (zero
        beyond its edges), from the part of it they reach (the same values as from the
        whole frame). An 8- or 16-bit RGB frame of a colour laser comes back with a
        fourth channel after its three, the same values (OpenCV's bilinear remap of four
        channels is the faster one: benchmarks/RESULTS.md, las33)."""
        part = img[self._window]
        if img.ndim == 3 and img.shape[2] == 3 and img.dtype in (np.uint8, np.uint16) and channel in CHANNEL_INDEX:
            part = cv2.cvtColor(part, cv2.COLOR_RGB2RGBA)
        return cv2.remap(part, *self._window_maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)

    def _line_peaks(self, polar: np.ndarray, polar_raw: np.ndarray, full: float) -> _LinePeaks:
        """Each scan line's strongest peak, refined by the three-point Gaussian fit and
        tested (SNR, height, ambiguity, saturation, width, radius)."""
        cfg = self.config
        # Per line (compiled, :mod:`omnipipe.laser._kernels`): background (median) and
        # robust noise (MAD of the line's first difference), both estimated on every 4th
        # sample (robust statistics, 4x cheaper); the strongest peak, the strongest
        # response farther than separation_px from it (ambiguity) and the saturated
        # samples around it.
        sep = int(round(cfg.separation_px / cfg.radial_step_px))
        step = int(round(1.0 / cfg.radial_step_px))
        # The raw laser channel against the threshold in float32, as a float32 copy of it
        # was (its whole numbers are exact in float32); a channel mean in float64.
        threshold = cfg.saturation * full
        clipped = polar_raw >= (threshold if polar_raw.dtype == np.float64 else np.float32(threshold))
        stats = line_statistics(polar, clipped, sep, step)
        noise = 1.4826 * stats.mad / math.sqrt(2)
        noise = np.maximum(noise, 0.5)
        k = stats.peak_index
        peak = stats.around[:, 1]
        snr = peak / noise
        ok = (snr >= cfg.min_snr) & (peak >= cfg.min_peak) & (k > 0) & (k < polar.shape[1] - 1)
        ok &= stats.second < cfg.ambiguity_ratio * peak
        # Saturation: a clipped top is still symmetric if the clipped run is short;
        # longer plateaus have no peak to fit and are rejected.
        run_len = stats.clipped_run
        ok &= run_len <= 3
        off, width = _gaussian_fit(stats.around)
        ok &= np.isfinite(off) & (np.abs(off) <= 1.0)
        off = off * step  # samples
        radius = self.radii[0] + (k + off) * cfg.radial_step_px
        shift = _centroid_shift(cfg, polar, stats.background, k, off, (run_len > 0) & ok)
        # Sub-pixel uncertainty of a Gaussian peak's centre ~ width / SNR.
        rad_sigma = np.where(ok, width / np.maximum(snr, 1e-6), np.nan)
        if cfg.max_width_factor > 0 and np.sum(ok) > 10:
            # A peak much wider than the ring's typical one is the sheet grazing a wall
            # nearly parallel to it (a dent's or bulge's flank): its centre is off the plane.
            typical = float(np.nanmedian(width[ok]))
            ok &= width <= cfg.max_width_factor * typical
        ok &= radius <= self.camera.radius_max
        return _LinePeaks(ok, radius, snr, width, rad_sigma, run_len > 0, shift, peak, k, stats.background)


EDGE_MIN_GAP_LINES = 16
"""Scan lines without a peak the ring's widest gap needs for :func:`_gap_edges` to
locate the stripe's end at either side (8 deg at 720 lines, the analysis' smallest cut;
a water line cuts tens to hundreds; texture drops one or two)."""

EDGE_PLATEAU_PX = (2.5, 6.0)
"""How far (px along the ring, from the last peak before a gap) the lit stripe's
plateau is taken (:func:`_gap_edges`): beyond the blurred end's fall-off (the optics'
blur about a pixel) and near enough to share the end's texture and range."""

EDGE_BEYOND_PX = 4.0
"""How far (px along the ring) :func:`_gap_edges` follows the stripe into a gap."""

EDGE_FLANK_PX = (1.0, 1.5, 2.0, 2.5, 3.0)
"""Radial offsets (px, both sides of the stripe's centre) :func:`_gap_edges` reads the
stripe's height along the ring at: the first whose plateau is at most
:data:`EDGE_FLANK_SHARE` of the peaks' (below any clipping of the stripe's top)."""

EDGE_FLANK_SHARE = 0.6
"""Largest share of the peaks' plateau height the flank taken by :func:`_gap_edges` may
hold: a stripe clipped at the sensor's full scale is clipped in its core only, and the
half of a clipped plateau lies past the edge (the brighter the stripe, the further: 0.3-0.7
px at 400x300 where half its peaks clip); its flanks keep the edge's true profile."""

EDGE_CLIPPED_SHARE = 0.25
"""Share of an end's plateau peaks clipped above which :func:`_gap_edges` reads the
stripe's flanks (the ring's "laser saturated" warning's share)."""

EDGE_CLIP_SHIFT_PX = 1.0
"""Largest move (px along the ring, towards the lit wall) of the flanks' reading from the
core's that :func:`_gap_edges` takes as the clipping's: a clipped core's half height lies
past the edge by less than the blurred step's width; a larger move is the stripe's
profile changing along the ring (a lateral's rim, a grazing wall: random-features seed
1's lateral read 17-59 mm of reach on its flanks), where the core's reading stands."""

_FLANK_SIDES = np.array([(-f, f) for f in EDGE_FLANK_PX])


def _gap_edges(polar: np.ndarray, peaks: _LinePeaks, r0: float, step: float) -> np.ndarray:
    """(E, 3) float32 rows (end line, direction, offset), E <= 2, locating where the lit
    stripe ends at each side of the ring's widest gap when it spans more than
    :data:`EDGE_MIN_GAP_LINES` scan lines without an accepted peak (the only gap the
    analysis takes for a water line's cut): ``end line`` the last accepted line before the gap,
    ``direction`` +1 when the gap lies at higher lines, -1 at lower, ``offset`` (scan
    lines, fractional, positive into the gap) where the stripe's height along the ring
    falls to half its plateau (:data:`EDGE_PLATEAU_PX`). An edge that stops the light
    (a water line, a shadow) is a step blurred by the optics: its half height is the
    edge itself, wherever the extractor's tests (SNR, a competing texture peak) stopped
    accepting peaks. Heights: the accepted peaks', else the largest background-free
    sample within one radial step of the stripe's radius (extrapolated along the ring
    from the plateau's peaks) up to :data:`EDGE_BEYOND_PX` into the gap; where the
    plateau's peaks clip, the signal on both flanks of the stripe (:data:`EDGE_FLANK_PX`
    from its radius, the two sides' mean, so an oblique edge's shifts cancel): a flank
    is not clipped where the stripe's core is (:func:`_edge_offset`). An end with no
    fall-off to half within that reach (or less than three plateau peaks) is left out. ``polar`` (L, S) the line signal,
    ``r0`` / ``step`` its first radius and radial step (px)."""
    ok = peaks.ok
    n = len(ok)
    idx = np.flatnonzero(ok)
    if len(idx) < 2:
        return np.zeros((0, 3), np.float32)
    gaps = np.diff(idx)
    g = int(np.argmax(gaps))
    width = int(gaps[g])
    if n - (idx[-1] - idx[0]) > width:  # the gap across line 0
        g, width = len(idx) - 1, int(n - (idx[-1] - idx[0]))
    rows = []
    if width > EDGE_MIN_GAP_LINES:
        for end, d in ((int(idx[g]), 1), (int(idx[(g + 1) % len(idx)]), -1)):
            row = _edge_offset(polar, peaks, end, d, width - 1, r0, step)
            if row is not None:
                rows.append((end, d, row))
    return np.array(rows, np.float32).reshape(-1, 3)


def _edge_offset(
    polar: np.ndarray, peaks: _LinePeaks, end: int, d: int, gap: int, r0: float, step: float
) -> float | None:
    """The offset (lines, + into the gap) of :func:`_gap_edges`' half-height point past
    the accepted line ``end`` whose gap of ``gap`` lines lies in direction ``d``; None
    where it is not found. Read on the stripe's core (its peaks' heights), or on its
    flanks (:data:`EDGE_FLANK_PX`) where the plateau's peaks clip (more than
    :data:`EDGE_CLIPPED_SHARE` of them) and the flanks put the edge before the core's
    reading by at most :data:`EDGE_CLIP_SHIFT_PX`: what a clipped core can move it."""
    n = len(peaks.ok)
    px_line = max(float(peaks.radius[end]) * 2.0 * math.pi / n, 1e-3)
    p0 = min(max(2, math.ceil(EDGE_PLATEAU_PX[0] / px_line)), 60)
    p1 = min(max(p0 + 3, math.ceil(EDGE_PLATEAU_PX[1] / px_line)), 90)
    q = min(max(3, math.ceil(EDGE_BEYOND_PX / px_line)), gap, 60)
    inside = np.arange(p0, p1 + 1)
    lines = (end - d * inside) % n
    lit = peaks.ok[lines]
    if lit.sum() < 3:
        return None
    plateau = float(np.median(peaks.height[lines[lit]]))
    # The stripe's radius along the ring (px per line): from the plateau's peaks to the end's.
    r_end = float(peaks.radius[end])
    slope = (r_end - float(peaks.radius[lines[lit]].mean())) / float(inside[lit].mean())
    j = np.arange(-p0, q + 1)
    prof = (end + d * j) % n
    k = np.rint((r_end + slope * j - r0) / step).astype(int)
    half = int(math.ceil(1.0 / step))
    cols = np.clip(k[:, None] + np.arange(-half, half + 1)[None, :], 0, polar.shape[1] - 1)
    h = polar[prof[:, None], cols].max(axis=1) - peaks.background[prof]
    own = (j <= 0) & peaks.ok[prof]
    h = np.where(own, peaks.height[prof], h).astype(float)
    core = _half_crossing(j, h, 0.5 * plateau, 0)
    if core is None or float(np.mean(peaks.saturated[lines[lit]])) <= EDGE_CLIPPED_SHARE:
        return core
    flank = _flank_offset(polar, peaks, end, d, (p0, p1, q), (r_end, slope), r0, step, plateau)
    if flank is not None and 0.0 < (core - flank) * px_line <= EDGE_CLIP_SHIFT_PX:
        return flank
    return core


def _half_crossing(j: np.ndarray, h: np.ndarray, thr: float, start: int) -> float | None:
    """Where the profile ``h`` at offsets ``j`` (lines) first falls below ``thr`` from
    index ``start`` on (linear between samples); None where it does not or at once."""
    below = np.flatnonzero(h[start:] < thr)
    if thr <= 0.0 or len(below) == 0 or below[0] == 0:
        return None
    b = start + int(below[0])
    t = (h[b - 1] - thr) / max(h[b - 1] - h[b], 1e-9)
    return float(j[b - 1] + t)


def _flank_offset(
    polar: np.ndarray,
    peaks: _LinePeaks,
    end: int,
    d: int,
    span: tuple[int, int, int],
    ramp: tuple[float, float],
    r0: float,
    step: float,
    plateau: float,
) -> float | None:
    """:func:`_edge_offset` read on the stripe's two flanks: the signal at
    :data:`EDGE_FLANK_PX` either side of its radius (each accepted line's own peak, beyond
    them ``ramp`` = (radius at ``end``, px per line)), the first offset whose plateau is at
    most :data:`EDGE_FLANK_SHARE` of the peaks' ``plateau``; ``span`` = (p0, p1, q) lines."""
    p0, p1, q = span
    n = len(peaks.ok)
    j = np.arange(-p1, q + 1)
    prof = (end + d * j) % n
    radius = np.where((j <= 0) & peaks.ok[prof], peaks.radius[prof], ramp[0] + ramp[1] * j)
    in_plateau = (j <= -p0) & peaks.ok[prof]
    # Every flank's two sides at once (F, 2, J): the first flank low enough, else the last.
    x = (radius[None, None, :] + _FLANK_SIDES[:, :, None] - r0) / step
    k = np.clip(np.floor(x).astype(int), 0, polar.shape[1] - 2)
    t = np.clip(x - k, 0.0, 1.0)
    v = 0.5 * ((1.0 - t) * polar[prof, k] + t * polar[prof, k + 1])
    flanks = v[:, 0] + v[:, 1] - peaks.background[prof]
    levels = np.median(flanks[:, in_plateau], axis=1)
    low = np.flatnonzero(levels <= EDGE_FLANK_SHARE * plateau)
    f = int(low[0]) if len(low) else len(levels) - 1
    return _half_crossing(j, flanks[f], 0.5 * float(levels[f]), p1 - p0)


@dataclass(frozen=True)
class _LinePeaks:
    """Per scan line (L,): accepted, peak radius (px), SNR, Gaussian sigma (px), radius
    sigma (px, NaN where not accepted), whether the peak's top is clipped, the
    move (px, float32) from the peak's centre to its clipped-peak centroid (empty: no
    centroid asked for), the peak's background-free height, its sample index and the line's background."""

    ok: np.ndarray
    radius: np.ndarray
    snr: np.ndarray
    width: np.ndarray
    radius_sigma: np.ndarray
    saturated: np.ndarray
    centroid_shift: np.ndarray
    height: np.ndarray
    index: np.ndarray
    background: np.ndarray


def _centroid_shift(
    cfg: ExtractionConfig, polar: np.ndarray, background: np.ndarray, k: np.ndarray, off: np.ndarray, use: np.ndarray
) -> np.ndarray:
    """(L,) float32 radial move (px) from each line's three-point centre (``k`` + ``off``
    samples) to the centroid (:func:`_centroid_offset`) of the lines ``use`` (clipped,
    accepted peaks), 0 elsewhere and where the centroid is undefined; (0,) when
    ``cfg.centroid_half_px`` is 0."""
    half = int(round(cfg.centroid_half_px / cfg.radial_step_px))
    if half <= 0:
        return np.zeros(0, np.float32)
    shift = np.zeros(len(k), np.float32)
    if use.any():
        cen = _centroid_offset(polar[use], background[use], k[use], half)
        move = (cen - off[use]) * cfg.radial_step_px
        shift[use] = np.where(np.isfinite(move), move, 0.0)
    return shift


def _gaussian_fit(around: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Three-point Gaussian fit on the 1-px grid around each peak (Fisher & Naidu).

    Args:
        around: (L, 3) the signal one sample before, at and after each line's peak.

    Returns:
        (L,) sub-sample offset of the centre (NaN where the log-parabola opens upwards)
        and (L,) Gaussian sigma from its curvature, sigma^2 = -1 / den (samples).
    """
    y0 = np.maximum(around[:, 0], 1e-3)
    y1 = np.maximum(around[:, 1], 1e-3)
    y2 = np.maximum(around[:, 2], 1e-3)
    l0, l1, l2 = np.log(y0), np.log(y1), np.log(y2)
    den = l0 - 2 * l1 + l2
    with np.errstate(invalid="ignore", divide="ignore"):
        off = np.where(den < -1e-9, 0.5 * (l0 - l2) / den, np.nan)
        width = np.sqrt(np.where(den < 0, -1.0 / den, np.nan))
    return off, width


def _centroid_offset(polar: np.ndarray, background: np.ndarray, k: np.ndarray, half: int) -> np.ndarray:
    """(L,) offset (samples) from each line's peak sample ``k`` (L,) of the centroid of
    its background-free signal ``polar`` (L, S) - ``background`` (L,), negative parts
    taken as 0, over the samples within ``half`` of the peak (on the line); NaN where
    that signal sums to nothing."""
    j = np.arange(-half, half + 1)
    idx = k[:, None] + j[None, :]
    inside = (idx >= 0) & (idx < polar.shape[1])
    y = np.take_along_axis(polar, np.clip(idx, 0, polar.shape[1] - 1), axis=1).astype(np.float64)
    y = np.where(inside, np.maximum(y - background[:, None], 0.0), 0.0)
    total = y.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0, (y @ j) / total, np.nan)


def _radii_meeting(
    camera: CameraModel, plane: LaserPlane, radii: np.ndarray, cos: np.ndarray, sin: np.ndarray, margin: int
) -> np.ndarray:
    """The consecutive part of ``radii`` (float32, px) from the first to the last radius
    at which some scan line's ray (angle ``cos``, ``sin``: (L, 1)) meets ``plane`` as
    :func:`~omnipipe.laser.triangulate.intersect_plane` accepts, widened by ``margin``
    radii each side; all of ``radii`` when no ray meets it."""
    x = camera.cx + radii[None, :].astype(float) * cos
    y = camera.cy + radii[None, :].astype(float) * sin
    with np.errstate(invalid="ignore"):
        rays = camera.unproject(np.stack([x.ravel(), y.ravel()], axis=1))
    _, valid = intersect_plane(rays, plane)
    meets = np.flatnonzero(valid.reshape(x.shape).any(axis=0))
    if len(meets) == 0:
        return radii
    return radii[max(int(meets[0]) - margin, 0) : int(meets[-1]) + margin + 1]


def _spread_rings(rings: list[LaserRing], max_rings: int) -> list[LaserRing]:
    """Up to ``max_rings`` evenly chosen rings with triangulated points and peak widths."""
    usable = [r for r in rings if len(r.points_in_rig) >= 20 and len(r.peak_width_px) == len(r.pixels)]
    if not usable:
        return []
    pick = np.unique(np.linspace(0, len(usable) - 1, min(max_rings, len(usable))).round().astype(int))
    return [usable[i] for i in pick]


def ring_blur_mm(rings: list[LaserRing], max_rings: int = 50) -> float:
    """Gaussian sigma (mm along the wall) of the light section's smoothing along the ring.

    The imaged stripe's peak width (``peak_width_px``, Gaussian sigma across the
    stripe) times the ring's scale along itself (mm of wall per px of ring, from
    neighbouring samples): the crest of a narrow defect is seen through this blur
    (:func:`omnipipe.analysis.sizing.seen_bump_model`). Median over up to
    ``max_rings`` evenly chosen rings with triangulated points.

    Returns:
        The sigma (mm); 0.0 when no ring has enough samples.
    """
    values = []
    for r in _spread_rings(rings, max_rings):
        dp = np.linalg.norm(np.diff(r.points_in_rig, axis=0), axis=1)
        dx = np.linalg.norm(np.diff(r.pixels, axis=0), axis=1)
        ok = (dx > 0.2) & (dx < 5.0)  # neighbours on the ring, not across a gap
        if ok.sum() < 10:
            continue
        values.append(float(np.median(r.peak_width_px)) * float(np.median(dp[ok] / dx[ok])))
    return float(np.median(values)) if values else 0.0


def edge_reach_mm(rings: list[LaserRing], max_rings: int = 50) -> tuple[float, float]:
    """How far (mm along the wall) the light section's samples run on past the end of a
    lit stretch (a water line, a shadow edge), and the spread of that over the rings.

    Where the stripe stops at an edge its image along the ring is a step blurred by the
    ring's Gaussian sigma ``s`` (the :func:`ring_blur_mm` of that ring): I(x) = I0 Phi(-x / s)
    with x measured from the edge into the dark side, half the lit brightness at the edge
    itself. The extractor keeps a peak down to its detection threshold, a fraction
    f = (the ring's faintest accepted SNR) / (its median SNR) of the lit stripe, so the
    last sample lies s Phi^-1(1 - f) beyond the edge. Median over up to ``max_rings``
    evenly chosen rings with triangulated points. The wall's texture and noise lift the
    faintest peaks over the threshold, so samples may run up to about s / 2 further
    (tests/laser/test_laser.py; the true-motion captures: 0.9 mm of 5.9 mm).

    Returns:
        (reach, 1-sigma of one ring's reach about the median) in mm; (0.0, 0.0) when no
        ring has enough samples.
    """
    from scipy.special import ndtri

    values = []
    for r in _spread_rings(rings, max_rings):
        dp = np.linalg.norm(np.diff(r.points_in_rig, axis=0), axis=1)
        dx = np.linalg.norm(np.diff(r.pixels, axis=0), axis=1)
        ok = (dx > 0.2) & (dx < 5.0)
        conf = r.confidence[np.isfinite(r.confidence)]
        if ok.sum() < 10 or len(conf) < 10:
            continue
        blur = float(np.median(r.peak_width_px)) * float(np.median(dp[ok] / dx[ok]))
        frac = float(np.min(conf)) / max(float(np.median(conf)), 1e-9)
        values.append(blur * float(ndtri(1.0 - min(max(frac, 1e-6), 0.5))))
    if not values:
        return 0.0, 0.0
    v = np.array(values)
    return float(np.median(v)), float(1.4826 * np.median(np.abs(v - np.median(v))))


EDGE_SIGMA_PX = 0.5
"""1-sigma (px of image along the ring) of a ring's reach (:func:`station_edge_reach`,
both ends' mean) about the true one: the edge's image is resolved to its pixel (the
renderer classifies each pixel by its centre ray: +-0.5 px across the water line's
image, more along an oblique stripe), and the plateau's texture and speckle move the
half-height point. The rings of one run err alike (benchmarks/RESULTS.md, wat28):
the analysis takes it as shared by the run's stations."""


def station_edge_reach(rings: list[LaserRing]) -> tuple[np.ndarray, np.ndarray]:
    """Each ring's reach past the ends of its largest gap (a water line's cut), measured
    from the stripe's fall-off there (``LaserRing.gap_edges``): how far (mm along the
    wall, + beyond the edge into the gap) the ring's last samples at both ends lie past
    the stripe's half-height point, the two ends' mean, and its 1-sigma
    (:data:`EDGE_SIGMA_PX` through the ring's mm per px at its ends). A ring's own
    last sample at each end (after triangulation and outlier removal) is matched to the
    extractor's end row on the same side of the gap.

    Returns:
        (K,) reach and (K,) 1-sigma, mm; NaN where a ring has no gap of more than
        :data:`EDGE_MIN_GAP_LINES` lines or either end has no row.
    """
    reach, sigma = np.full(len(rings), np.nan), np.full(len(rings), np.nan)
    for i, r in enumerate(rings):
        edges = np.asarray(r.gap_edges, float).reshape(-1, 3)
        if len(edges) < 2 or len(r.points_in_rig) < 20 or not r.scanned:
            continue
        n = int(r.scanned)
        lines = np.round(np.asarray(r.angle_rad) * n / (2.0 * math.pi)).astype(int) % n
        order = np.argsort(lines, kind="stable")
        lines = lines[order]
        gaps = np.diff(np.r_[lines, lines[0] + n])
        g = int(np.argmax(gaps))
        if gaps[g] <= EDGE_MIN_GAP_LINES:
            continue
        ends = []
        for pos, d in ((g, 1), ((g + 1) % len(lines), -1)):
            e = int(lines[pos])
            cand = edges[edges[:, 1] == d]
            c = (d * (cand[:, 0].astype(int) - e)) % n
            cand, c = cand[c < gaps[g]], c[c < gaps[g]]
            if not len(cand):
                break
            k = int(np.argmin(c))
            near = order[[(pos - d * j) % len(lines) for j in range(10)]]
            dl = np.abs(np.diff(lines[[(pos - d * j) % len(lines) for j in range(10)]]))
            dl = np.minimum(dl, n - dl)
            one = dl == 1
            if one.sum() < 3:
                break
            mm = np.linalg.norm(np.diff(r.points_in_rig[near], axis=0), axis=1)[one]
            px = np.linalg.norm(np.diff(r.pixels[near], axis=0), axis=1)[one]
            mm_line, px_line = float(np.median(mm)), max(float(np.median(px)), 1e-6)
            ends.append((-(c[k] + cand[k, 2]) * mm_line, EDGE_SIGMA_PX * mm_line / px_line))
        if len(ends) == 2:
            reach[i] = 0.5 * (ends[0][0] + ends[1][0])
            sigma[i] = 0.5 * (ends[0][1] + ends[1][1])
    return reach, sigma


def axial_blur_mm(rings: list[LaserRing], camera: CameraModel, max_rings: int = 50) -> float:
    """Gaussian sigma (mm along the pipe axis) of the light section's smoothing across the ring.

    Across the stripe the image is blurred too (``peak_width_px``: the sheet's thickness,
    the optics and the pixel): each ring sees a band of wall along the axis, and on an
    axially curved crest its peak is that band's ridge. One px of image radius at a ring
    sample spans ``dz`` mm of wall along the axis (the rays through the pixel half a px
    inwards and outwards, met at the sample's distance from the rig's axis); the sigma is
    the median of ``peak_width_px * dz`` over up to ``max_rings`` evenly chosen rings.

    Returns:
        The sigma (mm); 0.0 when no ring has enough samples.
    """
    centre = np.array([camera.cx, camera.cy], float)
    values = []
    for r in _spread_rings(rings, max_rings):
        off = r.pixels - centre
        rad = np.linalg.norm(off, axis=1, keepdims=True)
        unit = off / np.maximum(rad, 1e-9)
        rho = np.hypot(r.points_in_rig[:, 0], r.points_in_rig[:, 1])
        z = []
        for step in (-0.5, 0.5):
            d = camera.unproject(centre + (rad + step) * unit)
            z.append(rho * d[:, 2] / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9))
        dz = np.abs(z[1] - z[0])
        ok = np.isfinite(dz) & np.isfinite(r.peak_width_px)
        if ok.sum() < 10:
            continue
        values.append(float(np.median(r.peak_width_px[ok] * dz[ok])))
    return float(np.median(values)) if values else 0.0
