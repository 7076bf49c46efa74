"""The headline diameter's sigma where its median lies on a diameter change no taper was
reported for (issue 30: random-features-small seed 23, a 279.6 -> 244.7 mm reducer over
10 mm read by 12 stations whose rings mix both sections), against seeded synthetic truth;
runs whose stations agree keep their sigma."""

from __future__ import annotations

import math

import numpy as np

from omnipipe.analysis.stations import Station, headline, median_move_mm


def _station(axial: float, diameter: float, sigma: float) -> Station:
    return Station(
        axial_mm=axial, diameter_mm=diameter, diameter_sigma_mm=sigma, diameter_min_mm=diameter,
        diameter_max_mm=diameter, ovality=0.0, ovality_sigma=0.001, ovality_angle_deg=0.0,
        ovality_angle_sigma_deg=10.0,
    )


def _old_sigma(d: np.ndarray, shared: float) -> float:
    """The headline's sigma without the median's move (its statistical and shared terms)."""
    resid = d[1:-1] - 0.5 * (d[:-2] + d[2:])
    scatter = 1.4826 * float(np.median(np.abs(resid))) / math.sqrt(1.5)
    return math.hypot(1.2533 * scatter / math.sqrt(len(d)), shared)


def test_median_on_an_unreported_reducer_is_covered() -> None:
    """Seed 23's stations in their run order: 4 before a 10 mm ramp, 3 on it, 5 past it
    (the rings mixing both sections, so the ramp fit could not report it). The median
    reads the ramp between 247 and 250 mm; the truth is the 244.7 mm section the run
    measured most (the bench's rule over the frames' rings) or the median ring (249.2 mm
    over the distinct rings). The sigma without the median's move (0.7 mm) holds neither;
    with it both lie within 3 sigma."""
    rng = np.random.default_rng(23)
    before = 279.6 + rng.normal(0.0, 4.0, 4)
    ramp = np.array([254.0, 250.0, 247.1]) + rng.normal(0.0, 0.5, 3)
    after = 244.67 + rng.normal(0.0, 0.25, 5)
    d = np.concatenate([before, ramp, after])
    stations = [_station(float(i), float(x), 0.3) for i, x in enumerate(d)]
    head = headline(stations, 0.65)
    old = _old_sigma(d, 0.65)
    assert math.isclose(head.diameter_mm, float(np.median(d)))
    assert abs(head.diameter_mm - 244.67) > 3.0 * old
    for truth in (244.67, 249.2):
        assert abs(head.diameter_mm - truth) <= 3.0 * head.sigma_mm, (truth, head)
    assert math.isclose(head.sigma_mm, math.hypot(old, head.move_sigma_mm), rel_tol=1e-9)
    # The move: one station more on either side moves the median to a neighbour.
    srt = np.sort(d)
    assert math.isclose(median_move_mm(d), (srt[7] + srt[6] - srt[5] - srt[4]) / 4.0)


def test_agreeing_stations_keep_their_sigma() -> None:
    """A plain run (40 stations, 0.3 mm noise), one with a joint's 3 of 10 stations read
    9 mm wide (the median is robust to them), and a slow 0.5 mm deformation along 60
    stations: the stations beside the median agree within the sigma, which stays as it
    was, to the last bit."""
    rng = np.random.default_rng(5)
    runs = [
        300.0 + rng.normal(0.0, 0.3, 40),
        np.concatenate([533.0 + rng.normal(0.0, 1.0, 7), 542.0 + rng.normal(0.0, 1.0, 3)]),
        250.0 + 0.5 * np.sin(np.linspace(0.0, 3.0, 60)) + rng.normal(0.0, 0.1, 60),
    ]
    for d in runs:
        head = headline([_station(float(i), float(x), 0.3) for i, x in enumerate(d)], 0.2)
        assert head.move_sigma_mm == 0.0
        assert head.sigma_mm == _old_sigma(d, 0.2)


def test_median_move_of_few_values() -> None:
    """Odd and even counts from the order statistics beside the median; 0 for one value."""
    assert median_move_mm(np.array([5.0])) == 0.0
    assert median_move_mm(np.array([1.0, 3.0])) == 1.0
    assert median_move_mm(np.array([9.0, 1.0, 4.0])) == 4.0
    assert median_move_mm(np.array([0.0, 1.0, 3.0, 10.0])) == (10.0 + 3.0 - 1.0 - 0.0) / 4.0
