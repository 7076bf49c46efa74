"""Scale matching with the laser (paper Sec. V-D, Fig. 15, Eq. 17).

Structure from motion gives the translation between two frames a and b only up to
scale. The laser points of frame a are metric (light section, Eq. 5). Each is found
again in frame b by template matching on perspective-converted patches (Sec. V-A):
a small projection plane tangent to the wall at the laser point is drawn from frame
a (the laser stripe itself masked out) and compared with the same plane drawn from
frame b for every candidate translation length s along the SfM direction, i.e.
along the epipolar curve. The best s of each point is the scale l at which the SfM
point l p'_k meets the laser point p_k; Eq. (17) combines them with the log
objective, whose minimiser over one scale is the median of the per-point log ratios.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import cv2
import numba
import numpy as np

from omnipipe.camera import CameraModel
from omnipipe.camera._kernels import project_point
from omnipipe.camera.base import CompiledProjection
from omnipipe.config import bounded
from omnipipe.image import sample_bilinear
from omnipipe.sfm._kernels import candidate_maps


@dataclass(frozen=True)
class LaserScaleConfig:
    """Template matching of laser points.

    Attributes:
        patch_radius: the patch has (2 r + 1)^2 samples.
        stripe_half_width_mm: band around the laser stripe left out of the template.
        stripe_half_width_px: ... and at least this many template samples (about pixels):
            the stripe's blur and colour crosstalk reach a few pixels whatever the size
            in mm, and a template holding the stripe would pull matches to zero motion.
        scale_range_mm: (min, max) translation length searched (mm).
        scale_steps: number of log-spaced candidates (then refined).
        min_ncc: a point's match counts when its best NCC exceeds this.
        min_template_std: templates flatter than this (grey levels) are skipped.
        max_points: laser points tried per frame pair (evenly spread around the ring).
        detrend: remove a brightness plane from template and patches before the NCC
            (a compiled closed form). The LEDs' fall-off and the mirror's vignetting move
            with the robot; where the wall's own texture is weak beside them (a ring
            near the blind centre, a plain or large-tiled wall at low resolution) a
            patch's variance is mostly that gradient, the same at every candidate, and
            the correlation follows it instead of the wall. Off: on textured walls the
            plane carries some of the wall's own signal (benchmarks/RESULTS.md).
        prior_window_log: a keyframe step's laser search (:func:`match_laser_points_near`)
            first tries only the candidates within this factor (log) of the step's
            feature-depth length; the full range when that answer is weak. 0: always
            the full range.
        flat_field_keyframes: a keyframe step's frames are divided by the rig-fixed
            illumination, the per-pixel median of this many keyframes around the step
            (:mod:`omnipipe.sfm.flat_field`: the LEDs' fall-off and the laser's own
            light move with the robot, the wall does not), before its Eq. 17 matching;
            0: off (the frames as they are).
    """

    patch_radius: int = bounded(6, ge=1)
    stripe_half_width_mm: float = bounded(1.2, ge=0)
    stripe_half_width_px: float = bounded(2.5, ge=0)
    scale_range_mm: tuple[float, float] = bounded((0.2, 200.0), gt=0)
    scale_steps: int = bounded(96, ge=2)
    min_ncc: float = bounded(0.8, ge=-1, le=1)
    min_template_std: float = bounded(2.0, ge=0)
    max_points: int = bounded(120, ge=1)
    detrend: bool = False
    prior_window_log: float = bounded(0.5, ge=0)
    flat_field_keyframes: int = bounded(0, ge=0)


@dataclass
class LaserMatches:
    """Laser points of frame a found again in frame b.

    Attributes:
        index: (M,) indices into the laser points of frame a that matched.
        scale_mm: (M,) translation length that puts each point on its match (mm).
        pixels_b: (M, 2) their omni pixels in frame b.
        ncc: (M,) best normalised cross-correlation.
        scale: combined translation length (mm) by Eq. (17); NaN without matches.
        peak_scales_mm: (P,) translation lengths where the consensus of all points
            (mean of their clipped NCC curves along the epipolar curves) peaks, best
            first. A periodic wall (brick courses, joints) gives several peaks.
        peak_scores: (P,) the consensus value of each peak (0..1).
    """

    index: np.ndarray
    scale_mm: np.ndarray
    pixels_b: np.ndarray
    ncc: np.ndarray
    scale: float
    peak_scales_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    peak_scores: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def ambiguity(self) -> float:
        """Second consensus peak over the best (0: one clear answer, 1: a tie)."""
        if len(self.peak_scores) < 2 or self.peak_scores[0] <= 0:
            return 0.0
        return float(self.peak_scores[1] / self.peak_scores[0])


def consensus_peaks(
    scales: np.ndarray, ncc: np.ndarray, min_separation: float = 0.15
) -> tuple[np.ndarray, np.ndarray]:
    """Peaks of the points' consensus along the epipolar curve.

    Args:
        scales: (S,) increasing candidate translation lengths (mm), log-spaced.
        ncc: (N, S) each point's NCC at each candidate (-1 where not comparable).
        min_separation: peaks closer than this in log scale count as one.

    Returns:
        (P,) peak lengths (mm) and (P,) consensus scores, best first. The consensus is
        the mean over points of max(NCC, 0)^2: a point votes where its patch matches.
    """
    if ncc.size == 0:
        return np.zeros(0), np.zeros(0)
    c = np.mean(np.clip(ncc, 0.0, 1.0) ** 2, axis=0)
    padded = np.concatenate([[-np.inf], c, [-np.inf]])
    is_peak = (padded[1:-1] >= padded[:-2]) & (padded[1:-1] > padded[2:])
    idx = np.flatnonzero(is_peak)
    idx = idx[np.argsort(-c[idx])]
    logs = np.log(scales)
    kept: list[int] = []
    for i in idx:
        if all(abs(logs[i] - logs[j]) > min_separation for j in kept):
            kept.append(int(i))
    kept_arr = np.array(kept, int)
    return scales[kept_arr], c[kept_arr]


def _ncc(
    template: np.ndarray,
    patches: np.ndarray,
    weight: np.ndarray,
    basis: np.ndarray | None = None,
) -> np.ndarray:
    """NCC of (N, K) templates with (N, S, K) patches, (N, K) sample weights.

    With ``basis`` ((B, K), e.g. the patch coordinates), template and patch each lose
    their weighted least-squares fit of a constant plus those functions before the
    correlation: a brightness gradient across the patch (the LEDs' fall-off, which
    moves with the robot) then cannot pull the match along the epipolar curve.

    Without ``basis`` a compiled kernel computes it (bit-identical to
    :func:`_ncc_numpy`, NumPy's pairwise sums included; one pass instead of a dozen
    (N, S, K) temporaries); with a (2, K) basis (a plane) another one, equal to it
    within rounding.
    """
    w = weight[:, None, :] if weight.ndim == 2 else weight
    out = np.empty(patches.shape[:2])
    args = (np.ascontiguousarray(template), np.ascontiguousarray(patches), np.ascontiguousarray(w, dtype=float))
    if basis is None:
        _ncc_kernel(*args, out)
    elif basis.shape[0] == 2:
        _ncc_plane_kernel(*args, np.ascontiguousarray(basis, dtype=float), out)
    else:
        return _ncc_numpy(template, patches, w, basis)
    return out


def _ncc_numpy(
    template: np.ndarray,
    patches: np.ndarray,
    weight: np.ndarray,
    basis: np.ndarray | None = None,
) -> np.ndarray:
    """:func:`_ncc` in NumPy (the detrended variant; the reference of the kernel)."""
    w = weight[:, None, :] if weight.ndim == 2 else weight
    t = template[:, None, :]
    valid = np.isfinite(patches) & np.isfinite(t)
    ww = np.where(valid, w, 0.0)
    wsum = np.maximum(ww.sum(axis=2), 1e-9)
    p = np.where(valid, patches, 0.0)
    tt = np.where(valid, t, 0.0)
    if basis is None:
        dp = p - ((ww * p).sum(axis=2) / wsum)[..., None]
        dt = tt - ((ww * tt).sum(axis=2) / wsum)[..., None]
    else:
        A = np.vstack([np.ones((1, basis.shape[1])), basis])  # (B+1, K)
        M = np.einsum("nsk,ik,jk->nsij", ww, A, A) + 1e-9 * np.eye(len(A))

        def detrend(v: np.ndarray) -> np.ndarray:
            rhs = np.einsum("nsk,ik->nsi", ww * v, A)[..., None]
            coef = np.linalg.solve(M, rhs)[..., 0]
            return v - np.einsum("nsi,ik->nsk", coef, A)

        dp, dt = detrend(p), detrend(np.broadcast_to(tt, p.shape))
    num = (ww * dp * dt).sum(axis=2)
    den = np.sqrt((ww * dp * dp).sum(axis=2) * (ww * dt * dt).sum(axis=2))
    ncc = num / np.maximum(den, 1e-9)
    return np.where(valid.mean(axis=2) > 0.8, ncc, -1.0)


@numba.njit(cache=True)
def _block_sum(a, lo, n):  # pragma: no cover - compiled
    """NumPy's pairwise sum of a[lo:lo + n] for n <= 128 (eight accumulators)."""
    if n < 8:
        res = -0.0
        for i in range(n):
            res += a[lo + i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - (n % 8):
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@numba.njit(cache=True)
def _pairwise_sum(a, n, stack, values):  # pragma: no cover - compiled
    """Sum of a[:n] in NumPy's pairwise order (``np.add.reduce`` of float64 along a
    contiguous axis), bit for bit: halves (rounded down to multiples of 8) until a block
    has at most 128 elements. Iterative (a cached recursive numba function crashes on
    load); ``stack`` (64, 3) int64 and ``values`` (64,) float64 are scratch space."""
    if n <= 128:
        return _block_sum(a, 0, n)
    sp, vp = 1, 0
    stack[0, 0], stack[0, 1], stack[0, 2] = 0, n, 0
    while sp > 0:
        lo, m, stage = stack[sp - 1, 0], stack[sp - 1, 1], stack[sp - 1, 2]
        if m <= 128:
            values[vp] = _block_sum(a, lo, m)
            vp += 1
            sp -= 1
            continue
        half = m // 2
        half -= half % 8
        if stage == 0:  # left half first
            stack[sp - 1, 2] = 1
            stack[sp, 0], stack[sp, 1], stack[sp, 2] = lo, half, 0
            sp += 1
        elif stage == 1:  # then the right half
            stack[sp - 1, 2] = 2
            stack[sp, 0], stack[sp, 1], stack[sp, 2] = lo + half, m - half, 0
            sp += 1
        else:  # both done: left + right
            values[vp - 2] = values[vp - 2] + values[vp - 1]
            vp -= 1
            sp -= 1
    return values[0]


@numba.njit(cache=True, error_model="numpy")
def _ncc_kernel(template, patches, weight, out):  # pragma: no cover - compiled
    """:func:`_ncc_numpy` without basis: (N, K) templates, (N, S, K) patches, (N, 1 or S,
    K) weights -> (N, S) ``out``; the same operations in the same order (sums pairwise
    as NumPy's, started from 0)."""
    n_pts, n_s, k_len = patches.shape
    ww = np.empty(k_len)
    p = np.empty(k_len)
    tt = np.empty(k_len)
    acc = np.empty(k_len)
    stack = np.empty((64, 3), np.int64)
    values = np.empty(64)
    for i in range(n_pts):
        for j in range(n_s):
            jw = j if weight.shape[1] > 1 else 0
            n_valid = 0
            for k in range(k_len):
                pv = patches[i, j, k]
                tv = template[i, k]
                if np.isfinite(pv) and np.isfinite(tv):
                    n_valid += 1
                    ww[k] = weight[i, jw, k]
                    p[k] = pv
                    tt[k] = tv
                else:
                    ww[k] = 0.0
                    p[k] = 0.0
                    tt[k] = 0.0
            wsum = 0.0 + _pairwise_sum(ww, k_len, stack, values)
            if wsum < 1e-9:  # np.maximum(wsum, 1e-9); NaN stays NaN
                wsum = 1e-9
            for k in range(k_len):
                acc[k] = ww[k] * p[k]
            mean_p = (0.0 + _pairwise_sum(acc, k_len, stack, values)) / wsum
            for k in range(k_len):
                acc[k] = ww[k] * tt[k]
            mean_t = (0.0 + _pairwise_sum(acc, k_len, stack, values)) / wsum
            for k in range(k_len):
                p[k] = p[k] - mean_p  # dp
                tt[k] = tt[k] - mean_t  # dt
            for k in range(k_len):
                acc[k] = ww[k] * p[k] * tt[k]
            num = 0.0 + _pairwise_sum(acc, k_len, stack, values)
            for k in range(k_len):
                acc[k] = ww[k] * p[k] * p[k]
            spp = 0.0 + _pairwise_sum(acc, k_len, stack, values)
            for k in range(k_len):
                acc[k] = ww[k] * tt[k] * tt[k]
            stt = 0.0 + _pairwise_sum(acc, k_len, stack, values)
            den = math.sqrt(spp * stt)
            if den < 1e-9:  # np.maximum(den, 1e-9); NaN stays NaN
                den = 1e-9
            out[i, j] = num / den if n_valid / k_len > 0.8 else -1.0


@numba.njit(cache=True, error_model="numpy")
def _solve3(m, b, x):  # pragma: no cover - compiled
    """x = m^-1 b for a (3, 3) symmetric positive definite ``m`` (Cramer's rule)."""
    c00 = m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1]
    c01 = m[1, 2] * m[2, 0] - m[1, 0] * m[2, 2]
    c02 = m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]
    det = m[0, 0] * c00 + m[0, 1] * c01 + m[0, 2] * c02
    c11 = m[0, 0] * m[2, 2] - m[0, 2] * m[2, 0]
    c12 = m[0, 1] * m[2, 0] - m[0, 0] * m[2, 1]
    c22 = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    x[0] = (c00 * b[0] + c01 * b[1] + c02 * b[2]) / det
    x[1] = (c01 * b[0] + c11 * b[1] + c12 * b[2]) / det
    x[2] = (c02 * b[0] + c12 * b[1] + c22 * b[2]) / det


