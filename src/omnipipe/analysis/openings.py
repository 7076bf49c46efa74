"""Openings in the wall seen as missing laser returns (issue 30): a lateral's hole.

Where the ring crosses a lateral's opening the light goes on into the branch: its wall
is lit only where it is close (a large branch, a steep angle), and otherwise the ring
returns nothing there. The deep samples of a lit branch wall are found by
:mod:`.features`; this module finds the other half of the evidence, the stretches of a
ring without samples:

* per ring, every angular gap between consecutive samples wider than ``min_steps``
  sample steps and ``min_arc_mm`` of wall (:func:`return_gaps`); a ring broken into
  more than ``max_gaps`` pieces (the shadow of a joint's step or a taper's edge on a
  tilted ring: random-features-small seeds 0 and 3 lost 6-14 stretches on such rings)
  tells no opening, nor does a ring spread along the axis over more than
  ``max_spread_rel`` x the radius (tilted some 15 deg or more to the fitted axis: a
  ring straddling a step in the section, whose angles do not map onto one wall; seed
  7's rings at a 95 mm reducer step spread over 0.9 R);
* a gap is an opening's only where the wall is seen at those angles by other rings
  of the run: the rings without samples across the gap's middle form one block along
  the axis around it, no longer than ``max_length_rel`` x the diameter, with a ring on
  both sides sampling those angles (:func:`local_gaps`; seed 21's first eight rings,
  bunched within 7 mm at a slow start, lost a shrinking stretch that no earlier ring
  could show to close). Standing water, a
  shadow of the rig or a dropout along the whole run miss the same angles on every
  ring, and are left to the stations' water cut (:mod:`.stations`);
* local gaps on rings next to each other along the axis (within 1.5 ring spacings)
  whose angles overlap are one opening (:func:`gap_clusters`), one chord per ring: a
  ring losing its light there in several pieces is a ragged shadow (seed 11's rings
  behind a steep reducer step lost 2-3 stretches each), not a hole's clean chord.

Angles are radians about the centreline (theta of :meth:`.Centreline.coordinates`),
axial positions mm.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass

import numpy as np

from omnipipe.analysis.feature_rings import robust_sine_fit
from omnipipe.analysis.ring_spans import RingIndices, RingSpans
from omnipipe.analysis.sample_arcs import SampleArcs


@dataclass(frozen=True)
class ReturnGap:
    """One ring's stretch without laser returns.

    Attributes:
        ring: the ring's index (the points' ``frame``).
        axial_mm: where the ring crosses the gap (the two bounding samples' mean axial
            position).
        start: angle (rad, [0, 2 pi)) of the last sample before the gap.
        width: angle (rad) from it to the first sample after the gap.
        step: the ring's median sample step (rad).
    """

    ring: int
    axial_mm: float
    start: float
    width: float
    step: float

    @property
    def centre(self) -> float:
        return (self.start + 0.5 * self.width) % (2.0 * math.pi)

    def covers(self, theta: np.ndarray) -> np.ndarray:
        """(M,) True for the angles inside the gap's middle half."""
        d = (np.asarray(theta) - self.start - 0.25 * self.width) % (2.0 * math.pi)
        return d <= 0.5 * self.width


def return_gaps(
    sigma: np.ndarray,
    theta: np.ndarray,
    frame: np.ndarray,
    radius_mm: float,
    min_arc_mm: float,
    min_steps: float = 4.0,
    max_gaps: int = 3,
    max_spread_rel: float = 0.5,
    lit: np.ndarray | None = None,
) -> list[ReturnGap]:
    """Every ring's gaps between consecutive samples (sorted by angle, around the seam)
    at least ``min_steps`` x its median sample step and ``min_arc_mm`` of wall wide
    (``radius_mm``: the wall radius the arc is taken at); none of a ring with more
    than ``max_gaps`` of them, or spread along the axis over ``max_spread_rel`` x
    ``radius_mm``. ``lit``: (N,) bool, the samples that count (None: all; the others are
    no returns). Each ring's samples are read on their own (:class:`.ring_spans.RingSpans`:
    the run's arrays are not copied)."""
    out: list[ReturnGap] = []
    spans = RingSpans(frame)
    for i, k in enumerate(spans.rings):
        s_k, t_k = spans.values(i, sigma), spans.values(i, theta)
        if lit is not None:
            keep = spans.values(i, lit)
            s_k, t_k = s_k[keep], t_k[keep]
        out += _ring_gaps(int(k), s_k, t_k, radius_mm, min_arc_mm, min_steps, max_gaps, max_spread_rel)
    return out


