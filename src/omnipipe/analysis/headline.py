"""The run's headline numbers and the uncertainty terms the stations share.

The inner diameter (:func:`sections_and_headline`: the stations' mean diameter, on a
reducer that of the section most stations measured) and the section features (taper,
bend, ovality, water) with the terms averaging the stations cannot remove: radial errors
shared by whole rings, the rig calibration and the laser peaks' sub-pixel bias
(:func:`with_ring_terms`), the rings' tilt to the pipe (:func:`tilt_corrected`), the
sections each ring mixes; and the run's standing water (:func:`run_water`). Lengths mm,
ovality a fraction of the diameter, all sigmas 1-sigma.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from omnipipe.analysis.centreline import Centreline
from omnipipe.analysis.feature_types import Ovality, Stretch, Taper
from omnipipe.analysis.footprint import with_footprint_terms
from omnipipe.analysis.records import AnalysisConfig, AnalysisInputs
from omnipipe.analysis.ring_spans import RingGroups
from omnipipe.analysis.ring_tilt import (
    ovality_beyond_tilt,
    ring_tilts,
    tilt_check,
    with_tangent_sigma,
    with_tilt,
)
from omnipipe.analysis.sections import section_features, significant_ovality
from omnipipe.analysis.station_profiles import StationProfiles, station_list
from omnipipe.analysis.stations import (
    Headline,
    SectionConfig,
    Station,
    headline,
    headline_of_a_section,
    ovality_scatter,
    with_deformation,
)


def sections_and_headline(
    st_list: list[Station],
    line: Centreline,
    sec_config: SectionConfig,
    radial_sys: float,
    shared: float,
    mixing: tuple[np.ndarray, np.ndarray],
    tilt_direction_rad: np.ndarray | None = None,
    footprint_mm: np.ndarray | None = None,
) -> tuple[list[Station], list[Stretch], Headline, list[str]]:
    """The stations with their deformation and shared terms, the section features
    (taper, bend, ovality, water), the headline diameter (the stations' mean diameter,
    or on a reducer the section most stations measured, not the ramp) and warnings: an
    ovality stretch its rings' tilt could make up (``tilt_direction_rad`` (S,), the
    stations' rings' tilt directions: :func:`.ring_tilt.ovality_beyond_tilt`) is not
    reported; nor one within :data:`~omnipipe.analysis.sections.OVALITY_MIN_SIGMAS` of
    none (``footprint_mm`` (S,), half each station's ring's axial extent: stations whose
    rings overlap count once in a stretch's sigma)."""
    head = headline(st_list, shared)
    st_list = with_deformation(st_list, head)
    st_list, features = _with_shared_terms(st_list, line, head, sec_config, radial_sys, shared, mixing, footprint_mm)
    warnings: list[str] = []
    if tilt_direction_rad is not None:
        features, warnings = ovality_beyond_tilt(features, st_list, tilt_direction_rad, sec_config.ovality_feature_pct)
    features, weak = significant_ovality(features)
    warnings += weak
    tapers = [f for f in features if isinstance(f, Taper)]
    if tapers:
        t = tapers[0]
        head = headline_of_a_section(
            head, st_list, (t.axial_from_mm, t.axial_to_mm), (t.diameter_from_mm, t.diameter_to_mm), shared
        )
        st_list = with_deformation(st_list, head)
    return st_list, features, head, warnings


def with_ring_terms(
    config: AnalysisConfig,
    inputs: AnalysisInputs,
    frame: np.ndarray,
    k: int,
    stations: StationProfiles,
    radial_sys: float,
    diameter: float,
) -> tuple[list[Station], float]:
    """The stations with the terms whole rings share in their diameter sigmas (radial
    systematics, calibration, the peaks' sub-pixel bias), and the run's shared term (mm)
    for the headline."""
    cal = float(inputs.calibration_sigma_rel)
    peak_mm = _peak_bias_mm(config, inputs, frame, k)
    run_peak = float(np.median(peak_mm)) if len(peak_mm) else 0.0
    shared = math.hypot(2.0 * radial_sys, cal * float(diameter), 2.0 * run_peak)
    st_list = [
        replace(
            st,
            diameter_sigma_mm=math.hypot(st.diameter_sigma_mm, 2.0 * radial_sys, cal * st.diameter_mm, 2.0 * pk),
        )
        for st, pk in zip(station_list(stations), _or_zeros(peak_mm, len(stations.axial)), strict=True)
    ]
    return st_list, shared


def tilt_corrected(
    st_list: list[Station],
    shared: float,
    line: Centreline,
    pts: np.ndarray,
    frame: np.ndarray,
    measured: np.ndarray,
    radial_sys: float,
) -> tuple[list[Station], float, np.ndarray | None]:
    """The stations and the headline's shared term (mm) after :func:`.ring_tilt.tilt_check`:
    rings square to the pipe under a centreline drawn off it measured in their own
    plane; an undecided tilt's ambiguity added to the shared term; each station's
    ovality sigma with the centreline direction's uncertainty through its ring's tilt
    (:func:`.ring_tilt.with_tangent_sigma`); and (S,) the rings' tilt directions (rad;
    None when the rings do not match the stations)."""
    rings = np.flatnonzero(measured)
    if len(rings) != len(st_list) or not len(rings):
        return st_list, shared, None
    tilt, direction = ring_tilts(
        pts, RingGroups(frame, rings), line.tangent[rings], line.normal[rings], line.binormal[rings]
    )
    d = np.array([st.diameter_mm for st in st_list])
    check = tilt_check(st_list, tilt, direction, 4.0 * radial_sys / max(float(np.median(d)), 1e-9))
    st_list = with_tangent_sigma(with_tilt(st_list, check), check.tilt_rad)
    return st_list, math.hypot(shared, check.ambiguity_mm(d)), direction


def _peak_bias_mm(config: AnalysisConfig, inputs: AnalysisInputs, frame: np.ndarray, k: int) -> np.ndarray:
    """(S,) each measured station's radius error (mm) from the peaks' shared sub-pixel
    bias (``config.systematic_peak_px`` x its ring's radial pixel scale; a ring of unknown
    scale takes the run's median), in the order of the stations with enough points
    (:func:`.station_profiles.station_profiles`); empty when the inputs state no scale."""
    scale = np.asarray(inputs.radial_mm_per_px, float)
    if len(scale) != k or not np.isfinite(scale).any():
        return np.zeros(0)
    scale = np.where(np.isfinite(scale), scale, float(np.nanmedian(scale)))
    measured = np.bincount(frame, minlength=k)[:k] >= 12
    return config.systematic_peak_px * scale[measured]


def _or_zeros(x: np.ndarray, n: int) -> np.ndarray:
    return x if len(x) == n else np.zeros(n)


def _with_shared_terms(
    st_list: list[Station],
    line: Centreline,
    head: Headline,
    sec_config: SectionConfig,
    radial_sys: float,
    shared_diameter_mm: float,
    mixing: tuple[np.ndarray, np.ndarray],
    footprint_mm: np.ndarray | None = None,
) -> tuple[list[Station], list[Stretch]]:
    """The stations and section features (ovality, tapers, ...) with the terms averaging
    the stations cannot remove: a ring-shape error shared by the run (``radial_sys`` mm
    in cos 2 theta) moves every station's ovality alike, by up to 4 radial_sys / D; the
    rings' shapes scatter from station to station by more than their fits say
    (:func:`.stations.ovality_scatter`, added to each station's ovality sigma); the
    diameter's shared part (``shared_diameter_mm``: the systematic ring radius, the
    peaks' sub-pixel bias, the rig calibration; as in the headline's sigma) moves both
    ends of a taper with every station, as it moves the headline; the sections each ring
    mixes (``mixing``: :func:`.footprint.footprint_terms`, (S,) diameter mm and ovality
    per station) move neighbouring stations alike, so a taper end or an ovality stretch
    takes its stations' median of them whole. The features are found on the stations
    without the mixing terms (a taper's own ramp is no noise), which are then added."""
    oval_sys = 4.0 * radial_sys / max(head.diameter_mm, 1e-9)
    scatter = ovality_scatter(st_list)  # the ring shapes' own scatter, each station's alone
    st_list = [replace(st, ovality_sigma=math.hypot(st.ovality_sigma, oval_sys, scatter)) for st in st_list]
    axial = np.array([st.axial_mm for st in st_list])
    d_mix, o_mix = mixing

    def median_over(term: np.ndarray, sel: np.ndarray) -> float:
        return float(np.median(term[sel])) if sel.any() else 0.0

    features: list[Stretch] = []
    for f in section_features(st_list, line, head, sec_config, d_mix, footprint_mm):
        if isinstance(f, Ovality) and f.percent_sigma is not None:
            inside = (axial >= f.axial_from_mm) & (axial <= f.axial_to_mm)
            mix = 100.0 * median_over(o_mix, inside)
            f = replace(f, percent_sigma=math.hypot(f.percent_sigma, 100.0 * oval_sys, mix))
        elif isinstance(f, Taper):
            start, end = median_over(d_mix, axial <= f.axial_from_mm), median_over(d_mix, axial >= f.axial_to_mm)
            f = replace(
                f,
                diameter_from_sigma_mm=_hypot_or_none(f.diameter_from_sigma_mm, shared_diameter_mm, start),
                diameter_to_sigma_mm=_hypot_or_none(f.diameter_to_sigma_mm, shared_diameter_mm, end),
            )
        features.append(f)
    return with_footprint_terms(st_list, d_mix, o_mix), features


def _hypot_or_none(sigma: float | None, *terms: float) -> float | None:
    return None if sigma is None else math.hypot(sigma, *terms)


def run_water(stations: list[Station]) -> tuple[float, float]:
    """Median water depth over the wet stations and its 1-sigma (mm): the independent
    part / sqrt(n), the part all stations share whole."""
    wet = [s for s in stations if s.water_depth_mm > 0]
    depth = np.array([s.water_depth_mm for s in wet])
    shared = float(np.median([s.water_depth_shared_sigma_mm for s in wet]))
    sig = np.sqrt(np.maximum(np.array([s.water_depth_sigma_mm for s in wet]) ** 2 - shared**2, 0.0))
    spread = float(np.std(depth)) if len(depth) > 2 else 0.0
    stat = 1.2533 * max(spread, float(np.median(sig))) / math.sqrt(len(depth))
    return float(np.median(depth)), math.hypot(stat, shared)
