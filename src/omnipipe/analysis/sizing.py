"""Defect sizing by a model fitted to the deviation map, with standard uncertainties.

The largest of noisy samples overestimates a defect's height (the more so the smaller
the defect), and half-height crossings taken from it inherit the bias. Instead every
detected defect is measured by least squares of a smooth bump to all samples around
it (the defect and the wall beside it):

    value(u, z) = b + h * P(u - u0; W, f_u W) * P(z - z0; L, f_z L)

with ``value`` the deviation signed so that the defect is positive, ``u`` the arc
length around the pipe and ``z`` the axial position (mm), and ``P(x; full, ramp)`` the
raised-cosine plateau (1 inside, cosine ramps of length ``ramp``, exactly 0.5 at
|x| = full / 2). The parameters are therefore directly the contract's quantities:
height ``h``, width ``W`` and length ``L`` at half height, centre (u0, z0); f_u, f_z in
[0.05, 1] shape the flanks (1: a raised cosine without plateau) and ``b`` absorbs a
local offset of the wall.

Uncertainty: the fit's covariance with ``s`` the RMS residual of the fit (noise and model
mismatch), for noise that is correlated from sample to sample along each ring (a light
section's sub-pixel peaks err alike over a few samples: on simulated runs the residual's
correlation is 0.65 at one sample) plus errors shared by each ring's samples (an
offset: its pose, its wall profile; an error of the defect's cross-section's shape), all
estimated from the fit's own residuals (:func:`_correlated_cov`). Treating the samples
as independent understated the length's sigma about twofold (76.9 % of true lengths
within +-2 sigma on seeds 100-106 of ``benchmarks/bench_metrology.py``). Where few rings
cross a defect or an end's flank, the shape trades against height and length (a steep
flank near a ring or a gentle one further out): their profile likelihoods then give
the sigmas where larger. Rings sample the axis sparsely: where no ring crosses one end's
flank (all rings read 0 or the plateau there), that end may lie anywhere between its two
rings, a uniform spread of variance spacing^2 / 12 added to the length and axial start.
Lengths along the run also carry the camera motion's scale uncertainty (added by the
caller).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import OptimizeResult, least_squares
from threadpoolctl import threadpool_limits

from omnipipe.analysis._kernels import GH_W, GH_X, seen_bump_with_jacobian

# Fewer rings than this across a defect's half-height length: its height's sigma is also
# taken from the profile likelihood (the linearised covariance misses a crest between rings).
PROFILE_RINGS = 4
# The axial flank is taken as round (a raised cosine without plateau) unless that costs
# the fit more than this chi-square, in units of the fit's residual variance (a crest
# between rings cannot tell a rounded bump from a lower plateau; chosen on seeds 100-129
# of ``benchmarks/bench_metrology.py``, height bias -0.074 -> -0.033 mm).
ROUND_FLANK_CHI2 = 9.0
# Parameters of the fit that absorb part of the rings' cross-section errors (height,
# centre, length, axial flank): the moment estimate of those errors is scaled by G / (G - 4).
CROSS_SECTION_DOF = 4.0

__all__ = ["BumpFit", "bump_model", "detection_limit", "fit_bump", "plateau", "seen_bump_model"]


@dataclass(frozen=True)
class BumpFit:
    """A fitted defect (mm; u around the pipe, z along it, both in the caller's frame).

    Attributes:
        height, width, length: h, W, L of the model (half-height extents).
        u0, z0: centre.
        ramp_u, ramp_z: flank fractions f_u, f_z.
        offset: local wall offset b.
        height_sigma, width_sigma, length_sigma, u0_sigma, z0_sigma, start_sigma:
            1-sigma uncertainties (start = z0 - L / 2).
        noise: RMS residual of the fit.
        n: samples used.
    """

    height: float
    width: float
    length: float
    u0: float
    z0: float
    ramp_u: float
    ramp_z: float
    offset: float
    height_sigma: float
    width_sigma: float
    length_sigma: float
    u0_sigma: float
    z0_sigma: float
    start_sigma: float
    noise: float
    n: int


def plateau(x: np.ndarray, full_width: float, ramp: float) -> np.ndarray:
    """Raised-cosine plateau: 1 inside, 0 outside, 0.5 exactly at |x| = full_width / 2.

    Args:
        x: offsets from the centre (mm), any shape.
        full_width: extent at half height (mm).
        ramp: length of each cosine flank (mm), 0 < ramp <= full_width.
    """
    x = np.asarray(x, dtype=float)
    if x.ndim == 0:
        return plateau(x.reshape(1), full_width, ramp)[0]
    phase = np.abs(x)  # then, in place: clip((|x| - inner) / ramp, 0, 1)
    phase -= 0.5 * (full_width - ramp)
    phase /= max(ramp, 1e-9)
    np.maximum(phase, 0.0, out=phase)
    np.minimum(phase, 1.0, out=phase)
    phase *= np.pi
    np.cos(phase, out=phase)
    phase += 1.0
    phase *= 0.5
    return phase


def bump_model(params: np.ndarray, u: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Model value at (u, z) for params [h, u0, z0, W, L, f_u, f_z, b] (see module doc)."""
    h, u0, z0, w, length, fu, fz, b = params
    return b + h * plateau(u - u0, w, fu * w) * plateau(z - z0, length, fz * length)


# Gauss-Hermite nodes and weights of a unit Gaussian (7 points: exact for polynomials
# up to degree 13, far below the model's resolution at the blurs that occur).
_GH_X, _GH_W = GH_X, GH_W


def _blurred_plateau(x: np.ndarray, full_width: float, ramp: float, blur_mm: float) -> np.ndarray:
    """:func:`plateau` convolved with a Gaussian of sigma ``blur_mm`` (Gauss-Hermite)."""
    if not blur_mm > 0:
        return plateau(x, full_width, ramp)
    # Every node's plateau in one (7, ...) evaluation, summed node by node in order (the
    # same floating-point sums as one plateau per node, without 7 calls' overhead).
    x = np.asarray(x, float)
    nodes = plateau(x[None, ...] + (blur_mm * _GH_X).reshape((-1,) + (1,) * x.ndim), full_width, ramp)
    total = _GH_W[0] * nodes[0]
    for w, p in zip(_GH_W[1:], nodes[1:], strict=True):
        total = total + w * p
    return total


def seen_bump_model(
    params: np.ndarray, u: np.ndarray, z: np.ndarray, blur_u_mm: float, blur_z_mm: float = 0.0
) -> np.ndarray:
    """The bump as the light section sees it: smoothed along the ring and along the axis.

    The imaged laser stripe is blurred (its peak's Gaussian sigma along a scan line,
    ``peak_width_px``); where the ring curves over a defect's crest the blurred ridge
    is, to first order, the true ring convolved along the ring with that Gaussian, so a
    narrow defect's crest reads low and its flanks wide (on simulated runs heights came
    out -1.7 % on bulges, -2.3 % on dents, widths +0.13 mm). ``blur_u_mm`` is that sigma
    in mm along the wall (0: none). Across the ring the same blur, with the sheet's
    thickness, spreads each ring over a band of wall along the axis: the stripe's peak
    on an axially curved crest is that band's ridge, the profile convolved along the
    axis with ``blur_z_mm`` (:func:`omnipipe.laser.extract.axial_blur_mm`; short
    defects read low without it: -0.17 mm under 30 mm long at 800x600). The model is
    separable, so each direction's convolution is one-dimensional.
    """
    h, u0, z0, w, length, fu, fz, b = params
    pu = _blurred_plateau(u - u0, w, fu * w, blur_u_mm)
    pz = _blurred_plateau(z - z0, length, fz * length, blur_z_mm)
    return b + h * pu * pz


def _end_var(z_rings: np.ndarray, z_edge: float, ramp: float) -> tuple[bool, float]:
    """Whether one end's flank is sampled, and the variance of a uniform spread over the
    gap between the rings on either side of it (inf when it has no ring on one side).

    A ring is informative where the cosine flank reads between 15 % and 85 % of the
    height: within 0.25 ramp of the half-height point ``z_edge``. Otherwise the end may
    lie anywhere between the rings on either side: variance gap^2 / 12.
    """
    sampled = bool(np.any(np.abs(z_rings - z_edge) < 0.25 * ramp))
    before = z_rings[z_rings <= z_edge]
    after = z_rings[z_rings > z_edge]
    if not len(before) or not len(after):
        return sampled, math.inf
    gap = float(after.min() - before.max())
    return sampled, gap * gap / 12.0


def _add_lag_correlation(
    meat: np.ndarray,
    grg: np.ndarray,
    Js: np.ndarray,
    es: np.ndarray,
    rs: np.ndarray,
    inv: np.ndarray,
    g: np.ndarray,
    total: float,
    max_lag: int,
) -> float:
    """The correlated noise along the rings, added in place: to ``meat`` (K, K) the
    Jacobian's lag products weighted by the residuals' correlation rho_k, to ``grg`` (R,)
    each ring's q^T R q of the cross-section ``g``. Samples ``Js``, ``es``, ``rs``, ``inv``
    (ring slot), ``g`` in ring, then arc order; lags up to ``max_lag`` or the first where
    rho falls to 0.02. Returns the sum of the rho_k used."""
    rho_sum = 0.0
    for k in range(1, max_lag + 1):
        same = rs[k:] == rs[:-k]
        if not same.any():
            break
        rho = float(es[k:][same] @ es[:-k][same]) / max(total, 1e-30)
        if rho <= 0.02:
            break
        m = Js[:-k][same].T @ Js[k:][same]
        meat += rho * (m + m.T)
        rho_sum += rho
        grg += 2.0 * rho * np.bincount(inv[k:][same], weights=g[k:][same] * g[:-k][same], minlength=len(grg))
    return rho_sum


def _correlated_cov(
    J: np.ndarray,
    res: np.ndarray,
    ring: np.ndarray,
    u: np.ndarray,
    noise: float,
    prior_info: np.ndarray,
    max_lag: int = 12,
    profile: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The fit's covariance with the noise correlated along each ring and ring offsets.

    A light section's errors are not independent from sample to sample: the laser
    line's sub-pixel peak is found on a blurred stripe, so neighbouring samples of one
    ring err alike (on the simulated runs the residual's correlation is about 0.65 at one
    sample, 0.35 at two, 0.1 at four). The sum of a ring's samples across a defect
    then varies about twice as much as independent noise would give, and so do the
    height, length and ends fitted from it. Each ring's residuals, in order around the
    pipe, give the correlation rho_k at lag k samples (pooled over the rings, summed up to
    the first lag where it falls below 0.02), and whatever the ring means scatter
    beyond that is a ring offset shared by all its samples (its pose, its wall profile):
    variance tau^2. Likewise each ring's residual along the defect's cross-section
    ``profile`` (errors correlated over the defect's width, an axial shift of a ring on
    a flank) gives a ring-wide error of that shape (on the simulated runs about 0.1 mm
    beyond the correlated noise, beside the defects as on them). With S the noise
    covariance so modelled, the estimate's covariance is the sandwich

        A^-1 (J^T S J / s^4 + P) A^-1,   A = J^T J / s^2 + P,

    with P the weak prior information of :func:`fit_bump` (directions the samples do not
    constrain keep the prior's variance).

    Args:
        J: (N, K) Jacobian of the residuals (mm per parameter unit).
        res: (N,) residuals (mm); ring: (N,) ring index; u: (N,) position along the ring.
        noise: RMS residual s (mm).
        prior_info: (K, K) prior information P.
        max_lag: largest lag (samples) considered.
        profile: (N,) the defect's cross-section at each sample (0-1), or None.

    Returns:
        (covariance with correlation, covariance as if the samples were independent).
    """
    s2 = max(noise, 1e-9) ** 2
    info = J.T @ J / s2 + prior_info
    cov_iid = np.linalg.inv(info)
    order = np.lexsort((u, ring))
    Js, es, rs = J[order], res[order], ring[order]
    total = float(es @ es)
    meat = J.T @ J
    ids, inv, counts = np.unique(rs, return_inverse=True, return_counts=True)
    g = np.asarray(profile, float)[order] if profile is not None else np.zeros(len(es))
    # Per ring: q.q and q^T R q (R: the noise correlation).
    gg = np.bincount(inv, weights=g * g, minlength=len(ids))
    grg = gg.copy()
    rho_sum = _add_lag_correlation(meat, grg, Js, es, rs, inv, g, total, max_lag)
    if len(ids) >= 3:
        # Ring offsets: the ring means' scatter beyond what the correlated noise explains.
        means = np.bincount(inv, weights=es) / counts
        expected = s2 * (1.0 + 2.0 * rho_sum) / counts
        tau2 = max(float(np.mean(means**2 - expected)), 0.0)
        if tau2 > 0:
            sums = np.zeros((len(ids), J.shape[1]))
            np.add.at(sums, inv, Js)
            meat += tau2 / s2 * (sums.T @ sums)
    if profile is not None and len(ids) >= 3 and np.sum(gg**2) > 0:
        # Errors of a whole ring with the defect's cross-section q (noise correlated along
        # the ring over the defect's width, a ring's axial shift on the flanks): each ring's
        # residual along q beyond what the correlated noise explains, pooled over all the
        # window's rings (those beside the defect measure it as well).
        ge = np.bincount(inv, weights=g * es, minlength=len(ids))
        g_eff = float(np.sum(gg) ** 2 / np.sum(gg**2))
        excess = float(np.sum(ge**2 - s2 * grg)) / float(np.sum(gg**2))
        amp2 = max(excess, 0.0) * g_eff / max(g_eff - CROSS_SECTION_DOF, 1.0)
        if amp2 > 0:
            v = np.zeros((len(ids), J.shape[1]))
            np.add.at(v, inv, Js * g[:, None])
            meat += amp2 / s2 * (v.T @ v)
    cov = cov_iid @ (meat / s2 + prior_info) @ cov_iid
    return cov, cov_iid


def _profile_sigma(
    residual: _BumpResidual,
    p: np.ndarray,
    index: int,
    factors: tuple[tuple[float, ...], tuple[float, ...]],
    cost: float,
    noise: float,
    lower: list[float],
    upper: list[float],
    inflation: float = 1.0,
) -> float:
    """Half of the larger side of one parameter's 2-sigma profile-likelihood interval.

    Steps parameter ``index`` (0: height, 4: length) outward from the fit ``p`` by the
    ``factors`` (a downward and an upward sequence), each step refitting the other
    parameters warm-started from the previous step and from a rounded flank, until
    chi-square exceeds the best by 4 x ``inflation``, interpolating the crossing; a side
    that never exceeds it ends at its last step. ``inflation`` is the ratio of the
    parameter's variance with correlated noise to its variance with independent samples
    (the chi-square of correlated samples counts each error that many times).
    """
    v0 = float(p[index])
    limit = 4.0 * max(inflation, 1.0) * max(noise, 1e-9) ** 2
    half = 0.0
    for steps in factors:
        x, prev_v, prev_d = np.array(p, float), v0, 0.0
        edge = v0
        for f in steps:
            vv = v0 * f
            if not lower[index] < vv < upper[index]:
                break
            lo_f, hi_f = list(lower), list(upper)
            lo_f[index], hi_f[index] = vv - 1e-6 * v0, vv + 1e-6 * v0
            sol = None
            # The flank shape has local minima: warm start, and a rounded flank.
            for fz in (None, 1.0):
                x0 = np.array(x, float)
                x0[index] = vv
                if fz is not None:
                    x0[6] = fz
                x0 = np.clip(x0, np.array(lo_f) + 1e-12, np.array(hi_f) - 1e-12)
                trial = least_squares(residual, x0, bounds=(lo_f, hi_f), jac=residual.jac, x_scale="jac", max_nfev=80)
                if sol is None or trial.cost < sol.cost:
                    sol = trial
            d = 2.0 * (sol.cost - cost)
            if d > limit:
                # chi-square grows about quadratically with the parameter: interpolate its root.
                r0, r1 = math.sqrt(max(prev_d, 0.0)), math.sqrt(d)
                edge = prev_v + (vv - prev_v) * (math.sqrt(limit) - r0) / max(r1 - r0, 1e-12)
                break
            x, prev_v, prev_d, edge = sol.x, vv, d, vv
        half = max(half, abs(edge - v0))
    return 0.5 * half


def _profiled(
    residual: _BumpResidual,
    sol: OptimizeResult,
    var: np.ndarray,
    cov_iid: np.ndarray,
    zr: np.ndarray,
    noise: float,
    lower: list[float],
    upper: list[float],
) -> float:
    """Height's and length's variances ``var`` (changed in place) raised to their
    profile likelihood's where the linearised covariance misses an ambiguity; returns the
    length's profiled sigma (0: not profiled).

    A crest between rings: with few rings across the half-height length, a low flat bump
    and a taller, shorter or rounder one fit the samples alike, and the linearised
    covariance misses that. The height's profile likelihood gives its 2-sigma interval
    instead (heights whose best fit of the other parameters stays within chi-square 4 of
    the best); its larger half, halved, is the sigma where that is larger.

    An end whose flank (the ramp, 0-100 % of the height) holds fewer than two rings is
    ambiguous the same way: one ring's value on a flank is met by a steep flank near it
    or a gentle one further out (on seed 113 of bench_metrology a boxy and a rounded fit,
    4.5 mm apart in length, differ by 0.1 % in chi-square). The length's profile
    likelihood then gives its sigma where that is larger.
    """
    p = sol.x
    z0, length, fz = p[2], p[4], p[6]
    ramp = fz * length
    prof_length = 0.0
    few_across = np.sum(np.abs(zr - z0) < 0.5 * length) < PROFILE_RINGS
    flank_rings = min(
        int(np.sum(np.abs(zr - (z0 + side * 0.5 * length)) < 0.5 * ramp)) for side in (-1.0, 1.0)
    )
    profiles = [(0, ((0.85, 0.7, 0.5), (1.15, 1.35, 1.7, 2.5)))] if few_across else []
    if few_across or flank_rings < 2:
        profiles.append((4, ((0.95, 0.9, 0.8, 0.65, 0.5), (1.05, 1.1, 1.25, 1.5, 2.0))))
    for index, steps in profiles:
        inflation = float(var[index] / max(cov_iid[index, index], 1e-30))
        prof = _profile_sigma(residual, p, index, steps, sol.cost, noise, lower, upper, inflation)
        var[index] = max(var[index], prof**2)
        if index == 4:
            prof_length = math.sqrt(var[4])
    return prof_length


def _end_variances(
    var: np.ndarray,
    cov: np.ndarray,
    zr: np.ndarray,
    z0: float,
    length: float,
    ramp: float,
    prof_length: float,
) -> tuple[float, float, float]:
    """(length, centre, start) variances (mm^2) of a bump centred at ``z0`` along the
    axis, from the fit's (co)variances and the rings ``zr`` (mm) sampling its ends.

    Each end (z0 -+ L / 2): the fit's variance where a ring samples its flank, the
    uniform spread between the bracketing rings where none does; the bracketing rings
    bound an end even where the fit constrains it poorly. The flank-shape ambiguity
    (``prof_length``, the length's profiled sigma) moves both ends: each by half.
    """
    sampled_lo, gap_lo = _end_var(zr, z0 - 0.5 * length, ramp)
    sampled_hi, gap_hi = _end_var(zr, z0 + 0.5 * length, ramp)
    fit_lo = max(var[2] + 0.25 * var[4] - cov[2, 4], 0.0)
    fit_hi = max(var[2] + 0.25 * var[4] + cov[2, 4], 0.0)
    var_lo = min(fit_lo, gap_lo) if sampled_lo else gap_lo
    var_hi = min(fit_hi, gap_hi) if sampled_hi else gap_hi
    var_lo = fit_lo if not math.isfinite(var_lo) else var_lo
    var_hi = fit_hi if not math.isfinite(var_hi) else var_hi
    both_fit = var_lo == fit_lo and var_hi == fit_hi
    cov_ends = var[2] - 0.25 * var[4] if both_fit else 0.0
    var_length = max(var_lo + var_hi - 2.0 * cov_ends, prof_length**2)
    var_centre = max(0.25 * (var_lo + var_hi + 2.0 * cov_ends), 0.0)
    var_lo = max(var_lo, 0.25 * prof_length**2)
    return var_length, var_centre, var_lo


class _BumpResidual:
    """Residuals of :func:`seen_bump_model` against the kept samples, a weak prior, and
    their analytic Jacobian (:func:`._kernels.seen_bump_with_jacobian`).

    The prior (worth one sample at the noise level ``prior_scale``) pulls flank shapes
    that no sample constrains (a flank between two rings) to the middle of their range.
    ``keep`` and ``prior_scale`` are set between the fit's passes. The model and its
    Jacobian are computed together and the Jacobian kept for the same parameters
    (least squares asks for the residuals, then the Jacobian, at each accepted step).
    """

    def __init__(
        self, u: np.ndarray, z: np.ndarray, value: np.ndarray, blur_u_mm: float, blur_z_mm: float
    ) -> None:
        self.u, self.z, self.value = u, z, value
        self.blur_u_mm, self.blur_z_mm = blur_u_mm, blur_z_mm
        self.keep = np.ones(len(value), bool)
        self.prior_scale = 0.05
        self._last: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    @property
    def keep(self) -> np.ndarray:
        """(N,) bool: the samples the residuals hold."""
        return self._keep

    @keep.setter
    def keep(self, keep: np.ndarray) -> None:
        self._keep = np.asarray(keep, bool)
        self._u = np.ascontiguousarray(self.u[self._keep], float)
        self._z = np.ascontiguousarray(self.z[self._keep], float)
        self._value = self.value[self._keep]
        self._last = None

    def model(self, p: np.ndarray) -> np.ndarray:
        """(N,) the bump of parameters ``p`` at every sample, kept or not (mm)."""
        return seen_bump_model(p, self.u, self.z, self.blur_u_mm, self.blur_z_mm)

    def _evaluate(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = np.array(p, float)
        if self._last is not None and np.array_equal(self._last[0], p):
            return self._last[1], self._last[2]
        model, jac = seen_bump_with_jacobian(p, self._u, self._z, self.blur_u_mm, self.blur_z_mm)
        res = np.concatenate([model - self._value, self.prior_scale * (p[5:7] - 0.5) / 0.5])
        full = np.zeros((len(res), len(p)))
        full[:-2] = jac
        full[-2, 5] = full[-1, 6] = self.prior_scale / 0.5
        self._last = (p, res, full)
        return res, full

    def __call__(self, p: np.ndarray) -> np.ndarray:
        return self._evaluate(p)[0].copy()

    def jac(self, p: np.ndarray) -> np.ndarray:
        """(N_kept + 2, 8) Jacobian of :meth:`__call__` at ``p``."""
        return self._evaluate(p)[1].copy()


def _bump_bounds(
    start: tuple[float, float, float, float, float],
    bounds_u: tuple[float, float],
    bounds_z: tuple[float, float],
) -> tuple[list[float], list[float]]:
    """Lower and upper bounds of (height, u0, z0, width, length, ramp_u, ramp_z, offset)."""
    h0 = start[0]
    span_u = bounds_u[1] - bounds_u[0]
    span_z = bounds_z[1] - bounds_z[0]
    lower = [1e-3, bounds_u[0], bounds_z[0], 0.2, 0.2, 0.05, 0.05, -5.0]
    upper = [
        max(3.0 * h0, h0 + 2.0),
        bounds_u[1],
        bounds_z[1],
        max(span_u, 0.3),
        max(span_z, 0.3),
        1.0,
        1.0,
        5.0,
    ]
    return lower, upper


def _solve_bump(
    residual: _BumpResidual,
    start: tuple[float, float, float, float, float],
    lower: list[float],
    upper: list[float],
) -> OptimizeResult | None:
    """The least-squares bump: three starting flank shapes, one pass of outlier rejection
    (extraction outliers, a neighbouring defect's edge; ``residual.keep`` then holds the
    samples kept), then the roundest axial flank the samples accept. None: fewer than 12
    samples kept."""
    h0, u00, z00, w0, l0 = start
    starts = []
    for fu, fz in ((0.5, 0.5), (1.0, 1.0), (0.15, 0.3)):
        x0 = np.clip(
            [h0, u00, z00, max(w0, 0.5), max(l0, 0.5), fu, fz, 0.0],
            np.array(lower) + 1e-9,
            np.array(upper) - 1e-9,
        )
        starts.append(
            least_squares(residual, x0, bounds=(lower, upper), jac=residual.jac, x_scale="jac", max_nfev=400)
        )
    best = min(starts, key=lambda sol: sol.cost)  # the first of the lowest
    res = best.fun[:-2]
    scale = 1.4826 * float(np.median(np.abs(res))) + 1e-9
    residual.prior_scale = scale
    residual.keep = np.abs(residual.model(best.x) - residual.value) <= max(5.0 * scale, 1e-6)
    if residual.keep.sum() < 12:
        return None
    sol = least_squares(residual, best.x, bounds=(lower, upper), jac=residual.jac, x_scale="jac", max_nfev=400)
    n, k = int(residual.keep.sum()), len(sol.x)
    free_cost, s2 = sol.cost, float(np.sum(sol.fun[:-2] ** 2) / max(n - k, 1))
    if ROUND_FLANK_CHI2 > 0 and sol.x[6] < 0.95:
        # The roundest axial flank the samples accept. With one to three rings across a
        # defect, a crest between them is met as well by a lower plateau with a longer,
        # steeper-ended profile as by a taller rounded bump; the free fit drifted to the
        # plateau (heights -0.3 mm under 20 mm long at 8 mm ring spacing, with the same
        # data read +0.09 mm by the true shape). Round is kept unless the samples reject it.
        trial_lo = list(lower)
        trial_lo[6] = 1.0 - 1e-6
        x0 = np.clip(sol.x, np.array(trial_lo) + 1e-9, np.array(upper) - 1e-9)
        rnd = least_squares(residual, x0, bounds=(trial_lo, upper), jac=residual.jac, x_scale="jac", max_nfev=400)
        if 2.0 * (rnd.cost - free_cost) < ROUND_FLANK_CHI2 * s2:
            sol = rnd
    return sol


def fit_bump(
    u: np.ndarray,
    z: np.ndarray,
    value: np.ndarray,
    ring: np.ndarray,
    start: tuple[float, float, float, float, float],
    *,
    bounds_u: tuple[float, float],
    bounds_z: tuple[float, float],
    blur_u_mm: float = 0.0,
    blur_z_mm: float = 0.0,
) -> BumpFit | None:
    """Least-squares bump fit to the samples around one defect.

    Args:
        u: (N,) arc length around the pipe, unwrapped around the defect (mm).
        z: (N,) axial position (mm).
        value: (N,) deviation, signed so that the defect is positive (mm).
        ring: (N,) ring index of each sample (for the axial sampling term).
        start: initial (height, u0, z0, width, length).
        bounds_u, bounds_z: the window; the centre stays inside it.
        blur_u_mm: the light section's Gaussian smoothing along the ring (mm; see
            :func:`seen_bump_model`); 0 fits the bump as sampled.
        blur_z_mm: the same along the pipe axis (mm).

    Returns:
        The fit, or None when it does not converge to a positive bump.
    """
    u, z, value = (np.asarray(a, float) for a in (u, z, value))
    if len(value) < 12:
        return None
    # Single-threaded BLAS: the solver's SVDs of a (N, 8) Jacobian are far too small to
    # share out, and threads waiting on a busy machine cost more than the SVD.
    with threadpool_limits(limits=1, user_api="blas"):
        return _fit_bump(u, z, value, np.asarray(ring), start, bounds_u, bounds_z, blur_u_mm, blur_z_mm)


def _fit_bump(
    u: np.ndarray,
    z: np.ndarray,
    value: np.ndarray,
    ring: np.ndarray,
    start: tuple[float, float, float, float, float],
    bounds_u: tuple[float, float],
    bounds_z: tuple[float, float],
    blur_u_mm: float,
    blur_z_mm: float,
) -> BumpFit | None:
    """:func:`fit_bump`'s work, its arguments checked."""
    h0, _, _, w0, l0 = start
    lower, upper = _bump_bounds(start, bounds_u, bounds_z)
    residual = _BumpResidual(u, z, value, blur_u_mm, blur_z_mm)
    sol = _solve_bump(residual, start, lower, upper)
    if sol is None:
        return None
    keep = residual.keep
    n, k = int(keep.sum()), len(sol.x)
    p = sol.x
    res = sol.fun[:-2]
    noise = float(np.sqrt(np.sum(res**2) / max(n - k, 1)))
    J = sol.jac[:-2]
    # Directions the samples do not constrain keep a broad prior variance instead of the
    # zero a pseudo-inverse would give them (a defect end between two rings).
    prior_sigma = np.array([max(h0, 1.0), w0, l0, w0, l0, 0.5, 0.5, 1.0])
    cov, cov_iid = _correlated_cov(
        J, res, ring[keep], u[keep], noise, np.diag(1.0 / prior_sigma**2), profile=plateau(u[keep] - p[1], p[3], p[5] * p[3])
    )
    var = np.clip(np.diag(cov), 0.0, None)
    h, u0, z0, w, length, fu, fz, _ = p
    if not h > 0:
        return None
    # Ends of the defect along the axis that no ring sampled: uniform between rings.
    zr = np.array([float(np.median(z[keep & (ring == r)])) for r in np.unique(ring[keep])])
    near_u = np.abs(u - u0) <= 0.5 * w
    if near_u.any():
        zr = np.array(
            [float(np.median(z[keep & near_u & (ring == r)])) for r in np.unique(ring[keep & near_u])]
        )
    prof_length = _profiled(residual, sol, var, cov_iid, zr, noise, lower, upper)
    var_length, var_centre, var_lo = _end_variances(var, cov, zr, z0, length, fz * length, prof_length)
    return BumpFit(
        height=float(h),
        width=float(w),
        length=float(length),
        u0=float(u0),
        z0=float(z0),
        ramp_u=float(fu),
        ramp_z=float(fz),
        offset=float(p[7]),
        height_sigma=float(math.sqrt(var[0])),
        width_sigma=float(math.sqrt(var[3])),
        length_sigma=float(math.sqrt(var_length)),
        u0_sigma=float(math.sqrt(var[1])),
        z0_sigma=float(math.sqrt(var_centre)),
        start_sigma=float(math.sqrt(var_lo)),
        noise=noise,
        n=n,
    )


def detection_limit(
    *,
    noise_mm: float,
    threshold_mm: float,
    sample_spacing_mm: float,
    ring_spacing_mm: float,
    min_points: int,
    width_mm: float,
    length_mm: float,
    z_score: float = 1.645,
) -> float:
    """Smallest height of a reference defect the detector finds with high probability.

    The reference defect is a raised cosine (no plateau) ``width_mm`` wide and
    ``length_mm`` long at half height, placed in the worst way between the rings (its
    crest half a ring spacing from the nearest ring) and between samples. It is found when
    at least ``min_points`` samples exceed the threshold; a sample whose expected value is
    ``z_score`` noise sigmas above the threshold does so with probability >= 95 %.

    Returns:
        The height (mm); inf when the reference defect fits between the rings.
    """
    need = threshold_mm + z_score * noise_mm
    du = max(sample_spacing_mm, 1e-3)
    n_u = int(math.ceil(2.0 * width_mm / du)) + 2
    us = (np.arange(-n_u, n_u + 1) + 0.5) * du  # samples straddling the crest
    pu = plateau(us, width_mm, width_mm)
    ds = max(ring_spacing_mm, 1e-3)
    n_z = int(math.ceil(2.0 * length_mm / ds)) + 2
    zs = (np.arange(-n_z, n_z + 1) + 0.5) * ds  # rings straddling the crest
    pz = plateau(zs, length_mm, length_mm)
    profile = np.sort(np.outer(pz, pu).ravel())[::-1]
    if len(profile) < min_points or profile[min_points - 1] <= 0:
        return math.inf
    # The min_points-th largest sample must reach ``need``.
    return float(need / profile[min_points - 1])