def _ring_gaps(
    k: int,
    sigma: np.ndarray,
    theta: np.ndarray,
    radius_mm: float,
    min_arc_mm: float,
    min_steps: float,
    max_gaps: int,
    max_spread_rel: float,
) -> list[ReturnGap]:
    """:func:`return_gaps` of ring ``k``'s (M,) samples (sigma mm, theta rad, ascending
    index order)."""
    if len(sigma) < 12 or np.ptp(sigma) > max_spread_rel * radius_mm:
        return []
    o = np.argsort(np.mod(theta, 2.0 * math.pi))
    t = np.mod(theta, 2.0 * math.pi)[o]
    s = sigma[o]
    gaps = np.diff(np.concatenate([t, [t[0] + 2.0 * math.pi]]))
    step = float(np.median(gaps))
    wide = np.flatnonzero(gaps >= max(min_steps * step, min_arc_mm / radius_mm))
    if len(wide) > max_gaps:
        return []
    out = []
    for i in wide:
        j = (i + 1) % len(t)
        out.append(ReturnGap(k, 0.5 * float(s[i] + s[j]), float(t[i]), float(gaps[i]), step))
    return out


def local_gaps(
    gaps: list[ReturnGap],
    theta: np.ndarray,
    frame: np.ndarray,
    ring_axial: dict[int, float],
    max_length_mm: float,
    lit: np.ndarray | None = None,
) -> list[ReturnGap]:
    """The gaps whose angles other rings of the run sample (see the module's
    docstring): the rings (ordered along the axis, ``ring_axial``: each ring's axial
    position) without a sample in the gap's middle half form a block around the gap's
    ring at most ``max_length_mm`` long, and a ring on either side of the block samples
    there. ``lit``: as for :func:`return_gaps`. A ring's angles are read when a gap's
    block reaches it (not the run's held)."""
    rings = sorted(ring_axial, key=lambda k: ring_axial[k])
    if len(rings) < 3:
        return []
    by_ring = _RingAngles(RingSpans(frame, np.array(rings)), theta, lit)
    slot = {k: i for i, k in enumerate(rings)}
    out = []
    for g in gaps:
        # The block's rings, walked out from the gap's ring only while they do not sample
        # its angles and the block stays short enough (each gap looks at its neighbours:
        # linear in the run).
        i = slot[g.ring]
        lo = i
        while lo > 0 and not g.covers(by_ring[rings[lo - 1]]).any() and ring_axial[rings[i]] - ring_axial[rings[lo]] <= max_length_mm:
            lo -= 1
        hi = i
        while hi < len(rings) - 1 and not g.covers(by_ring[rings[hi + 1]]).any() and ring_axial[rings[hi]] - ring_axial[rings[lo]] <= max_length_mm:
            hi += 1
        if lo == 0 or hi == len(rings) - 1:
            continue  # not seen to close on both sides: water, a shadow, the run's end
        if ring_axial[rings[hi]] - ring_axial[rings[lo]] > max_length_mm:
            continue
        out.append(g)
    return out


def ring_points(frame: np.ndarray, rings: np.ndarray) -> Mapping[int, np.ndarray]:
    """For each ring index in ``rings``, the indices of its points (``frame == k``,
    ascending), each made when asked (:class:`.ring_spans.RingIndices`: a binary search
    of the integrated run's ring-ordered ``frame``, one stable sort of any other): linear
    in the run, not one pass over every point per ring, and no index of every point held."""
    return RingIndices(RingSpans(frame, np.asarray(rings)))


def ring_angles(frame: np.ndarray, rings: np.ndarray, theta: np.ndarray, lit: np.ndarray | None = None) -> Mapping[int, np.ndarray]:
    """For each ring index in ``rings``, its points' angles ``theta`` (only the ``lit``
    ones: (N,) bool; None: all) in ascending index order, each read when asked (equal to
    a dict of ``theta[on[lit[on]]]`` per ring, without holding them)."""
    return _RingAngles(RingSpans(frame, np.asarray(rings)), theta, lit)


