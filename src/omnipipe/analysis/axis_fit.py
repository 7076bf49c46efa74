"""The pipe's axis: the piecewise centreline and the whole run's cylinder
(:func:`fit_axis`), re-centred on each station's own section with the points' pipe
coordinates about it (:func:`recentred_line`: (N,) sigma mm along the axis, rho mm from
it, theta rad), and the break planes at offset joints (:func:`offset_breaks`) either side
of which the sections are fitted separately. Points are world-frame (N, 3), mm.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import Executor

import numpy as np

from omnipipe.analysis.centreline import (
    COORDINATE_BLOCK,
    Centreline,
    fit_centreline,
    recentred,
    rig_axis_prior,
)
from omnipipe.analysis.cylinder import Cylinder, fit_cylinder
from omnipipe.analysis.feature_types import Joint, PointFeature
from omnipipe.analysis.records import AnalysisConfig, AnalysisInputs, section_config
from omnipipe.analysis.station_profiles import ring_groups
from omnipipe.analysis.stations import ring_cut, section_order
from omnipipe.analysis.wall_profile import fit_wall_profile
from omnipipe.executor import InlineExecutor, chunks, ordered_map
from omnipipe.spill import ScratchWriter, drop_pages


def recentred_line(
    config: AnalysisConfig,
    inputs: AnalysisInputs,
    line: Centreline,
    pts: np.ndarray,
    frame: np.ndarray,
    window: float,
    breaks: Sequence[tuple[np.ndarray, np.ndarray]],
    executor: Executor | None = None,
) -> tuple[Centreline, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The centreline re-centred on each station's own section (their fits on
    ``executor``; None: here; the result is the same), and the points' (N,) pipe
    coordinates (sigma, rho, theta) about it."""
    centres = _section_centres(config, line, pts, frame, executor)
    prior = rig_axis_prior(np.asarray(inputs.world_from_rig, float)[: len(line.arc_mm)], line.centre)
    line = recentred(line, centres, inputs.reference_from_world, 0.5 * window, breaks, axis_prior=prior)
    # The coordinates wait in the run's scratch, read when needed (24 bytes a point),
    # written there a block at a time (each point's numbers those of the whole run's).
    out = [ScratchWriter(len(frame), float) for _ in range(3)]
    for a in range(0, len(frame), COORDINATE_BLOCK):
        for w, part in zip(out, line.coordinates(pts[a : a + COORDINATE_BLOCK], frame[a : a + COORDINATE_BLOCK]), strict=True):
            w.write(part)
    sigma, rho, theta = (w.array() for w in out)
    drop_pages()  # the points' pages, read again when needed (omnipipe.spill)
    return line, (sigma, rho, theta)


def offset_breaks(features: Sequence[PointFeature], line: Centreline) -> list[tuple[np.ndarray, np.ndarray]]:
    """(point, normal) world planes at the joints whose offset is significant (>= 0.5 mm
    and 3 sigma): the sections either side are fitted separately."""
    out = []
    for f in features:
        if not isinstance(f, Joint) or f.offset_mm is None:
            continue
        if f.offset_mm < max(0.5, 3.0 * (f.offset_sigma_mm or 0.0)):
            continue
        k = int(np.argmin(np.abs(line.arc_mm - f.axial_mm)))
        t = line.tangent[k]
        out.append((line.centre[k] + (f.axial_mm - line.arc_mm[k]) * t, t))
    return out


