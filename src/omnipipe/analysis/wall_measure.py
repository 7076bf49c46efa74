"""The wall's measurement: the stations' wall profiles and the defects found in the
deviations from them, refitted without the defects' samples (:func:`measure_wall`), and
the terms the defect fits cannot see added to their sigmas (:func:`with_systematics`,
:func:`blur_height_sigma`). Lengths mm, angles rad.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import replace

import numpy as np

from omnipipe.analysis.defect_search import FeatureZone
from omnipipe.analysis.defects import DefectSearch, find_defects
from omnipipe.analysis.records import AnalysisConfig, AnalysisInputs
from omnipipe.analysis.station_profiles import StationProfiles, ring_groups, station_profiles
from omnipipe.analysis.wall_profile import WallSamples
from omnipipe.contract import Defect
from omnipipe.progress import phase
from omnipipe.spill import compressed_on_disk, drop_pages


def measure_wall(
    config: AnalysisConfig,
    inputs: AnalysisInputs,
    frame: np.ndarray,
    poses: np.ndarray,
    sigma: np.ndarray,
    rho: np.ndarray,
    theta: np.ndarray,
    radius: float,
    not_wall: np.ndarray,
    executor: Executor | None = None,
    zones: Sequence[FeatureZone] = (),
    stray: np.ndarray | None = None,
) -> tuple[StationProfiles, DefectSearch]:
    """The stations' wall profiles and the defects in the deviations from them.

    Pass 1 fits the profiles to all points; pass 2 without the samples of the defects
    found (so a wide defect does not pull its ring's wall profile), and so on until the
    excluded samples stop changing (at most two passes).
    """
    ok_station = np.bincount(frame, minlength=len(poses))[: len(poses)] >= 12
    circ = 2 * np.pi * radius
    exclude = not_wall.copy()
    # The robot's travel from the first frame to each ring's frame (path along the poses).
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    travel = np.concatenate([[0.0], np.cumsum(steps)])
    tick = phase("defects", 2)
    for done in range(1, 3):
        # Each ring's indices made per pass: not held under the defect search (8 bytes a point).
        groups = ring_groups(frame, len(poses))
        stations = station_profiles(
            config, groups, theta, rho, sigma, ok_station, exclude, zones, radius, stray, executor
        )
        del groups
        ok = np.isfinite(stations.deviation) & ~not_wall
        # In the run's scratch, gathered a block at a time (read when needed; a local
        # pool's workers share the files).
        samples = WallSamples(
            sigma_mm=compressed_on_disk(sigma, ok),
            arc_mm=compressed_on_disk(theta, ok, lambda t: _arcs(t, radius)),
            deviation_mm=compressed_on_disk(stations.deviation, ok),
            ring=compressed_on_disk(frame, ok),
            circumference_mm=circ,
            ring_travel_mm=travel,
        )
        search = find_defects(
            samples,
            min_height_mm=config.min_height_mm,
            noise_factor=config.noise_factor,
            min_points=config.min_points,
            grid_mm=config.grid_mm,
            limit_width_mm=config.limit_width_mm,
            limit_length_mm=config.limit_length_mm,
            ring_blur_mm=inputs.ring_blur_mm,
            axial_blur_mm=inputs.axial_blur_mm,
            zones=zones,
            executor=executor,
        )
        del samples  # the next pass' samples are built without these
        drop_pages()  # their copies the workers read
        tick(done)
        if not search.defects:
            break
        cover = np.zeros(int(ok.sum()), bool)
        for m in search.masks or []:
            cover[m] = True
        new_exclude = not_wall.copy()
        new_exclude[np.flatnonzero(ok)[cover]] = True
        if np.array_equal(new_exclude, exclude):
            break
        exclude = new_exclude
        if done < 2:  # the next pass' profiles replace these: not held both at once
            del stations, search, cover, new_exclude
    tick(2)
    return stations, search


def _arcs(theta: np.ndarray, radius: float) -> np.ndarray:
    """``theta`` (rad) made arcs in place: (theta % 2 pi) x ``radius`` (mm)."""
    np.remainder(theta, 2 * np.pi, out=theta)
    theta *= radius
    return theta


def blur_height_sigma(height: float, width: float, length: float, blur: tuple[float, float], rel: float) -> float:
    """1-sigma of a defect's height from a relative error ``rel`` of the light section's
    blur (Gaussian sigmas mm along the ring and the axis) its fit modelled.

    The fit keeps the blurred bump's area: taking the bump as a Gaussian of variance
    s^2 = (W / 2.355)^2 (W its fitted half-height extent), seen with variance s^2 + b^2,
    a relative error r of b moves the height by h (b / s)^2 r (per direction, in
    quadrature). Wide defects: nil. The quick demo's 5 mm wide bulge under a 1.2 mm blur:
    0.32 h r; refitted with the blur x 1.25 its height rose 0.94 mm (4.71 -> 5.65), so
    this is, if anything, low."""
    out = 0.0
    for extent, b in ((width, blur[0]), (length, blur[1])):
        if b > 0 and extent > 0:
            out = math.hypot(out, height * (2.355 * b / extent) ** 2 * rel)
    return out


def with_systematics(
    config: AnalysisConfig, search: DefectSearch, cal: float, blur: tuple[float, float] = (0.0, 0.0)
) -> list[Defect]:
    """The found defects with the terms their fit cannot see added to height and width:
    the blurred ring on the defect's flanks, the blur's own uncertainty
    (:func:`blur_height_sigma`), the ring's lateral resolution and the rig calibration's
    share ``cal`` (relative; the lengths along the pipe get it in
    :func:`.uncertainty.report_fields`, with the motion's scale)."""
    width_res = config.width_resolution_samples * search.sample_spacing_mm
    out = []
    for d in search.defects:
        if d.height_sigma_mm is not None and d.width_sigma_mm is not None:
            d = replace(
                d,
                height_sigma_mm=round(
                    math.hypot(
                        d.height_sigma_mm,
                        config.systematic_height_factor * search.noise_mm,
                        blur_height_sigma(d.height_mm, d.width_mm, d.length_mm, blur, config.blur_sigma_rel),
                    ),
                    4,
                ),
                width_sigma_mm=round(math.hypot(d.width_sigma_mm, width_res), 4),
            )
        if cal > 0 and d.height_sigma_mm is not None and d.width_sigma_mm is not None:
            d = replace(
                d,
                height_sigma_mm=round(math.hypot(d.height_sigma_mm, cal * d.height_mm), 4),
                width_sigma_mm=round(math.hypot(d.width_sigma_mm, cal * d.width_mm), 4),
            )
        out.append(d)
    return out