class _RingAngles(Mapping[int, np.ndarray]):
    """{ring: its ``lit`` samples' angles (rad, ascending index order)} of ``spans``'
    rings, each read when asked."""

    def __init__(self, spans: RingSpans, theta: np.ndarray, lit: np.ndarray | None) -> None:
        self.spans, self.theta, self.lit = spans, theta, lit
        self._slot = {int(k): i for i, k in enumerate(spans.rings)}

    def __getitem__(self, k: int) -> np.ndarray:
        i = self._slot[int(k)]
        t = self.spans.values(i, self.theta)
        return t if self.lit is None else t[self.spans.values(i, self.lit)]

    def __iter__(self) -> Iterator[int]:
        return iter(self._slot)

    def __len__(self) -> int:
        return len(self._slot)


def closes_both_sides(
    ring_axial: dict[int, float],
    wall_theta: dict[int, np.ndarray],
    inside: set[int],
    centre: float,
    half: float,
    max_length_mm: float,
) -> bool:
    """Whether an opening seen by the rings ``inside`` closes along the axis on both
    sides (the rule of :func:`local_gaps` for deep samples): the rings (ordered along the
    axis, ``ring_axial``) without a wall sample (``wall_theta``: each ring's wall
    samples' angles, rad) within ``half`` rad of ``centre`` form a block around them no
    longer than ``max_length_mm``, with a ring on either side sampling the wall there.
    Standing water cuts the rings at the same angles to the run's end, and the laser
    peaks found there on texture (no return from the water) stand far off the wall
    like a branch's: such a block reaches the first or last ring."""
    rings = sorted(ring_axial, key=lambda k: ring_axial[k])
    pos = [i for i, k in enumerate(rings) if k in inside]
    if len(rings) < 3 or not pos:
        return False

    def seen(k: int) -> bool:
        d = np.abs((wall_theta[k] - centre + math.pi) % (2.0 * math.pi) - math.pi)
        return bool(np.any(d <= half))

    lo, hi = min(pos), max(pos)
    while lo > 0 and not seen(rings[lo - 1]):
        lo -= 1
    while hi < len(rings) - 1 and not seen(rings[hi + 1]):
        hi += 1
    if lo == 0 or hi == len(rings) - 1:
        return False
    return ring_axial[rings[hi]] - ring_axial[rings[lo]] <= max_length_mm


def gap_clusters(gaps: list[ReturnGap], link_mm: float, min_rings: int = 2) -> list[list[ReturnGap]]:
    """The gaps linked into openings: two gaps on different rings within ``link_mm``
    along the axis whose angles overlap are one; each cluster spanning at least
    ``min_rings`` rings with one gap on each (see the module's docstring), largest
    first."""
    n = len(gaps)
    parent = list(range(n))

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a in range(n):
        for b in range(a + 1, n):
            ga, gb = gaps[a], gaps[b]
            if ga.ring == gb.ring or abs(ga.axial_mm - gb.axial_mm) > link_mm:
                continue
            d = abs((ga.centre - gb.centre + math.pi) % (2.0 * math.pi) - math.pi)
            if d < 0.5 * (ga.width + gb.width):
                parent[root(a)] = root(b)
    groups: dict[int, list[ReturnGap]] = {}
    for a in range(n):
        groups.setdefault(root(a), []).append(gaps[a])
    out = [g for g in groups.values() if len({x.ring for x in g}) >= min_rings and len({x.ring for x in g}) == len(g)]
    return sorted(out, key=len, reverse=True)


@dataclass(frozen=True)
class HoleExtent:
    """A hole's reach along the axis on its meridian, from the rings disturbed there.

    Attributes:
        lo_mm, hi_mm: its ends (axial mm): halfway between the last ring disturbed at
            the hole's angles and the first clean one beyond it.
        lo_sigma_mm, hi_sigma_mm: their 1-sigma (that spacing / sqrt(12)).
        chords: (M, 4) per ring disturbed there outside the chords it was grown from:
            axial position at the hole's angle, chord centre and half-width (arc mm),
            ring index.
        closed: (lower, upper) whether the hole was seen to close on that side; where
            not (the growth reached the run's end or a joint), the end is the last
            disturbed ring's position, a bound only.
    """

    lo_mm: float
    hi_mm: float
    lo_sigma_mm: float
    hi_sigma_mm: float
    chords: np.ndarray
    closed: tuple[bool, bool] = (True, True)


