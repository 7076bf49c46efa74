"""A ring's axial footprint and the sections it mixes (analysis.footprint)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnipipe.analysis.footprint import (
    footprint_mm,
    footprint_terms,
    section_change_mm,
    water_footprint_terms,
    with_footprint_terms,
    with_water_footprint,
)
from omnipipe.analysis.stations import Station
from omnipipe.errors import ShapeError


def _stations(axial: np.ndarray, diameter: np.ndarray) -> list[Station]:
    return [Station(float(a), float(d), 0.1, float(d), float(d), 0.01, 0.001, 0.0, 1.0) for a, d in zip(axial, diameter, strict=True)]


def test_a_step_within_the_footprint_counts_whole_a_ramp_not_at_all() -> None:
    """Stations every 5 mm: a 4 mm diameter step at 50 mm is Delta D = 4 mm for rings
    whose footprint (+-8 mm) straddles it, 0 for those far from it; a linear ramp
    (which a tilted ring sees as a first harmonic only) gives 0 inside it, and its kinks
    count where a footprint reaches them."""
    axial = np.arange(0.0, 100.0, 5.0)
    step = np.where(axial < 50, 300.0, 296.0)
    change = section_change_mm(axial, step, np.full(len(axial), 8.0))
    near = np.abs(axial - 47.5) <= 8.0
    assert np.all(change[~near] == 0.0)
    assert change[near].max() == pytest.approx(4.0, rel=0.05)
    ramp = 300.0 - 0.2 * np.clip(axial - 20, 0, 60)
    change = section_change_mm(axial, ramp, np.full(len(axial), 8.0))
    inside = (axial >= 30) & (axial <= 70)
    assert np.all(change[inside] < 1e-9)
    assert change[axial == 20].item() == pytest.approx(2 * 0.2 * 8 / 2, rel=0.05)  # half the footprint on the ramp


def test_terms_are_the_uniform_split_of_the_change() -> None:
    """Delta D / sqrt(12) on the diameter, sqrt(2) Delta D / (pi D) on the ovality; added
    in quadrature to the stations' sigmas (a station without ovality keeps NaN)."""
    axial = np.arange(0.0, 100.0, 5.0)
    diameter = np.where(axial < 50, 300.0, 294.0)
    sts = _stations(axial, diameter)
    d_term, o_term = footprint_terms(sts, np.full(len(axial), 8.0))
    k = int(np.argmax(d_term))
    assert d_term[k] == pytest.approx(6.0 / math.sqrt(12.0), rel=0.05)
    assert o_term[k] == pytest.approx(math.sqrt(2.0) * 6.0 / (math.pi * diameter[k]), rel=0.05)
    sts[0] = Station(0.0, 300.0, 0.1, 300.0, 300.0, math.nan, math.nan, math.nan, math.nan)
    out = with_footprint_terms(sts, d_term, o_term)
    assert out[k].diameter_sigma_mm == pytest.approx(math.hypot(0.1, d_term[k]))
    assert out[k].ovality_sigma == pytest.approx(math.hypot(0.001, o_term[k]))
    assert math.isnan(out[0].ovality_sigma)
    assert footprint_terms(sts[:1], np.ones(1))[0].tolist() == [0.0]


def test_footprint_is_half_the_rings_axial_spread() -> None:
    """A ring tilted by 10 degrees in a 300 mm pipe spans +-150 tan 10 deg along the axis."""
    theta = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    sigma = np.concatenate([150 * math.tan(math.radians(10)) * np.cos(theta), np.zeros(720)])
    groups = [np.arange(720), np.arange(720, 1440), np.zeros(0, int)]
    fp = footprint_mm(sigma, groups, np.array([True, True, False]))
    assert fp[0] == pytest.approx(150 * math.tan(math.radians(10)) * math.cos(math.radians(9)), rel=0.02)  # 5-95 %: cos 9 deg
    assert fp[1] == 0.0 and len(fp) == 2


def test_a_wet_rings_depth_sigma_holds_the_depth_change_across_its_footprint() -> None:
    """A ring across a reducer's end (random-features seed 3: stations placed ~12 mm
    upstream of the sections they read) measures a depth that belongs to no one section:
    stations every 2 mm whose depth steps 40 -> 55 mm at 50 mm, footprints +-6 mm, each
    measured as the section 6 mm upstream. The depth term is Delta h / sqrt(3) where the
    footprint straddles the step (Delta h the chord's largest departure, twice: up to
    2 x 15 mm where the step sits at the footprint's end; 0 elsewhere and on dry
    stations); the station keeps it
    apart; a stretch over the step holds the median whole, so a station's error of up to
    Delta h stays within 3 sigma of its stretch; the depth-step test ignores it."""
    from dataclasses import replace

    from omnipipe.analysis.sections import SectionConfig, _water_stretches

    axial = np.arange(0.0, 100.0, 2.0)
    true = np.where(axial < 50, 40.0, 55.0)
    measured = np.where(axial - 6.0 < 50, 40.0, 55.0)
    sts = [
        replace(s, water_depth_mm=float(h), water_depth_sigma_mm=1.0)
        for s, h in zip(_stations(axial, np.full(len(axial), 300.0)), measured, strict=True)
    ]
    sts[-1] = replace(sts[-1], water_depth_mm=0.0, water_depth_sigma_mm=3.0)  # dry: untouched
    term = water_footprint_terms(sts, np.full(len(axial), 6.0))
    near = np.abs(axial - 55.0) <= 8.0
    assert term[-1] == 0.0 and np.all(term[~near] == 0.0)
    assert 15.0 / math.sqrt(3.0) <= term[near].max() <= 30.0 / math.sqrt(3.0)
    out = with_water_footprint(sts, term)
    assert out[-1] == sts[-1]
    k = int(np.argmax(term))
    assert out[k].water_depth_sigma_mm == pytest.approx(math.hypot(1.0, term[k]))
    with pytest.raises(ShapeError, match="half_extent: 49 values for 50 stations"):
        water_footprint_terms(sts, np.full(len(axial) - 1, 6.0))  # never a silent 0
    assert out[k].water_depth_footprint_sigma_mm == pytest.approx(term[k])
    # The stations between the true step and the placed one (50 <= axial < 56) read the
    # upstream depth: within 3 of their own sigmas.
    wrong = (axial >= 50) & (axial < 56)
    assert np.all(np.abs(measured - true)[wrong] <= 3.0 * np.array([s.water_depth_sigma_mm for s in out])[wrong])
    cfg = SectionConfig()
    three = _water_stretches(out[44:48], cfg)  # 88-94 mm: no term
    assert len(three) == 1 and three[0].depth_sigma_mm == pytest.approx(1.0 / math.sqrt(4.0))
    over = _water_stretches(out[26:29], cfg)  # 52-56 mm: on the step
    assert over[0].depth_sigma_mm >= float(np.median(term[26:29]))
