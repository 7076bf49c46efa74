"""Each candidate's measurement: the rough one from its samples beyond the threshold
(:func:`rough_measure`) and the model fit that starts from it (:func:`fit_candidate`, the
raised-cosine plateau bump of :mod:`.sizing` over the window about the candidate,
:func:`_window`), giving the reported :class:`~omnipipe.contract.Defect` with its 1-sigma
uncertainties and its mask (ascending sample indices the fitted bump covers,
:func:`_covered`). Sizes mm, angles degrees; a window reads only its axial slice of the
samples (:func:`.wall_profile.axial_range`).
"""

from __future__ import annotations

import math

import numpy as np

from omnipipe.analysis.sizing import BumpFit, fit_bump, plateau
from omnipipe.analysis.wall_profile import WallSamples, axial_range
from omnipipe.contract import Defect


def fit_candidate_job(
    job: tuple[WallSamples, Defect, float, float, float, float, float],
) -> tuple[Defect, np.ndarray]:
    """:func:`fit_candidate` of one candidate, its arguments as one tuple (for the executor)."""
    return fit_candidate(*job)


def rough_measure(
    s: WallSamples,
    members: np.ndarray,
    sign: float,
    kind: str,
    sample_spacing: float,
    ring_spacing: float,
) -> Defect:
    """Rough extent of a candidate from its samples beyond the threshold: the fit's start."""
    circ = s.circumference_mm
    value = sign * s.deviation_mm[members]
    ref = float(s.arc_mm[members[np.argmax(value)]])
    u = (s.arc_mm[members] - ref + 0.5 * circ) % circ - 0.5 * circ
    z = s.sigma_mm[members]
    w = value / value.sum()
    uc, zc = float(w @ u), float(w @ z)
    width = float(np.ptp(u)) + 2.0 * sample_spacing
    length = float(np.ptp(z)) + ring_spacing
    return Defect(
        kind=kind,
        height_mm=round(float(value.max()), 3),
        width_mm=round(width, 3),
        length_mm=round(length, 3),
        axial_start_mm=round(zc - 0.5 * length, 3),
        angle_deg=round(((ref + uc) % circ) / circ * 360.0, 3),
    )


def _window(
    s: WallSamples, d0: Defect, sample_spacing: float, ring_spacing: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The samples inside the fit's window about the roughly measured defect ``d0``'s
    centre: (M,) their indices (ascending), their arcs (mm, unwrapped) and axial
    positions (mm) about that centre. Only the window's axial slice of the samples is
    read (:func:`.wall_profile.axial_range`): the temporaries are the window's, not the run's."""
    circ = s.circumference_mm
    w0, l0 = max(d0.width_mm, sample_spacing), max(d0.length_mm, 0.5 * ring_spacing)
    zc = d0.axial_start_mm + 0.5 * l0
    hu = min(max(1.5 * w0, 0.5 * w0 + 10.0 * sample_spacing, 6.0), 0.45 * circ)
    hz = max(1.5 * l0, 0.5 * l0 + 3.0 * ring_spacing, 6.0)
    idx = axial_range(s, zc - hz, zc + hz)
    u = (s.arc_mm[idx] - d0.angle_deg / 360.0 * circ + 0.5 * circ) % circ - 0.5 * circ
    z = s.sigma_mm[idx] - zc
    win = (np.abs(u) <= hu) & (np.abs(z) <= hz)
    return idx[win], u[win], z[win]


def unfitted(
    s: WallSamples, d0: Defect, sign: float, sample_spacing: float, ring_spacing: float
) -> tuple[Defect, np.ndarray]:
    """A candidate left unfitted: ``d0`` and its samples in the fit's window above half
    its height (as :func:`fit_candidate` when the fit fails; sample indices, ascending)."""
    idx, _, _ = _window(s, d0, sample_spacing, ring_spacing)
    return d0, idx[sign * s.deviation_mm[idx] > 0.5 * d0.height_mm]


def _covered(s: WallSamples, fit: BumpFit, uc: float, zc: float) -> np.ndarray:
    """Ascending indices of the samples the fitted bump covers (model above 1 % of its
    height; ``uc``, ``zc``: the fit's origin, mm around and along the pipe). A plateau is
    0 beyond half its full width plus half its ramp: only that axial slice is read."""
    circ = s.circumference_mm
    reach = 0.5 * (abs(fit.length) + abs(fit.ramp_z * fit.length)) + 1e-6
    idx = axial_range(s, zc + fit.z0 - reach, zc + fit.z0 + reach)
    u = (s.arc_mm[idx] - uc + 0.5 * circ) % circ - 0.5 * circ
    z = s.sigma_mm[idx] - zc
    cover = (
        plateau(u - fit.u0, fit.width, fit.ramp_u * fit.width)
        * plateau(z - fit.z0, fit.length, fit.ramp_z * fit.length)
    ) > 0.01
    return idx[cover]


def fit_candidate(
    s: WallSamples, d0: Defect, sign: float, sample_spacing: float, ring_spacing: float,
    blur_u_mm: float = 0.0,
    blur_z_mm: float = 0.0,
) -> tuple[Defect, np.ndarray]:
    """Model fit around a roughly measured defect ``d0``: the reported defect and its mask
    (sample indices, ascending; without a usable fit: ``d0``, without uncertainties, and
    its samples above half its height)."""
    circ = s.circumference_mm
    w0, l0 = max(d0.width_mm, sample_spacing), max(d0.length_mm, 0.5 * ring_spacing)
    uc = d0.angle_deg / 360.0 * circ
    zc = d0.axial_start_mm + 0.5 * l0
    idx, u, z = _window(s, d0, sample_spacing, ring_spacing)
    value = sign * s.deviation_mm[idx]
    fit = fit_bump(
        u,
        z,
        value,
        s.ring[idx],
        (d0.height_mm, 0.0, 0.0, w0, l0),
        bounds_u=(-0.5 * w0 - 2 * sample_spacing, 0.5 * w0 + 2 * sample_spacing),
        bounds_z=(-0.5 * l0 - ring_spacing, 0.5 * l0 + ring_spacing),
        blur_u_mm=blur_u_mm,
        blur_z_mm=blur_z_mm,
    )
    top = float(np.max(value)) if len(value) else 0.0
    if fit is not None and fit.height > top + 3.0 * fit.noise + 0.25 * top:
        # The bump rises far above every sample (a crest extrapolated between rings from a
        # few points): not a measurement. The rough one is reported instead.
        fit = None
    if fit is None:
        return d0, idx[value > 0.5 * d0.height_mm]
    cover = _covered(s, fit, uc, zc)
    angle = ((uc + fit.u0) % circ) / circ * 360.0
    return Defect(
        kind=d0.kind,
        height_mm=round(fit.height, 3),
        width_mm=round(fit.width, 3),
        length_mm=round(fit.length, 3),
        axial_start_mm=round(zc + fit.z0 - 0.5 * fit.length, 3),
        angle_deg=round(angle, 3),
        height_sigma_mm=round(fit.height_sigma, 4),
        width_sigma_mm=round(fit.width_sigma, 4),
        length_sigma_mm=round(fit.length_sigma, 4),
        axial_start_sigma_mm=round(fit.start_sigma, 4),
        angle_sigma_deg=round(math.degrees(fit.u0_sigma / (circ / (2 * math.pi))), 5),
        fit_noise_mm=round(fit.noise, 4),
    ), cover