def ring_axial(sigma: np.ndarray, phi: np.ndarray, at: float) -> float:
    """Axial position (mm) at angle ``at`` (rad) of a ring whose wall samples lie at
    (``sigma`` mm, ``phi`` rad): the plane sigma = a + b cos phi + c sin phi fitted to
    them (:func:`.feature_rings.robust_sine_fit`: twice, without the samples beyond 3
    robust sigmas and 0.5 mm: the rim's stray ones)."""
    p, _, _ = robust_sine_fit(sigma, phi, 2, 3.0, 0.5)
    return float(p[0] + p[1] * math.cos(at) + p[2] * math.sin(at))


def _disturbed_chord(
    u: np.ndarray, dev: np.ndarray, half: float, step: float, low: float, min_stray: int = 4
) -> tuple[float, float, bool, bool] | None:
    """(centre, half-width arc mm, whether samples stray, whether returns are lost) of
    what disturbs one ring within ``half`` of the hole's centre (``u``: its samples' arc
    about it, ``dev``: their deviations): its stretches without samples wider than 2.5
    sample ``step`` s (lost returns), and its samples beyond ``low`` either way with a
    neighbour that is too (stray); None if nothing does. Without lost returns the
    chord is empty (0, 0): such a ring's light section lies beside the rim, outside
    the hole, its peaks biased by the rim's image or light scattered there."""
    inw = np.abs(u) <= half + step
    if not inw.any():
        return 0.0, half, False, True  # the whole window dark: the light lost in the hole
    o = np.argsort(u[inw])
    uu, dd = u[inw][o], dev[inw][o]
    ends: list[float] = []
    edges = np.concatenate([[-half - step], uu, [half + step]])
    for i in np.flatnonzero(np.diff(edges) > 2.5 * step):
        ends += [float(edges[i]), float(edges[i + 1])]
    off = np.abs(dd) > low
    nb = np.zeros(len(off), bool)
    nb[1:] |= off[:-1]
    nb[:-1] |= off[1:]
    stray = off & nb
    if not ends:  # a few stray samples: light scattered at the rim, nothing
        return (0.0, 0.0, True, False) if stray.sum() >= min_stray else None
    ends += [float(x) for x in uu[stray]]
    lo, hi = max(min(ends), -half), min(max(ends), half)
    return 0.5 * (lo + hi), 0.5 * max(hi - lo, step), bool(stray.any()), True


DARK_WIDENING = 1.25
"""Growing a hole outwards its outline narrows: a ring with lost returns only (no stray
samples showing the rim) whose lost stretch is more than this times the last grown
ring's (plus a sample step) lost its light to something else (a dark band past the
rim), not to the hole."""