@numba.njit(cache=True, error_model="numpy")
def _ncc_plane_kernel(template, patches, weight, basis, out):  # pragma: no cover - compiled
    """:func:`_ncc_numpy` with a (2, K) ``basis`` (u, v): each of template and patch
    loses its weighted least-squares plane a + b u + c v, in closed form. From the
    weighted sums (moments) M of (1, u, v), b_p and b_t of p and t against them:
    cov = S_pt - b_p' M^-1 b_t, var_p = S_pp - b_p' M^-1 b_p (likewise t); NCC =
    cov / sqrt(var_p var_t). (N, K), (N, S, K), (N, 1 or S, K) -> (N, S) ``out``."""
    n_pts, n_s, k_len = patches.shape
    m = np.empty((3, 3))
    bp = np.empty(3)
    bt = np.empty(3)
    xp = np.empty(3)
    xt = np.empty(3)
    for i in range(n_pts):
        t0 = 0.0  # centre the grey levels on the template's first value: smaller sums
        for k in range(k_len):
            if np.isfinite(template[i, k]):
                t0 = template[i, k]
                break
        for j in range(n_s):
            jw = j if weight.shape[1] > 1 else 0
            n_valid = 0
            m[:, :] = 0.0
            bp[:] = 0.0
            bt[:] = 0.0
            spp = 0.0
            stt = 0.0
            spt = 0.0
            for k in range(k_len):
                pv = patches[i, j, k]
                tv = template[i, k]
                if not (np.isfinite(pv) and np.isfinite(tv)):
                    continue
                n_valid += 1
                w = weight[i, jw, k]
                u = basis[0, k]
                v = basis[1, k]
                pv -= t0
                tv -= t0
                m[0, 0] += w
                m[0, 1] += w * u
                m[0, 2] += w * v
                m[1, 1] += w * u * u
                m[1, 2] += w * u * v
                m[2, 2] += w * v * v
                bp[0] += w * pv
                bp[1] += w * pv * u
                bp[2] += w * pv * v
                bt[0] += w * tv
                bt[1] += w * tv * u
                bt[2] += w * tv * v
                spp += w * pv * pv
                stt += w * tv * tv
                spt += w * pv * tv
            if not n_valid / k_len > 0.8:
                out[i, j] = -1.0
                continue
            m[1, 0] = m[0, 1]
            m[2, 0] = m[0, 2]
            m[2, 1] = m[1, 2]
            for d in range(3):
                m[d, d] += 1e-9
            _solve3(m, bp, xp)
            _solve3(m, bt, xt)
            cov = spt - (bp[0] * xt[0] + bp[1] * xt[1] + bp[2] * xt[2])
            vp = spp - (bp[0] * xp[0] + bp[1] * xp[1] + bp[2] * xp[2])
            vt = stt - (bt[0] * xt[0] + bt[1] * xt[1] + bt[2] * xt[2])
            den = math.sqrt(max(vp, 0.0) * max(vt, 0.0))
            if den < 1e-9:
                den = 1e-9
            out[i, j] = cov / den


