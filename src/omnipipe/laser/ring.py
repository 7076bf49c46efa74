"""The laser ring of one frame: what extraction finds and triangulation fills in."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class LaserRing:
    """The laser ring of one frame.

    Attributes:
        pixels: (N, 2) sub-pixel image coordinates (col, row) of accepted samples.
        angle_rad: (N,) angle of each sample's scan line around the principal point.
        confidence: (N,) peak height over the line noise (SNR).
        radius_sigma_px: (N,) 1-sigma radial uncertainty of each peak (px).
        peak_width_px: (N,) Gaussian sigma of each peak along its scan line (px).
        points_in_rig: (N, 3) metric points on the laser plane (mm), set by triangulation.
        sigma_mm: (N,) 1-sigma depth uncertainty of each point (mm).
        scanned: number of scan lines.
        warnings: why samples or the whole frame were rejected.
        centroid_shift_px: (N,) float32 radial move (px, outwards positive) from each
            peak's three-point Gaussian centre (``pixels``) to its clipped-peak centroid
            (:class:`~omnipipe.laser.extract.ExtractionConfig` ``centroid_half_px``; 0 on
            unclipped peaks), or empty: none. Camera motion uses ``pixels`` and
            ``points_in_rig``; the analysis the ring moved by it
            (:func:`~omnipipe.laser.triangulate.centroid_ring`).
        gap_edges: (E, 3) float32, per ring (not per sample): where the lit stripe ends
            at each side of the ring's long gaps (a water line's cut): the last accepted
            scan line, the gap's direction (+1 / -1 in line order) and the stripe's
            half-height point past that line (scan lines, + into the gap;
            :func:`~omnipipe.laser.extract._gap_edges`). The analysis' water depth
            takes its chord ends there (:func:`~omnipipe.laser.extract.station_edge_reach`).
    """

    pixels: np.ndarray
    angle_rad: np.ndarray
    confidence: np.ndarray
    radius_sigma_px: np.ndarray
    peak_width_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    points_in_rig: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    sigma_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    scanned: int = 0
    warnings: list[str] = field(default_factory=list)
    centroid_shift_px: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    gap_edges: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))

    @property
    def fraction(self) -> float:
        """Fraction of scan lines with an accepted sample."""
        return len(self.pixels) / self.scanned if self.scanned else 0.0
