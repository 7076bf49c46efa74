"""A ring's axial footprint and what a section change within it does to its station.

A laser ring is not a cross-section normal to the pipe's axis: its points spread along
the centreline over an axial footprint (the ring plane tilted against the axis: the rig
in a bend, riding a taper's cone; the wall's relief). Where the diameter changes within
that footprint (a taper's ends, a joint, an elbow seen by a tilted ring), the ring mixes
sections, and no fit of the ring alone can see it:

* its mean diameter lies anywhere between the sections it mixes: with the change Delta D
  across the footprint and the split uniform around the ring, the error is uniform in
  +-Delta D / 2, 1-sigma Delta D / sqrt(12);
* its ovality gains the second harmonic of that split: a radius step Delta D / 2 over an
  arc theta0 of the ring has cos 2 theta amplitude (Delta D / 2) |sin 2 theta0| / pi, so
  (Dmax - Dmin) / D = 2 Delta D |sin 2 theta0| / (pi D); over a uniform split its rms
  is sqrt(2) Delta D / (pi D).

* its water depth (below the chord across its cut, against the section it fitted)
  belongs to no one section either, and is compared with the water at the station's
  own position, which is one of them: with the depth's change Delta h across the
  footprint, the error is uniform in [0, Delta h], rms Delta h / sqrt(3). A ring that
  crosses a joint or a reducer's end reads the deeper or the shallower section's water
  wherever its station is placed along the axis.

Delta D (and Delta h) is read off the stations' own mean diameters (depths) along the centreline: twice their
largest departure, within each ring's footprint, from the chord across it (a step gives
its height; a linear ramp, which a tilted ring sees as a first harmonic only, nothing);
on straight, even pipe it is the stations' noise and the terms stay small.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from omnipipe.analysis.stations import Station
from omnipipe.errors import ShapeError


def footprint_mm(sigma: np.ndarray, groups: list[np.ndarray], measured: np.ndarray) -> np.ndarray:
    """(S,) half the axial extent (mm) of each measured ring's points: half the 5-95th
    percentile range of their axial positions ``sigma`` (N,), for the rings ``measured``
    (K,) bool among ``groups`` (K index arrays)."""
    out = []
    for k in np.flatnonzero(measured):
        s = sigma[groups[k]]
        out.append(0.5 * float(np.percentile(s, 95) - np.percentile(s, 5)) if len(s) else 0.0)
    return np.array(out)


def section_change_mm(axial: np.ndarray, diameter: np.ndarray, half_extent: np.ndarray) -> np.ndarray:
    """(S,) Delta D (mm): twice the largest departure of the stations' mean diameters
    ``diameter`` (S,) at ``axial`` (S,) from the chord across each station's
    +-``half_extent`` (S,) (linear between stations, constant beyond the first and last)."""
    order = np.argsort(axial, kind="stable")
    za, dd = axial[order], diameter[order]
    out = np.zeros(len(axial))
    for i, (z, h) in enumerate(zip(axial, half_extent, strict=True)):
        if h <= 0:
            continue
        grid = np.sort(np.concatenate([np.linspace(z - h, z + h, 9), za[(za > z - h) & (za < z + h)]]))
        prof = np.interp(grid, za, dd)
        chord = prof[0] + (prof[-1] - prof[0]) * (grid - grid[0]) / (grid[-1] - grid[0])
        out[i] = 2.0 * float(np.max(np.abs(prof - chord)))
    return out


def independent_count(axial: np.ndarray, half_extent: np.ndarray) -> int:
    """How many of the stations at ``axial`` (mm) read walls of their own: walking along
    the axis, a station counts when its ring's footprint (+-``half_extent`` mm) clears
    that of the last station counted (at least 1). Stations whose footprints overlap
    read the same wall, and what the pipe's shape there does to their ovality (the
    sections a ring mixes, its tilt) they share: they do not average it out."""
    order = np.argsort(axial, kind="stable")
    z, h = np.asarray(axial, float)[order], np.asarray(half_extent, float)[order]
    count, last = min(len(z), 1), 0
    for i in range(1, len(z)):
        if z[i] - z[last] >= h[i] + h[last]:
            count, last = count + 1, i
    return count


def footprint_terms(stations: list[Station], half_extent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(S,) 1-sigma of each station's mean diameter (mm) and of its ovality (fraction)
    from the sections its ring mixes: Delta D / sqrt(12) and sqrt(2) Delta D / (pi D)
    (:func:`section_change_mm`); zeros when they cannot be told (fewer than 2 stations)."""
    n = len(stations)
    if n < 2 or len(half_extent) != n:
        return np.zeros(n), np.zeros(n)
    axial = np.array([s.axial_mm for s in stations])
    diameter = np.array([s.diameter_mm for s in stations])
    change = section_change_mm(axial, diameter, half_extent)
    return change / math.sqrt(12.0), math.sqrt(2.0) * change / (math.pi * np.maximum(diameter, 1e-9))


def with_footprint_terms(stations: list[Station], d_term: np.ndarray, o_term: np.ndarray) -> list[Station]:
    """The stations with :func:`footprint_terms` in their diameter and ovality sigmas."""
    return [
        replace(
            st,
            diameter_sigma_mm=math.hypot(st.diameter_sigma_mm, float(d)),
            ovality_sigma=math.hypot(st.ovality_sigma, float(o)) if math.isfinite(st.ovality_sigma) else st.ovality_sigma,
        )
        for st, d, o in zip(stations, d_term, o_term, strict=True)
    ]


def water_footprint_terms(stations: list[Station], half_extent: np.ndarray) -> np.ndarray:
    """(S,) 1-sigma (mm) of each wet station's water depth from the sections its ring
    mixes: Delta h / sqrt(3), Delta h the water depths' :func:`section_change_mm` over
    the wet stations (depth > 0) within its footprint (``half_extent`` (S,) mm); 0 for
    dry stations and when it cannot be told (fewer than 2 wet stations). A
    ``half_extent`` of another length is a ShapeError (zeros would drop the term silently)."""
    n = len(stations)
    if len(half_extent) != n:
        raise ShapeError(f"half_extent: {len(half_extent)} values for {n} stations")
    out = np.zeros(n)
    depth = np.array([s.water_depth_mm for s in stations], float)
    wet = depth > 0
    if wet.sum() < 2:
        return out
    axial = np.array([s.axial_mm for s in stations], float)
    out[wet] = section_change_mm(axial[wet], depth[wet], np.asarray(half_extent, float)[wet]) / math.sqrt(3.0)
    return out


def with_water_footprint(stations: list[Station], term: np.ndarray) -> list[Station]:
    """The stations with :func:`water_footprint_terms` in their water depth's sigma (and
    kept apart in ``water_depth_footprint_sigma_mm``)."""
    return [
        replace(
            st,
            water_depth_sigma_mm=math.hypot(st.water_depth_sigma_mm, float(t)),
            water_depth_footprint_sigma_mm=float(t),
        )
        if st.water_depth_mm > 0 and t > 0
        else st
        for st, t in zip(stations, term, strict=True)
    ]