def _candidate_patches(
    gray_b: np.ndarray,
    projection: CompiledProjection,
    plane_b0: np.ndarray,
    scales: np.ndarray,
    direction: np.ndarray,
    sheet_n: np.ndarray | None,
    sheet_o: float,
    step: np.ndarray,
    half: np.ndarray,
    weight: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The (N, S, K) patches of frame b (float64, NaN where not seen) and their sample
    weights (N, 1 or S, K) of :func:`match_laser_points`' candidates: patch sample k of
    point n moved by ``scales[n, s]`` along ``direction`` (Eq. 17), projected by the
    camera's compiled ``projection`` and sampled bilinearly.

    Bit-identical to translating every sample (:func:`_translated`), projecting them
    (:meth:`CameraModel.project`), sampling the valid ones (:func:`sample_bilinear`)
    and weighting off the laser sheet (:func:`_off_sheet_weight`), but one compiled
    pass writes only the pixels (as ``cv2.remap`` maps) and weights, and one remap
    samples them.
    """
    n_pts, n_s, k_len = plane_b0.shape[0], scales.shape[1], plane_b0.shape[1]
    total = n_pts * n_s * k_len
    rows = max(-(-total // 4096), 1)
    # candidate_maps writes every one of the first ``total`` entries: only the tail filled.
    map_x = np.empty(rows * 4096, np.float32)
    map_y = np.empty(rows * 4096, np.float32)
    map_x[total:] = -1.0
    map_y[total:] = -1.0
    with_sheet = sheet_n is not None
    w = np.empty((n_pts, n_s, k_len)) if with_sheet else np.empty((0, 0, 0))
    normal = np.asarray(sheet_n if with_sheet else np.zeros(3), float)
    candidate_maps(  # bit for bit _candidate_maps (the reference), a candidate's samples as a block
        plane_b0, scales, direction, projection.kind, projection.params, with_sheet, normal, float(sheet_o), step, half, weight, _OUTSIDE, map_x, map_y, w,
    )
    fill = np.nan if gray_b.dtype.kind == "f" else 0
    out = cv2.remap(
        gray_b, map_x.reshape(rows, 4096), map_y.reshape(rows, 4096), cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT, borderValue=fill,
    )
    vals = out.reshape(-1)[:total].astype(np.result_type(gray_b.dtype, np.nan))
    invalid = map_x[:total] == _OUTSIDE
    vals[invalid] = np.nan
    return vals.reshape(n_pts, n_s, k_len), (w if with_sheet else weight[:, None, :])


_OUTSIDE = np.float32(-1.0e6)  # a remap coordinate far outside any image: not seen


@numba.njit(cache=True, error_model="numpy")
def _candidate_maps(
    plane, scales, direction, kind, params, with_sheet, normal, offset, step, half, weight, map_x, map_y, w,
):  # pragma: no cover - compiled
    """The pixels (float32 remap maps, :data:`_OUTSIDE` where not valid) and, with the
    sheet, the weights of :func:`_candidate_patches`, point by point."""
    n_pts, k_len = plane.shape[0], plane.shape[1]
    n_s = scales.shape[1]
    idx = 0
    for i in range(n_pts):
        for j in range(n_s):
            s0 = scales[i, j] * direction[0]
            s1 = scales[i, j] * direction[1]
            s2 = scales[i, j] * direction[2]
            for k in range(k_len):
                x = plane[i, k, 0] + s0
                y = plane[i, k, 1] + s1
                z = plane[i, k, 2] + s2
                col, row, ok = project_point(kind, params, x, y, z)
                if ok:
                    map_x[idx] = col
                    map_y[idx] = row
                else:
                    map_x[idx] = _OUTSIDE
                    map_y[idx] = _OUTSIDE
                if with_sheet:
                    along = x * normal[0] + y * normal[1] + z * normal[2]
                    rows = abs(along + offset) / step[i]
                    w[i, j, k] = weight[i, k] * (1.0 if rows > half[i] else 0.0)
                idx += 1


@numba.njit(cache=True)
def _translated(plane, scales, direction):  # pragma: no cover - compiled
    """(N, S, K, 3) points ``plane[n, k] + scales[n, s] * direction``: the NumPy
    broadcast ``plane[:, None] + scales[:, :, None, None] * direction`` (same two
    roundings), without its length-3 inner loops."""
    n_pts, k_len = plane.shape[0], plane.shape[1]
    n_s = scales.shape[1]
    out = np.empty((n_pts, n_s, k_len, 3))
    for i in range(n_pts):
        for j in range(n_s):
            s0 = scales[i, j] * direction[0]
            s1 = scales[i, j] * direction[1]
            s2 = scales[i, j] * direction[2]
            for k in range(k_len):
                out[i, j, k, 0] = plane[i, k, 0] + s0
                out[i, j, k, 1] = plane[i, k, 1] + s1
                out[i, j, k, 2] = plane[i, k, 2] + s2
    return out


@numba.njit(cache=True)
def _off_sheet_weight(along_normal, offset, step, half, weight):  # pragma: no cover - compiled
    """(N, S, K) ``weight[:, None, :] * (abs(along_normal + offset) / step > half)``
    (``step``, ``half``: (N,) per point; ``weight``: (N, K)), the NumPy expression's
    operations in its order."""
    n_pts, n_s, k_len = along_normal.shape
    out = np.empty((n_pts, n_s, k_len))
    for i in range(n_pts):
        for j in range(n_s):
            for k in range(k_len):
                rows = abs(along_normal[i, j, k] + offset) / step[i]
                out[i, j, k] = weight[i, k] * (1.0 if rows > half[i] else 0.0)
    return out


def _sheet(points: np.ndarray) -> tuple[np.ndarray | None, float]:
    """Plane n.x + o = 0 through (N, 3) laser points (their sheet), or (None, 0)."""
    ok = np.all(np.isfinite(points), axis=1)
    if ok.sum() < 3:
        return None, 0.0
    p = points[ok]
    c = p.mean(axis=0)
    _, sv, vt = np.linalg.svd(p - c, full_matrices=False)
    if sv[1] <= 1e-9:  # collinear: no plane
        return None, 0.0
    n = vt[2]
    return n, float(-n @ c)


class _Templates(NamedTuple):
    """Frame a's patches on the wall's tangent plane at N laser points, K samples each."""

    points: np.ndarray  # (N, 3) laser points in rig a (mm)
    ok_a: np.ndarray  # (N,) bool: the point projects into frame a
    step: np.ndarray  # (N,) sample spacing, about one pixel of frame a (mm)
    plane: np.ndarray  # (N, K, 3) sample points in rig a (mm)
    template: np.ndarray  # (N, K) grey levels of frame a, NaN off the image
    half: np.ndarray  # (N,) half width of the masked stripe (samples)
    weight: np.ndarray  # (N, K) 0 on the laser stripe, 1 elsewhere
    basis: np.ndarray | None  # (2, K) brightness-plane basis when detrending, else None
    std: np.ndarray  # (N,) std of the template off the stripe (grey levels)


def _templates(
    gray_a: np.ndarray, camera: CameraModel, P: np.ndarray, cfg: LaserScaleConfig
) -> _Templates:
    """Sample (H, W) ``gray_a`` on a (2 r + 1)^2 grid tangent to the wall at each of
    the (N, 3) laser points ``P`` (mm, rig a), the stripe masked out of the weights."""
    # Tangent plane of the wall at each point: radial normal about the rig axis.
    rho = np.hypot(P[:, 0], P[:, 1])
    sx = np.stack([-P[:, 1] / rho, P[:, 0] / rho, np.zeros(len(P))], axis=1)  # around the pipe
    sy = np.tile([0.0, 0.0, 1.0], (len(P), 1))  # along the pipe
    # Sample spacing: about one pixel of frame a at the point.
    px_a, ok_a = camera.project(P)
    step = np.linalg.norm(P, axis=1) * camera.pixel_angle(np.nan_to_num(px_a), (1.0, 0.0))
    step = np.clip(np.nan_to_num(step, nan=1.0), 0.05, 5.0)
    r = cfg.patch_radius
    grid = np.arange(-r, r + 1, dtype=float)
    gu, gv = np.meshgrid(grid, grid)
    gu, gv = gu.ravel(), gv.ravel()
    offsets = (gu[None, :, None] * sx[:, None, :] + gv[None, :, None] * sy[:, None, :]) * step[
        :, None, None
    ]
    plane = P[:, None, :] + offsets  # (N, K, 3) in rig a
    K = plane.shape[1]
    px, valid = camera.project(plane.reshape(-1, 3))
    template = np.where(valid, sample_bilinear(gray_a, np.nan_to_num(px, nan=-10.0)), np.nan).reshape(
        len(P), K
    )
    half = np.maximum(cfg.stripe_half_width_mm / step, cfg.stripe_half_width_px)
    weight = (np.abs(gv)[None, :] > half[:, None]).astype(float)  # stripe masked
    basis = np.vstack([gu, gv]) / max(r, 1) if cfg.detrend else None
    std = np.nanstd(np.where(weight > 0, template, np.nan), axis=1)
    return _Templates(P, ok_a, step, plane, template, half, weight, basis, std)


@dataclass(frozen=True, eq=False)
class _Scorer:
    """NCC of frame a's templates with frame b's patches at candidate lengths s (mm):
    the samples moved to rig b as R x + s d, frame b's own laser sheet left out."""

    gray_b: np.ndarray  # (H, W) frame b without the laser's channel
    camera: CameraModel
    projection: CompiledProjection | None  # the camera's compiled projection, if any
    plane_b0: np.ndarray  # (N, K, 3) template samples rotated into rig b (mm)
    direction: np.ndarray  # (3,) unit translation direction d
    sheet_n: np.ndarray | None  # (3,) laser sheet normal (rig a = rig b), or None
    sheet_o: float  # sheet offset (mm): n.x + o = 0
    tp: _Templates

    def __call__(self, scales: np.ndarray) -> np.ndarray:
        """(N, S) candidate lengths (mm) -> (N, S) NCC."""
        tp = self.tp
        if self.projection is not None:  # the same values in one compiled pass, without the (N, S, K, 3) points
            patches, w = _candidate_patches(
                self.gray_b, self.projection, self.plane_b0,
                np.ascontiguousarray(scales, dtype=float), self.direction,
                self.sheet_n, self.sheet_o, tp.step, tp.half, tp.weight,
            )
            return _ncc(tp.template, patches, w, tp.basis)
        pts_b = _translated(  # (N, S, K, 3)
            self.plane_b0, np.ascontiguousarray(scales, dtype=float), self.direction
        )
        pix, ok = self.camera.project(pts_b.reshape(-1, 3))
        # Only the valid samples are read (the others are NaN, as they were when every
        # pixel was sampled and then masked: bilinear samples do not depend on each other).
        vals = np.full(len(pix), np.nan, dtype=np.result_type(self.gray_b.dtype, np.nan))
        vals[ok] = sample_bilinear(self.gray_b, np.compress(ok, pix, axis=0))  # 6x pix[ok]
        patches = vals.reshape(len(tp.points), scales.shape[1], tp.plane.shape[1])
        w = tp.weight[:, None, :]
        if self.sheet_n is not None:
            # |pts_b . n + o| / step > half, times the template's weights (one pass).
            w = _off_sheet_weight(pts_b @ self.sheet_n, self.sheet_o, tp.step, tp.half, tp.weight)
        return _ncc(tp.template, patches, w, tp.basis)


def _coarse_scales(
    cfg: LaserScaleConfig, s_lo: float, s_hi: float, windowed: bool
) -> np.ndarray:
    """(S,) log-spaced candidate lengths in [s_lo, s_hi] (mm); a window keeps the
    full range's density per log unit."""
    steps = cfg.scale_steps
    if windowed:  # same density per log unit as the full search
        full = math.log(cfg.scale_range_mm[1] / cfg.scale_range_mm[0])
        steps = max(9, int(math.ceil(cfg.scale_steps * math.log(s_hi / s_lo) / full)) + 1)
    return np.geomspace(s_lo, s_hi, steps)


def _refine(
    coarse: np.ndarray, ncc: np.ndarray, score: _Scorer
) -> tuple[np.ndarray, np.ndarray]:
    """Finer pass around each point's best of the (S,) ``coarse`` lengths (NCC (N, S)),
    then a parabola through the best three: (N,) log length (log mm) and its NCC."""
    best = np.argmax(ncc, axis=1)
    ratio = coarse[1] / coarse[0]
    fine_offsets = np.geomspace(1 / ratio, ratio, 21)
    fine = coarse[best][:, None] * fine_offsets[None, :]
    ncc_f = score(fine)
    k = np.clip(np.argmax(ncc_f, axis=1), 1, fine.shape[1] - 2)
    rows = np.arange(len(ncc))
    y0, y1, y2 = ncc_f[rows, k - 1], ncc_f[rows, k], ncc_f[rows, k + 1]
    denom = y0 - 2 * y1 + y2
    safe = np.abs(denom) > 1e-12
    off = np.where(safe, 0.5 * (y0 - y2) / np.where(safe, denom, 1.0), 0.0).clip(-0.5, 0.5)
    log_s = np.log(fine[rows, k]) + off * np.log(fine_offsets[1] / fine_offsets[0])
    return log_s, y1


def _combined_scale(s_pt: np.ndarray) -> tuple[float, np.ndarray]:
    """Eq. (17) over (M,) per-point lengths (mm): the median of the log ratios after
    dropping outliers (3 MAD); returns the scale (mm) and the (M,) inlier mask."""
    # Eq. (17): min_l sum_k |log p_k - log l p'_k|, p'_k the unit-scale SfM point: the median.
    log_ratio = np.log(s_pt)
    med = float(np.median(log_ratio))
    mad = float(np.median(np.abs(log_ratio - med))) * 1.4826 + 1e-6
    inlier = np.abs(log_ratio - med) < 3.0 * mad + 0.02
    return float(np.exp(np.median(log_ratio[inlier]))), inlier


class _Search(NamedTuple):
    """One frame pair's Eq. (17) search: frame a's templates and frame b's scorer."""

    score: _Scorer
    tp: _Templates
    pts_idx: np.ndarray  # (N,) indices of the points tried into the caller's points
    rotation: np.ndarray  # (3, 3) b_from_a rotation
    direction: np.ndarray  # (3,) unit b_from_a translation direction


def _search(
    gray_a: np.ndarray,
    gray_b: np.ndarray,
    camera: CameraModel,
    laser_points_in_a: np.ndarray,
    b_from_a_rotation: np.ndarray,
    b_from_a_direction: np.ndarray,
    cfg: LaserScaleConfig,
) -> _Search | None:
    """The templates of at most ``cfg.max_points`` laser points (evenly around the ring)
    and the scorer of their candidates in frame b; None without points."""
    pts = np.asarray(laser_points_in_a, float)
    if len(pts) == 0:
        return None
    if len(pts) > cfg.max_points:
        pts_idx = np.linspace(0, len(pts) - 1, cfg.max_points).round().astype(int)
    else:
        pts_idx = np.arange(len(pts))
    tp = _templates(gray_a, camera, pts[pts_idx], cfg)
    R = np.asarray(b_from_a_rotation, float)
    d = np.asarray(b_from_a_direction, float) / np.linalg.norm(b_from_a_direction)
    plane_b0 = tp.plane @ R.T  # (N, K, 3) rotated into rig b, before the translation
    # Frame b's own stripe: the laser sheet moved with the robot, so in rig b it lies
    # where it lay in rig a. Its light leaks into the grey image (colour crosstalk, blur)
    # and, left in the patches, pulls every match towards zero motion (measured on a
    # 585 mm random rig: -9 % with true motion). Samples near the sheet in rig b are
    # left out of each candidate's correlation as they are out of the template.
    sheet_n, sheet_o = _sheet(pts)
    projection = camera.compiled_projection()
    score = _Scorer(gray_b, camera, projection, plane_b0, d, sheet_n, sheet_o, tp)
    return _Search(score, tp, pts_idx, R, d)


def _empty(peak_s: np.ndarray | None = None, peak_c: np.ndarray | None = None) -> LaserMatches:
    """No matches (the consensus peaks, if any, kept)."""
    z = np.zeros(0)
    return LaserMatches(
        np.zeros(0, int), z, np.zeros((0, 2)), z, math.nan,
        z if peak_s is None else peak_s, z if peak_c is None else peak_c,
    )


def _matches(
    search: _Search,
    camera: CameraModel,
    coarse: np.ndarray,
    ncc: np.ndarray,
    cfg: LaserScaleConfig,
    window: bool = False,
) -> LaserMatches:
    """The consensus peaks, each point's refined length and Eq. (17) from the (N, S)
    NCC of the (S,) ``coarse`` candidates. ``window``: the candidates are a window of
    the full search, whose first and last are not peaks (the curve goes on beyond them):
    no consensus peak and no point's best is taken there."""
    tp = search.tp
    tmpl_ok = tp.std > cfg.min_template_std
    peak_s, peak_c = consensus_peaks(coarse, ncc[tp.ok_a & tmpl_ok])
    if window:
        inner = (peak_s > coarse[0]) & (peak_s < coarse[-1])
        peak_s, peak_c = peak_s[inner], peak_c[inner]
    log_s, best_ncc = _refine(coarse, ncc, search.score)
    good = tp.ok_a & (best_ncc > cfg.min_ncc) & tmpl_ok & np.isfinite(log_s)
    if window:
        best = np.argmax(ncc, axis=1)
        good &= (best > 0) & (best < len(coarse) - 1)
    if not good.any():
        return _empty(peak_s, peak_c)
    s_pt = np.exp(log_s[good])
    R, d = search.rotation, search.direction
    pix_b, _ = camera.project(tp.points[good] @ R.T + s_pt[:, None] * d)
    scale, inlier = _combined_scale(s_pt)
    return LaserMatches(
        index=search.pts_idx[good][inlier],
        scale_mm=s_pt[inlier],
        pixels_b=pix_b[inlier],
        ncc=best_ncc[good][inlier],
        scale=scale,
        peak_scales_mm=peak_s,
        peak_scores=peak_c,
    )


def match_laser_points(
    gray_a: np.ndarray,
    gray_b: np.ndarray,
    camera: CameraModel,
    laser_points_in_a: np.ndarray,
    b_from_a_rotation: np.ndarray,
    b_from_a_direction: np.ndarray,
    config: LaserScaleConfig | None = None,
    scale_window_mm: tuple[float, float] | None = None,
) -> LaserMatches:
    """Find frame a's laser points in frame b along the epipolar curve; Eq. (17) scale.

    Args:
        gray_a, gray_b: (H, W) float32 images without the laser's channel (e.g. green).
        camera: the omni camera.
        laser_points_in_a: (N, 3) metric laser points in rig a (mm).
        b_from_a_rotation: (3, 3) rotation of rig_b_from_rig_a.
        b_from_a_direction: (3,) unit translation direction of rig_b_from_rig_a:
            p_b = R p_a + s d for the unknown length s (mm).
        config: matching settings.
        scale_window_mm: (min, max) translation lengths searched instead of the
            config's full range (used once the length is known roughly, so that a
            periodic wall cannot pull a point to the next course).

    Returns:
        The matches and the combined scale (translation length, mm).
    """
    cfg = config or LaserScaleConfig()
    s_lo, s_hi = cfg.scale_range_mm if scale_window_mm is None else scale_window_mm
    search = _search(
        gray_a, gray_b, camera, laser_points_in_a, b_from_a_rotation, b_from_a_direction, cfg
    )
    if search is None or not (0 < s_lo < s_hi):
        return _empty()
    # Candidate translation lengths: log-spaced, then a finer pass around each best.
    coarse = _coarse_scales(cfg, s_lo, s_hi, scale_window_mm is not None)
    ncc = search.score(np.tile(coarse, (len(search.tp.points), 1)))
    return _matches(search, camera, coarse, ncc, cfg)


# A windowed answer stands only when the consensus of its points falls at both ends of
# the window to at most this fraction of its peak: the peak is then the curve's own, not
# the slope of a stronger one outside.
WINDOW_EDGE_RATIO = 0.5
# ... and when at least this share of the points with a usable template match inside it
# (NCC above ``min_ncc`` at an inner candidate): a stray local peak matches few.
WINDOW_MIN_MATCHED = 0.5
# Fewest candidates a window holds (else the full search runs).
WINDOW_MIN_CANDIDATES = 5


def match_laser_points_near(
    gray_a: np.ndarray,
    gray_b: np.ndarray,
    camera: CameraModel,
    laser_points_in_a: np.ndarray,
    b_from_a_rotation: np.ndarray,
    b_from_a_direction: np.ndarray,
    config: LaserScaleConfig,
    expected_mm: float,
    agree_log: float,
) -> tuple[LaserMatches, bool]:
    """:func:`match_laser_points` over the full range, searched first only near an
    independent estimate of the length.

    The window is the full search's candidates within a factor
    ``exp(config.prior_window_log)`` of ``expected_mm``. Its answer stands when its
    Eq. (17) length agrees with ``expected_mm`` within ``agree_log`` (|log ratio|), at
    least :data:`WINDOW_MIN_MATCHED` of the points with a usable template match, and
    their consensus peaks inside the window and falls at both ends to at most
    :data:`WINDOW_EDGE_RATIO` of that peak. Otherwise the remaining candidates are
    scored too and the answer is the full search's, bit for bit. The consensus peaks of
    a window's answer are those inside it (a course off beyond it is not seen: the
    expected length, measured without the laser, chose the course).

    Returns:
        The matches and whether they are the window's (True) or the full search's.
    """
    cfg = config
    search = _search(
        gray_a, gray_b, camera, laser_points_in_a, b_from_a_rotation, b_from_a_direction, cfg
    )
    if search is None:
        return _empty(), False
    full = _coarse_scales(cfg, *cfg.scale_range_mm, False)
    n = len(search.tp.points)
    lo, hi = 0, len(full)
    if math.isfinite(expected_mm) and expected_mm > 0 and cfg.prior_window_log > 0:
        lo = int(np.searchsorted(full, expected_mm * math.exp(-cfg.prior_window_log)))
        hi = int(np.searchsorted(full, expected_mm * math.exp(cfg.prior_window_log), "right"))
    if hi - lo < WINDOW_MIN_CANDIDATES or hi - lo == len(full):
        return _matches(search, camera, full, search.score(np.tile(full, (n, 1))), cfg), False
    ncc_w = search.score(np.tile(full[lo:hi], (n, 1)))
    lm = _matches(search, camera, full[lo:hi], ncc_w, cfg, window=True)
    tp = search.tp
    rows = ncc_w[tp.ok_a & (tp.std > cfg.min_template_std)]
    if (
        len(rows)
        and len(lm.index) >= WINDOW_MIN_MATCHED * len(rows)
        and abs(math.log(lm.scale / expected_mm)) <= agree_log
    ):
        c = np.mean(np.clip(rows, 0.0, 1.0) ** 2, axis=0)
        top = int(np.argmax(c))
        if 0 < top < len(c) - 1 and max(c[0], c[-1]) <= WINDOW_EDGE_RATIO * c[top]:
            return lm, True
    parts = [
        ncc_w if part is None else search.score(np.tile(part, (n, 1)))
        for part in (full[:lo], None, full[hi:])
        if part is None or len(part)
    ]
    return _matches(search, camera, full, np.concatenate(parts, axis=1), cfg), False