def hole_extent(
    ring_z: dict[int, float],
    u: np.ndarray | SampleArcs,
    dev: np.ndarray,
    frame: np.ndarray,
    inside: set[int],
    half_width: float,
    low: float,
    stops: list[tuple[float, float]],
    z_at: Callable[[int, float], float] | None = None,
    inside_chords: Mapping[int, tuple[float, float]] | None = None,
) -> HoleExtent | None:
    """Grow a hole seen by the rings ``inside`` along the axis over the rings next to it
    that are disturbed at its angles (:func:`_disturbed_chord`, within ``half_width`` arc
    mm of its centre; ``u``: every sample's arc about it, ``dev`` its deviation, ``low``
    the deviation that counts): on the side where the branch wall meets the main wall at
    an obtuse angle, it stays within the feature threshold, and the deep samples and the
    rings' lost stretches see only part of it. A ring there keeps lost returns; one
    with samples off the wall and none lost lies beside the rim, outside the hole; one
    with lost returns only, their stretch much wider than the last grown ring's
    (:data:`DARK_WIDENING`), is not the hole's either. ``ring_z``: each ring's axial
    position at the hole's angle. Rings in
    ``stops`` (axial bands: the joints' gaps) end the growth: a side reaching one or
    the run's end is open (:attr:`HoleExtent.closed`). None without a ring inside.

    ``z_at(k, c)``: ring k's axial position at arc ``c`` mm about the hole's centre (a
    ring tilted to the axis meets the hole off its meridian somewhere else along the
    axis): each end lies between the last ring in the hole, at its chord's centre
    (``inside_chords``: the rings ``inside``'s chord centre and half-width, arc mm;
    ``ring_z`` where none is given), and the first ring beyond it at the meridian, where
    the hole reaches furthest: halfway, or with the chords given where the outline
    closes beyond the last ring's chord (:func:`_tip`)."""
    order = sorted(ring_z, key=lambda k: ring_z[k])
    pos = [i for i, k in enumerate(order) if k in inside]
    if not pos:
        return None

    def at(k: int, c: float | None) -> float:
        return ring_z[k] if z_at is None or c is None else z_at(k, c)

    chords = {} if inside_chords is None else dict(inside_chords)
    ends, sig, rows, closed, last = [], [], [], [], []
    for direction, start in ((-1, min(pos)), (1, max(pos))):
        i, j, dark = start, start + direction, []
        z_last = at(order[start], chords[order[start]][0] if order[start] in chords else None)
        width = math.inf  # the last grown ring's chord half-width on this side
        while 0 <= j < len(order) and not any(a <= ring_z[order[j]] <= b for a, b in stops):
            on = frame == (k := order[j])
            uk = u[on]
            step = float(np.median(np.diff(np.sort(uk)))) if on.sum() >= 12 else 0.0
            got = _disturbed_chord(uk, dev[on], half_width, step, low) if step > 0 else None
            if got is None or (not got[2] and got[1] > DARK_WIDENING * width + step):
                break  # clean; or lost returns only, wider than the outline allows
            width = got[1] if got[3] else width
            # Rings only missing samples there count when a ring beyond shows stray samples (the
            # hole's light lost, not a shadow past its rim): with none lost, that ring, beside the rim.
            if not got[3]:
                if dark:
                    rows += dark
                    z_last, i = dark[-1][0], j - direction
                break
            dark.append((at(k, got[0]), got[0], got[1], float(k)))
            if got[2]:
                rows += dark
                z_last = dark[-1][0]
                dark, i = [], j
            j += direction
        j = i + direction
        shut = 0 <= j < len(order) and not any(a <= ring_z[order[j]] <= b for a, b in stops)
        z_out = ring_z[order[j]] if shut else z_last
        ends.append(0.5 * (z_last + z_out))
        sig.append(abs(z_out - z_last) / math.sqrt(12.0))
        closed.append(shut)
        last.append((z_last, z_out, order[i]))
    grown = np.array(rows).reshape(-1, 4)
    if inside_chords is not None:
        chords.update({int(k): (float(c), float(h)) for _, c, h, k in grown})
        ends = _tip(ends, [(z_in, z_out, chords.get(k, (0.0, 0.0))[1]) for z_in, z_out, k in last],
                    max((h for _, h in chords.values()), default=0.0))
    return HoleExtent(ends[0], ends[1], sig[0], sig[1], grown, (closed[0], closed[1]))


def _tip(ends: list[float], last: list[tuple[float, float, float]], widest: float) -> list[float]:
    """The hole's (lower, upper) ends moved from halfway between the last ring in the
    hole and the first one beyond it (``last``: per end that ring's axial position, the
    other's, and the last one's chord half-width, arc mm) to where its outline closes: an
    ellipse of axial semi-axis a and circumferential semi-axis ``widest`` (its widest
    chord's half-width) ends a (1 - sqrt(1 - (h / widest)^2)) beyond a chord of
    half-width h, at most at the ring beyond; a is half the span of the ends so placed
    (iterated from the halfway ones). Rings spaced more than
    the hole's ends are sharp read the end off the last chord's width, not the spacing
    (random-features-small seed 4: rings 10 mm apart, the end 9 mm off halfway)."""
    if widest <= 0.0:
        return ends
    out = list(ends)
    for _ in range(8):  # a from the ends it places (halfway ends shorten it by up to a spacing)
        a = 0.5 * (out[1] - out[0])
        for i, (z_in, z_out, h) in enumerate(last):
            q = min(h / widest, 1.0)
            reach = a * (1.0 - math.sqrt(1.0 - q * q))
            room = z_out - z_in
            out[i] = ends[i] if room == 0.0 else z_in + math.copysign(min(reach, abs(room)), room)
    return out