def fit_axis(
    config: AnalysisConfig,
    inputs: AnalysisInputs,
    pts: np.ndarray,
    frame: np.ndarray,
    poses: np.ndarray,
    executor: Executor | None,
    breaks: Sequence[tuple[np.ndarray, np.ndarray]] = (),
) -> tuple[Centreline, Cylinder | None, float]:
    """The piecewise centreline (no window across a break plane: :func:`.fit_centreline`),
    the single cylinder of the whole run when the centreline is straight (None: it
    bends) and the window of the piecewise fits (mm)."""
    rings = _RingPoints(pts, ring_groups(frame, len(poses)))
    axis_guess = poses[:, :3, 2]
    # A first whole-run fit gives the scale for the window.
    sample = pts[np.linspace(0, len(pts) - 1, min(len(pts), 6000)).astype(int)]
    rough = fit_cylinder(sample, np.mean(axis_guess, axis=0), loss_scale_mm=config.loss_scale_mm)
    if config.window_mm:
        window = config.window_mm
    else:
        # A quarter diameter follows bends (a chord's sagitta there is L^2 / 8 R_bend), but
        # never fewer than about three rings.
        cents = np.array([r.mean(axis=0) for r in rings if len(r) >= 12])
        spacing = float(np.median(np.linalg.norm(np.diff(cents, axis=0), axis=1))) if len(cents) > 1 else 0.0
        window = max(0.25 * rough.diameter_mm, 3.0 * spacing)
    line = fit_centreline(
        rings,
        axis_guess,
        inputs.reference_from_world,
        window_mm=window,
        loss_scale_mm=config.loss_scale_mm,
        executor=executor,
        breaks=breaks,
    )
    if line.straightness_mm() > config.straight_tolerance_mm:
        return line, None, window
    whole = fit_cylinder(
        pts[np.linspace(0, len(pts) - 1, min(len(pts), 20000)).astype(int)],
        rough.axis,
        loss_scale_mm=config.loss_scale_mm,
    )
    return line, whole, window


class _RingPoints(Sequence[np.ndarray]):
    """Each ring's (M_k, 3) points of the run's (N, 3) ``pts``, gathered when indexed
    (the same arrays as ``[pts[g] for g in groups]``, not held: a copy of every point)."""

    def __init__(self, pts: np.ndarray, groups: list[np.ndarray]) -> None:
        self.pts, self.groups = pts, groups

    def __len__(self) -> int:
        return len(self.groups)

    def __getitem__(self, k: int) -> np.ndarray:  # type: ignore[override]
        return self.pts[self.groups[k]]


def _section_centres(
    config: AnalysisConfig, line: Centreline, pts: np.ndarray, frame: np.ndarray, executor: Executor | None = None
) -> np.ndarray:
    """(K, 2) each ring's section centre in its station's (normal, binormal) plane of
    ``line``: the order-1 terms of its wall profile (0 for a ring too sparse to fit).
    Each ring's coordinates are taken on their own (the same numbers as the whole run's):
    no (N,) array is held. The rings' fits on ``executor`` (:mod:`omnipipe.executor`, a
    few rings a task; None: here; the result is the same)."""
    k = len(line.arc_mm)
    out = np.zeros((k, 2))
    groups = ring_groups(frame, k)
    fitted = [i for i in range(k) if len(groups[i]) >= 12]
    ex = executor or InlineExecutor()
    parts = chunks(len(fitted), ex)
    # Each task's rings gathered only when it is sent (ordered_map keeps a few in flight).
    sent = (
        (config, line, [(pts[on], frame[on]) for on in (groups[fitted[j]] for j in part)]) for part in parts
    )
    for part, centres in zip(parts, ordered_map(ex, _centres_task, sent), strict=True):
        for j, c in zip(part, centres, strict=True):
            if c is not None:
                out[fitted[j]] = c
    return out


def _centres_task(
    sent: tuple[AnalysisConfig, Centreline, list[tuple[np.ndarray, np.ndarray]]],
) -> list[np.ndarray | None]:
    """One task of :func:`_section_centres`: each ring's ((M, 3) world points, (M,) its
    ring index) section centre (the order-1 terms of its wall profile, mm), or None
    where the ring supports no order 1."""
    config, line, rings = sent
    sec_config = section_config(config)
    out: list[np.ndarray | None] = []
    for pts, frame in rings:
        _, rho, theta = line.coordinates(pts, frame)
        cut, coverage = ring_cut(theta, sec_config)
        order = section_order(cut, coverage, config.profile_order, sec_config)
        out.append(fit_wall_profile(theta, rho, order, config.loss_scale_mm)[1:3] if order >= 1 else None)
    return out
