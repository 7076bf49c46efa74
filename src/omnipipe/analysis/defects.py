"""Bulges and dents from the radial deviation map (the paper's future work, Sec. VIII).

The deviation of a wall point is its distance from the axis minus the fitted wall
radius at its station and angle: negative for a bulge (into the pipe), positive
for a dent. The fitted wall is each station's own section (:mod:`.stations`: an ellipse
per ring, on the wall above any standing water, about the ring's own centre), so an
oval, tapering or bending pipe is the reference, never a defect; :class:`.wall_profile.WallSamples`
carries those deviations. Candidates are connected groups of points whose deviation exceeds a
threshold (``min_height_mm`` and a multiple of the measured noise) with a neighbour on
their ring at least half as far out (lone samples are extraction outliers), linked
across neighbouring rings and around the pipe's seam.

Each candidate is first measured roughly from its samples beyond the threshold
(largest deviation, extent, weighted centre); that is only the starting point of the
model fit of :mod:`.sizing` (a raised-cosine plateau bump in arc length and axial
position, least squares over the defect and the wall around it), which gives the
reported height, width, length, axial start and angle and their standard
uncertainties. A fitted defect lower than the run's detection limit
(:func:`.sizing.detection_limit`) is not reported. Each is a
:class:`~omnipipe.contract.Defect`.

The parts: the wall samples (:mod:`.wall_profile`), the candidates (:mod:`.defect_search`),
the edge of the measured wall (:mod:`.defect_truncation`), each candidate's fit
(:mod:`.defect_fit`) and which fits are reported (:mod:`.defect_accept`); here the search
itself (:func:`find_defects`).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass

import numpy as np

from omnipipe.analysis.defect_accept import merge_overlapping, reported, unfitted_warnings
from omnipipe.analysis.defect_fit import rough_measure
from omnipipe.analysis.defect_search import FeatureZone, clusters, scales
from omnipipe.analysis.defect_truncation import one_sided
from omnipipe.analysis.sizing import detection_limit
from omnipipe.analysis.wall_profile import WallSamples, with_axial_order
from omnipipe.contract import Defect


@dataclass
class DefectSearch:
    """What :func:`find_defects` found.

    Attributes:
        defects: largest first, each with its 1-sigma uncertainties, ``points`` (samples
            beyond the threshold) and ``travel_mm`` (the robot's travel from the first
            frame to the rings at the defect's start). The axial sigmas hold the fit and
            the ring sampling only (not the camera motion's scale).
        warnings: one line per rejected candidate.
        noise_mm: robust sigma of the deviation map.
        threshold_mm: sample threshold of the detector.
        detection_limit_mm: smallest height of the reference defect detected with >= 95 %
            probability (:func:`.sizing.detection_limit`); no reported defect is lower.
        ring_spacing_mm: median axial distance between consecutive rings.
        sample_spacing_mm: median arc length between samples along a ring.
        masks: per reported defect, the ascending indices of the samples its fitted bump
            covers (model above 1 % of its height), for refitting the wall without it.
    """

    defects: list[Defect]
    warnings: list[str]
    noise_mm: float = float("nan")
    threshold_mm: float = float("nan")
    detection_limit_mm: float = float("nan")
    ring_spacing_mm: float = float("nan")
    sample_spacing_mm: float = float("nan")
    masks: list[np.ndarray] | None = None

    def __iter__(self) -> Iterator[list[Defect] | list[str]]:
        """(defects, warnings) = find_defects(...) keeps working."""
        return iter((self.defects, self.warnings))


def find_defects(
    samples: WallSamples,
    *,
    min_height_mm: float,
    noise_factor: float,
    min_points: int,
    grid_mm: float,
    max_width_fraction: float = 0.5,
    limit_width_mm: float = 10.0,
    limit_length_mm: float = 20.0,
    ring_blur_mm: float = 0.0,
    axial_blur_mm: float = 0.0,
    zones: Sequence[FeatureZone] = (),
    executor: Executor | None = None,
) -> DefectSearch:
    """Detect and measure bulges and dents (the candidates' model fits on ``executor``,
    :mod:`omnipipe.executor`; None: here; the result is the same).

    Args:
        samples: the wall points.
        min_height_mm: smallest deviation reported as a defect.
        noise_factor: the threshold is also at least this many robust noise sigmas.
        min_points: a candidate needs this many points beyond the threshold.
        grid_mm: kept for the configuration's sake (the rough measurement that the model
            fit starts from no longer uses a grid).
        max_width_fraction: candidates wider than this fraction of the circumference are
            a shape change (ovality, a fit problem), not a local defect: reported as warnings.
        limit_width_mm, limit_length_mm: the reference defect of the detection limit.
        ring_blur_mm: the light section's Gaussian smoothing along the ring (mm), fitted
            with each defect (:func:`omnipipe.analysis.sizing.seen_bump_model`).
        axial_blur_mm: the same along the pipe axis (mm).
        zones: the found features' reach (:class:`.defect_search.FeatureZone`): a candidate seen by one
            ring inside one is a warning, not a defect (:func:`.defect_truncation.one_sided`), as is one seen
            by one ring at the edge of the measured wall.
    """
    warnings: list[str] = []
    if len(samples.deviation_mm) < 10:
        return DefectSearch([], warnings, masks=[])
    samples = with_axial_order(samples)
    sc = scales(samples, min_height_mm, noise_factor)
    limit = detection_limit(
        noise_mm=sc.noise,
        threshold_mm=sc.threshold,
        sample_spacing_mm=sc.sample_spacing,
        ring_spacing_mm=sc.typical_spacing,
        min_points=min_points,
        width_mm=limit_width_mm,
        length_mm=limit_length_mm,
    )
    candidates = [
        (sign, kind, members, rough_measure(samples, members, sign, kind, sc.sample_spacing, sc.typical_spacing))
        for sign, kind in ((-1.0, "bulge"), (1.0, "dent"))
        for members in clusters(samples, sc, sign, min_points)
        if not one_sided(samples, sc, members, kind, zones, warnings)
    ]
    # The light section resolves nothing narrower than its blur's full width at half height.
    limits = (max_width_fraction * samples.circumference_mm, limit, 2.355 * ring_blur_mm)
    defects, masks = reported(samples, sc, candidates, limits, (ring_blur_mm, axial_blur_mm), executor, warnings)
    defects, masks = merge_overlapping(defects, masks, samples.circumference_mm)
    warnings.extend(unfitted_warnings(defects))
    order_h = np.argsort([-d.height_mm for d in defects], kind="stable")
    return DefectSearch(
        [defects[i] for i in order_h],
        warnings,
        noise_mm=sc.noise,
        threshold_mm=sc.threshold,
        detection_limit_mm=limit,
        ring_spacing_mm=sc.typical_spacing,
        sample_spacing_mm=sc.sample_spacing,
        masks=[masks[i] for i in order_h],
    )
