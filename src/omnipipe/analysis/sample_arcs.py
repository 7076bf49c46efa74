"""The samples' arcs about an angle, made for the samples asked for only.

A lateral's outline is measured in arc mm about its angle (``u``). Making ``u`` for every
sample of the run (and ``u`` minus the outline's centre, and the outline's masks) cost a
few (N,) float64 arrays per hole: 14 MB each at 2,400 continuous frames at 400x300.
:class:`SampleArcs` makes the arcs of the samples indexed (a ring's, a block's), and
:func:`within_ellipses` tests the outline a block of :data:`BLOCK` samples at a time.
Every value is the whole-run expression's, element by element.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

BLOCK = 1 << 16
"""Samples tested at a time by :func:`within_ellipses`."""


class SampleArcs:
    """(N,) each sample's arc (mm) about the angle ``at`` (rad): ``((theta - at + pi) mod
    2 pi - pi) x radius``, minus ``offset`` (mm) when given; made for the samples an index
    selects (anything that indexes ``theta``: a slice, indices, a boolean mask), none held.

    Attributes:
        theta: (N,) the samples' angles (rad; not copied).
        at: the angle the arcs are measured from (rad).
        radius: the wall radius (mm).
        offset: subtracted from every arc (mm), or None.
    """

    def __init__(self, theta: np.ndarray, at: float, radius: float, offset: float | None = None) -> None:
        self.theta, self.at, self.radius, self.offset = theta, at, radius, offset

    def __len__(self) -> int:
        return len(self.theta)

    def __getitem__(self, sel: object) -> np.ndarray:
        u = ((self.theta[sel] - self.at + np.pi) % (2 * np.pi) - np.pi) * self.radius
        return u if self.offset is None else u - self.offset

    def minus(self, offset: float) -> SampleArcs:
        """The same arcs less ``offset`` (mm): ``u - offset`` of the whole-run ``u``."""
        if self.offset is not None:
            raise ValueError("SampleArcs.minus: arcs already offset")
        return SampleArcs(self.theta, self.at, self.radius, offset)


def within_ellipses(
    sigma: np.ndarray, u: SampleArcs, ellipses: Sequence[tuple[float, float, float, float]]
) -> np.ndarray:
    """(N,) True for the samples inside any of ``ellipses`` (axial centre, axial semi-axis,
    arc centre, arc semi-axis; mm): ``((sigma - z) / a) ** 2 + ((u - c) / b) ** 2 <= 1``
    with ``sigma`` the samples' axial positions and ``u`` their arcs. Tested
    :data:`BLOCK` samples at a time; the result's pages are written only where a block
    has a sample inside (a zeroed array: the rest stays unmapped)."""
    out = np.zeros(len(sigma), bool)
    for s in range(0, len(sigma), BLOCK):
        blk = slice(s, min(s + BLOCK, len(sigma)))
        zb, ub = sigma[blk], u[blk]
        hit = np.zeros(len(zb), bool)
        for z, a, c, b in ellipses:
            hit |= ((zb - z) / a) ** 2 + ((ub - c) / b) ** 2 <= 1.0
        if hit.any():
            out[blk] = hit
    return out
