"""Stop-and-go: which frames were taken while the rig stood still.

An earthworm robot anchors its front unit for most of each gait cycle, so runs of
consecutive frames show the same station. Two frames of one station differ only by
sensor noise; any motion shifts the wall texture. The test compares the frames'
smoothed difference with the difference that noise alone would give, estimated
from the images themselves (Immerkaer's fast noise estimate), so no threshold
depends on the camera, exposure or pipe. Lossy (JPEG, MJPG) frames lose the
pixel-scale noise that estimate measures while their box averages keep it; the
difference of frames at rest, found as three consecutive frames that differ alike
(:meth:`StationTracker.update_signature`), sets the floor then.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import cv2
import numba
import numpy as np

from omnipipe.config import bounded


@dataclass(frozen=True)
class StationConfig:
    """Stationary-frame detection.

    Attributes:
        downsample: images are box-filtered by this factor before comparing (noise averages out).
        noise_factor: a frame is stationary when its smoothed difference from the station's
            first frame is below this many times the difference noise alone gives (noise
            alone gives about 1.1-1.4; a 1.6 mm step of the paper rig at 640x480 gives 4).
            1.7, not 2.0: on a random 415 mm brick pipe a 0.5 mm creep after a stop gave
            1.87-1.91 and was taken for a standstill (the next step then 1.1 mm off);
            paper and bend keep the same motion.
        creep_factor: a frame taken for stationary whose ratio exceeds this, followed by
            a moving frame, is a moving frame too (:func:`promote_creep`): the creep
            before a stroke; so is a frame right after a moving frame whose ratio (then
            against that frame) exceeds it: the stroke's tail (random-wide seed 38, a
            brick wall: the first frame of each stop 0.8 mm past the stroke's last at
            ratio 1.42-1.51, its stop left at the stroke's last pose and the creep given to
            the next stroke). Stationary frames of the random family gave 0.93-1.03, a
            0.3-0.8 mm creep 1.16-1.6 (640x480); left at its station's pose, the next
            step absorbed it (bench_robustness seed 4: five steps off by 0.5-1.6 mm).
        noise_pixels: the noise estimate takes every k-th row of the mask's interior, k
            the largest that keeps at least this many pixels (:func:`noise_mask`): a
            1600x1200 frame's 1.1 million interior pixels give every 8th row; an 800x600
            frame's 256 000, and anything smaller, every row. Its median's relative standard
            error is then about 0.3 %, and its cost does not grow with the frame size.
        rest_spread: three consecutive frames whose three differences (smoothed, as the
            test compares) lie within this factor of each other are taken for frames at
            rest: noise alone makes the three alike (1.00-1.05 at rest on PNG and MJPG),
            motion makes the two-frame difference larger (about twice at constant speed)
            or smaller (back and forth). Their mean over the spatial estimate's expected
            difference, the lowest over the run so far and never below 1, scales that
            expectation: JPEG removes the fine-grain noise Immerkaer's estimate measures
            (an MJPG of the paper rig: 0.42 grey levels against 1.07 from the difference
            of frames at rest; rest pairs gave 4.1-4.7 times the expected difference,
            PNG 0.97-1.05).
        rest_max: the largest such factor believed: three frames differing alike by more
            are motion (frames each a texture's width apart differ alike too). A run that
            never rests keeps factor 1 (the spatial estimate alone).
    """

    downsample: int = bounded(4, ge=1)
    noise_factor: float = bounded(1.7, gt=0)
    noise_pixels: int = bounded(2**17, ge=1000)
    creep_factor: float = bounded(1.15, gt=0)
    rest_spread: float = bounded(1.2, ge=1)
    rest_max: float = bounded(8.0, ge=1)


def promote_creep(moved: np.ndarray, ratio: np.ndarray, creep_factor: float) -> np.ndarray:
    """(N,) ``moved`` with the frames just before a moving frame whose stationary-test
    ratio (N,) exceeds ``creep_factor`` made moving too.

    The robot creeps before a stroke; its last frame at the station, compared with the
    station's first, shows more than noise but less than the test's threshold. Given its
    own pose (resected like any moving frame), the creep does not land in the next step.
    """
    out = np.asarray(moved, bool).copy()
    r = np.asarray(ratio, float)
    before = np.zeros(len(out), bool)
    before[:-1] = ~out[:-1] & out[1:]
    out |= before & (np.nan_to_num(r, nan=0.0) > creep_factor)
    return out


# Immerkaer's noise operator: the difference of two Laplacians.
_NOISE_KERNEL = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)


def noise_sigma(gray: np.ndarray, mask: np.ndarray | None = None, *, inner: np.ndarray | None = None) -> float:
    """Sensor noise sigma of an image (Immerkaer 1996: Laplacian-difference operator).

    Args:
        gray: (H, W) grey image.
        mask: (H, W) bool, the pixels to use (eroded by one pixel here), or None.
        inner: (H, W) bool, the already eroded mask (:func:`inner_mask`; saves the erosion
            when many frames share one mask). Takes precedence over ``mask``.
    """
    resp = cv2.filter2D(gray.astype(np.float32), -1, _NOISE_KERNEL, borderType=cv2.BORDER_REFLECT)
    if inner is None and mask is not None:
        inner = inner_mask(mask)
    if inner is not None:
        resp = resp[inner]
    # The operator's weights square-sum to 36: its response to noise has sigma 6 sigma.
    # The median absolute response (robust to texture edges) is 0.6745 times that.
    return _median_abs(resp) / (6.0 * 0.6745)


def inner_mask(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool: ``mask`` eroded by one pixel (where the 3 x 3 operator sees only it)."""
    return cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0


def noise_mask(mask: np.ndarray, pixels: int | None = None) -> np.ndarray:
    """(H, W) bool: the pixels the noise estimate uses: :func:`inner_mask` of ``mask`` on
    every k-th row (rows 0, k, 2k, ...), k the largest that keeps at least ``pixels`` of
    it (None: every row)."""
    inner = inner_mask(mask)
    per_row = inner.sum(axis=1)
    row_step = 1
    if pixels:
        row_step = max([k for k in range(1, len(per_row) + 1) if per_row[::k].sum() >= pixels], default=1)
    if row_step > 1:
        keep = np.zeros(inner.shape[0], bool)
        keep[::row_step] = True
        inner &= keep[:, None]
    return inner


def _median_abs(values: np.ndarray) -> float:
    """The median of ``|values|`` (float32 values): ``np.median``, except for whole
    numbers (an integer image through an integer kernel: 8- and 16-bit frames), counted
    (5x faster than the partition a median needs) and read as grouped data
    (:func:`_grouped_median`)."""
    a = np.abs(values.ravel())
    if a.size == 0 or a.dtype != np.float32 or float(a.max()) >= 2**24:
        return float(np.median(a))
    ints = a.astype(np.int32)
    if not np.array_equal(ints, a):
        return float(np.median(a))
    return _grouped_median(np.bincount(ints))


def _grouped_median(hist: np.ndarray) -> float:
    """The median of whole-number magnitudes counted in ``hist`` (``hist[k]`` of them
    equal k), each taken for the interval it was rounded from ([k - 1/2, k + 1/2), and
    [0, 1/2) for 0) and spread evenly over it: the grouped-data median.

    The plain median of whole numbers moves in whole steps: an 8-bit frame's noise
    operator has a median magnitude of about 5 at a noise sigma of 1.2, so the estimate
    jumped by 20 % between frames (or between pixel subsets) whose counts barely
    differ, and a stationary frame's ratio with it (a random 800x600 run: 14 of its 78
    frames taken for moving or not by such a jump). Interpolated, it moves smoothly.
    NaN when ``hist`` counts nothing.
    """
    counts = np.cumsum(hist)
    n = int(counts[-1]) if len(counts) else 0
    if n == 0:
        return math.nan
    half = n / 2
    k = int(np.searchsorted(counts, half, side="left"))  # first k with counts[k] >= n / 2
    below = int(counts[k - 1]) if k else 0
    lower, width = (k - 0.5, 1.0) if k else (0.0, 0.5)
    return lower + width * (half - below) / int(hist[k])


def _small(gray: np.ndarray, factor: int) -> np.ndarray:
    h, w = gray.shape
    return cv2.resize(gray.astype(np.float32), (w // factor, h // factor), interpolation=cv2.INTER_AREA)


def frame_signature(
    image: np.ndarray,
    laser_channel: str,
    inner: np.ndarray,
    config: StationConfig | None = None,
    runs: np.ndarray | None = None,
) -> StationSignature:
    """:func:`station_signature` of a decoded frame's grey image without the laser
    (:func:`omnipipe.image.gray_without_laser`), the same bit for bit.

    A frame whose grey image is one of its 8- or 16-bit channels (a red laser: green;
    a one-channel frame) is read as that channel, in integers and compiled: the noise
    operator only at the ``inner`` pixels (:func:`_noise_histogram`, a histogram of its
    magnitudes instead of a float32 image and a masked median) and the box average as
    block sums. 1600x1200, the signature taken of every frame: 4.5 ms as float32 images,
    2.7 ms with ``cv2.filter2D`` over the whole frame, 1.2 ms with the
    :func:`noise_mask` of every 4th row, 1.0 ms with the default's every 8th. Any other
    frame goes through the grey image.

    Args:
        image: (H, W) or (H, W, C) frame as decoded.
        laser_channel: the rig's laser channel.
        inner: (H, W) bool, the pixels of the noise estimate: :func:`noise_mask` (or
            :func:`inner_mask`) of the camera's valid mask.
        runs: :func:`mask_runs` of ``inner`` when the caller keeps it (many frames share
            one mask); None: made here.
    """
    from omnipipe.image import CHANNEL_INDEX, gray_without_laser

    cfg = config or StationConfig()
    h, w = image.shape[:2]
    if image.ndim == 2:
        channel = image
    elif image.ndim == 3 and CHANNEL_INDEX.get(laser_channel) == 0 and image.shape[2] >= 2:
        channel = cv2.extractChannel(image, 1) if image.dtype in (np.uint8, np.uint16) else None
    else:
        channel = None
    if channel is None or channel.dtype not in (np.uint8, np.uint16) or inner.shape != (h, w):
        return station_signature(gray_without_laser(image, laser_channel), inner, cfg)
    channel = np.ascontiguousarray(channel)
    full = 255 if channel.dtype == np.uint8 else 65535
    # The operator's response is a whole number, |r| <= 16 x the channel's maximum.
    hist = np.zeros(16 * full + 1, np.int64)
    _noise_histogram(channel, mask_runs(inner) if runs is None else runs, hist)
    f = cfg.downsample
    if h % f == 0 and w % f == 0 and f * f * full < 2**24:
        # Whole f x f blocks: their sums (exact in float32) times 1 / f^2 are the area
        # resize's values bit for bit, without a float32 copy of the frame.
        # An 8-bit frame's 4 x 4 sums (<= 4080) are made in uint16: the signature's
        # pickled form as they are (:meth:`StationSignature.__getstate__`).
        packs = f == 4 and full == 255
        sums = np.empty((h // f, w // f), np.uint16 if packs else np.int32)
        if f == 4:
            _block_sums_4(channel, sums)
        else:
            _block_sums(channel, f, sums)
        small = sums.astype(np.float32) * np.float32(1.0 / (f * f))
        return StationSignature(small, _grouped_median(hist) / (6.0 * 0.6745), sums if packs else None)
    return StationSignature(_small(channel, f), _grouped_median(hist) / (6.0 * 0.6745))


def mask_runs(mask: np.ndarray) -> np.ndarray:
    """(R, 2) int64 [start, end) flat indices of the runs of True along the rows of the
    (H, W) bool ``mask`` (row-major)."""
    h, w = mask.shape
    padded = np.zeros((h, w + 2), np.int8)
    padded[:, 1:-1] = mask
    edges = np.diff(padded, axis=1)  # (H, W + 1): +1 where a run starts, -1 after it ends
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    runs = np.stack([starts // (w + 1) * w + starts % (w + 1), ends // (w + 1) * w + ends % (w + 1)], axis=1)
    return runs.astype(np.int64)


@numba.njit(cache=True, nogil=True)
def _noise_histogram(p, runs, hist):  # pragma: no cover - compiled
    """``hist[|r|] += 1`` for the noise operator's response r (:data:`_NOISE_KERNEL`,
    borders reflected as ``cv2.BORDER_REFLECT``) at every pixel of the row ``runs``
    (:func:`mask_runs`) of the (H, W) integer image ``p``.

    The operator is separable: each row used gets the column second difference
    v = p[y - 1] - 2 p[y] + p[y + 1] once, over its runs' span, and r is v's row second
    difference. The counts go to four interleaved histograms (when small), so that
    consecutive pixels' increments do not wait on each other.
    """
    h, w = p.shape
    n = runs.shape[0]
    v = np.zeros(w + 2, np.int32)  # v[x + 1]: column x; v[0], v[w + 1]: reflected
    split = hist.shape[0] <= 65536
    extra = np.zeros((3, hist.shape[0] if split else 1), np.int64)
    r = 0
    while r < n:
        y = runs[r, 0] // w
        last = r
        while last + 1 < n and runs[last + 1, 0] // w == y:
            last += 1
        lo, hi = runs[r, 0] - y * w, runs[last, 1] - y * w
        above, row, below = p[max(y - 1, 0)], p[y], p[min(y + 1, h - 1)]
        for x in range(max(lo - 1, 0), min(hi + 1, w)):
            v[x + 1] = np.int32(above[x]) - 2 * np.int32(row[x]) + np.int32(below[x])
        v[0] = v[1]
        v[w + 1] = v[w]
        for k in range(r, last + 1):
            x, end = runs[k, 0] - y * w, runs[k, 1] - y * w
            if split:
                while x + 4 <= end:
                    hist[abs(v[x] - 2 * v[x + 1] + v[x + 2])] += 1
                    extra[0, abs(v[x + 1] - 2 * v[x + 2] + v[x + 3])] += 1
                    extra[1, abs(v[x + 2] - 2 * v[x + 3] + v[x + 4])] += 1
                    extra[2, abs(v[x + 3] - 2 * v[x + 4] + v[x + 5])] += 1
                    x += 4
            while x < end:
                hist[abs(v[x] - 2 * v[x + 1] + v[x + 2])] += 1
                x += 1
        r = last + 1
    if split:
        for i in range(hist.shape[0]):
            hist[i] += extra[0, i] + extra[1, i] + extra[2, i]


@numba.njit(cache=True, nogil=True)
def _block_sums(p, f, sums):  # pragma: no cover - compiled
    """``sums[i, j]`` = the sum of ``p``'s f x f block (i, j), for the (H // f, W // f)
    ``sums`` (int32, or uint16 where every sum fits)."""
    bh, bw = sums.shape
    acc = np.empty(bw * f, np.int32)
    for by in range(bh):
        acc[:] = 0
        for j in range(f):
            row = p[by * f + j]
            for x in range(bw * f):
                acc[x] += row[x]
        for bx in range(bw):
            total = np.int32(0)
            for i in range(f):
                total += acc[bx * f + i]
            sums[by, bx] = total


@numba.njit(cache=True, nogil=True)
def _block_sums_4(p, sums):  # pragma: no cover - compiled
    """:func:`_block_sums` of 4 x 4 blocks (the default), its loops unrolled: each
    block row's four rows added in one pass, then each block's four columns."""
    bh, bw = sums.shape
    acc = np.empty(bw * 4, np.int32)
    for by in range(bh):
        a, b, c, d = p[4 * by], p[4 * by + 1], p[4 * by + 2], p[4 * by + 3]
        for x in range(bw * 4):
            acc[x] = np.int32(a[x]) + np.int32(b[x]) + np.int32(c[x]) + np.int32(d[x])
        for bx in range(bw):
            sums[by, bx] = acc[4 * bx] + acc[4 * bx + 1] + acc[4 * bx + 2] + acc[4 * bx + 3]


@dataclass(frozen=True)
class StationState:
    """The stationary test's state between frames (saved and restored by a resumed run).

    Attributes:
        reference: (h, w) float32, the current station's first frame's box average.
        last, before: (h, w) float32, the previous frame's and the one before's (None
            until seen).
        last_diff: the mean smoothed difference of ``before`` and ``last`` (grey levels;
            NaN until both are seen).
        rest_factor: the noise floor's factor over the spatial estimate's expectation
            (:attr:`StationConfig.rest_spread`; inf until three frames at rest).
        after_move: the last frame was a moving one (``reference`` is that frame).
    """

    reference: np.ndarray
    last: np.ndarray | None = None
    before: np.ndarray | None = None
    last_diff: float = math.nan
    rest_factor: float = math.inf
    after_move: bool = True


class StationTracker:
    """Feeds frames one at a time; tells for each whether the rig moved since the station began.

    Each frame is compared with the first frame of the current station, so a slow
    creep that no single pair of frames shows accumulates until it is detected.

    Args:
        mask: (H, W) bool, the pixels that see the wall (the camera's valid mask).
        config: detection settings.
    """

    def __init__(self, mask: np.ndarray, config: StationConfig | None = None) -> None:
        self.config = config or StationConfig()
        f = self.config.downsample
        small = _small(mask.astype(np.float32), f)
        self.mask_small = small > 0.999
        self.mask = mask
        self._inner: np.ndarray | None = None  # the noise estimate's pixels, made by update()
        self._state: StationState | None = None

    def update(self, gray: np.ndarray) -> tuple[bool, float]:
        """Add the next frame (grey, not the laser channel); return (moved, ratio).

        ``ratio`` is the smoothed difference over its noise-only expectation (inf for
        the first frame, which counts as moved: it starts a station).
        """
        if self._inner is None:
            self._inner = noise_mask(self.mask, self.config.noise_pixels)
        return self.update_signature(station_signature(gray, self._inner, self.config))

    @property
    def reference(self) -> StationState | None:
        """The tracker's whole state (None before a frame), saved and restored by a
        resumed run."""
        return self._state

    @reference.setter
    def reference(self, state: StationState | None) -> None:
        self._state = state

    @property
    def rest_factor(self) -> float:
        """The factor the noise floor of frames at rest puts on the spatial estimate's
        expected difference (1: none found, or no more than it)."""
        r = math.inf if self._state is None else self._state.rest_factor
        return 1.0 if math.isinf(r) else max(r, 1.0)

    def update_signature(self, signature: StationSignature) -> tuple[bool, float]:
        """:meth:`update` from the frame's :func:`station_signature` (computed anywhere,
        e.g. in the worker that decoded the frame)."""
        state, cur = self._state, signature.small
        if state is None:
            self._state = StationState(cur, cur)
            return True, math.inf
        f = self.config.downsample
        sigma = max(signature.noise_sigma, 0.3)
        # Box-averaging f x f pixels divides the noise sigma by f; a difference of two
        # frames multiplies it by sqrt(2); its mean absolute value is sigma sqrt(2/pi).
        expected = sigma / f * math.sqrt(2.0) * math.sqrt(2.0 / math.pi)
        last = cur if state.last is None else state.last
        before = cur if state.before is None else state.before
        sums = np.zeros(4)
        _masked_abs_sums(cur, state.reference, last, before, self.mask_small, sums)
        diff, step, skip = (float(x / max(sums[3], 1.0)) for x in sums[:3])
        rest = self._rest(state, step, skip, expected)
        ratio = diff / (expected * (1.0 if math.isinf(rest) else max(rest, 1.0)))
        moved = ratio > self.config.noise_factor or (
            # The stroke's tail: a frame right after a moving one that moved a little from
            # it (more than a creep) ends the stroke, and its station begins there.
            state.after_move and ratio > self.config.creep_factor
        )
        reference = cur if moved else state.reference  # a moving frame starts a station
        self._state = StationState(reference, cur, state.last, step, rest, bool(moved))
        return moved, ratio

    def _rest(self, state: StationState, step: float, skip: float, expected: float) -> float:
        """The state's rest factor, lowered to the current frame's when it and the two
        before differ alike (:attr:`StationConfig.rest_spread`) and by at most
        :attr:`StationConfig.rest_max` times ``expected``; ``step``, ``skip``: its mean
        smoothed difference from the last frame and from the one before."""
        cfg = self.config
        low = state.rest_factor
        if state.before is None or math.isnan(state.last_diff):
            return low
        diffs = (state.last_diff, step, skip)
        factor = sum(diffs) / 3.0 / expected
        if max(diffs) > cfg.rest_spread * min(diffs) or factor > cfg.rest_max:
            return low
        return min(low, factor)


@numba.njit(cache=True, nogil=True)
def _masked_abs_sums(cur, ref, last, before, mask, sums):  # pragma: no cover - compiled
    """``sums`` (4,) float64 = the sums of |cur - ref|, |cur - last| and |cur - before|
    over the True pixels of ``mask``, and their count (all (h, w))."""
    h, w = cur.shape
    a = b = c = 0.0
    n = 0
    for y in range(h):
        for x in range(w):
            if mask[y, x]:
                v = np.float64(cur[y, x])
                a += abs(v - ref[y, x])
                b += abs(v - last[y, x])
                c += abs(v - before[y, x])
                n += 1
    sums[0], sums[1], sums[2], sums[3] = a, b, c, n


@dataclass(frozen=True)
class StationSignature:
    """What the stationary-frame test needs of one frame (a few per cent of its size).

    Attributes:
        small: (H // f, W // f) float32 grey image box-averaged by ``downsample`` f.
        noise_sigma: the frame's sensor noise sigma (grey levels, :func:`noise_sigma`).

        packed: None, or (H // f, W // f) uint16 ``small`` x 16 exactly (an 8-bit frame's
            4 x 4 block sums, as :func:`frame_signature` makes them): what is pickled.

    Pickled (from the worker that decoded the frame to the process that compares), an
    8-bit frame's box average of 16 pixels travels as its block sums in uint16, exact
    and in half the bytes (bend: 160 -> 80 MB through the pipes); any other as is.
    ``packed`` saves finding them again from ``small`` (0.16 ms at 1600x1200).
    """

    small: np.ndarray
    noise_sigma: float
    packed: np.ndarray | None = field(default=None, compare=False, repr=False)

    def __getstate__(self) -> tuple:
        small = self.small
        if self.packed is not None:
            return self.packed, self.noise_sigma
        if small.dtype == np.float32 and small.size:
            sums = small * np.float32(16.0)
            if float(sums.max()) < 65536 and float(sums.min()) >= 0:
                packed = sums.astype(np.uint16)
                if np.array_equal(packed, sums):
                    return packed, self.noise_sigma
        return small, self.noise_sigma

    def __setstate__(self, state: tuple) -> None:
        small, sigma = state
        if small.dtype == np.uint16:
            small = small.astype(np.float32) * np.float32(1.0 / 16.0)
        object.__setattr__(self, "small", small)
        object.__setattr__(self, "noise_sigma", sigma)
        object.__setattr__(self, "packed", None)


def station_signature(
    gray: np.ndarray, inner: np.ndarray, config: StationConfig | None = None
) -> StationSignature:
    """The :class:`StationSignature` of a grey frame (not the laser channel).

    Args:
        gray: (H, W) grey image.
        inner: (H, W) bool, the pixels of the noise estimate: :func:`noise_mask` (or
            :func:`inner_mask`) of the camera's valid mask.
    """
    cfg = config or StationConfig()
    return StationSignature(_small(gray, cfg.downsample), noise_sigma(gray, inner=inner))



# A stationary frame whose ratio could hide a step longer than this (mm,
# :func:`hidden_steps`) is not verified by the stationary test. Random-wide seed 29 (a
# plain wall): 3.9-4.7 mm frame steps at ratios 1.38-1.56 taken for standing; seed 10:
# 2 mm after the last keyframe at ratios 1.06-1.08. 1 mm: bench_robustness's silent
# failure.
HIDDEN_STEP_MM = 1.0
# Added to a stationary frame's ratio before its hidden step is computed: the ratio of
# frames at rest scatters by about 0.02 (0.99-1.03 over the random family's PNG runs).
HIDDEN_RATIO_MARGIN = 0.03


def texture_gain(
    ratio: np.ndarray, positions: np.ndarray, registered: np.ndarray, config: StationConfig | None = None
) -> float:
    """The wall's texture gain g (per mm) of the stationary test's ratio: a shift L adds
    to the noise's difference in quadrature, ``r^2 = 1 + (g L)^2`` (the mean absolute
    difference of signal plus noise), the median over the frames the test found moving.

    Args:
        ratio: (N,) each frame's ratio against its station's first frame (inf for the
            first; NaN: not known).
        positions: (N, 3) the frames' positions, mm.
        registered: (N,) True where the position is valid.

    Returns:
        g (per mm), NaN with no moving frame of known ratio and positive length.
    """
    cfg = config or StationConfig()
    r = np.asarray(ratio, float)
    gains = []
    ref = -1
    for i in range(len(r)):
        starts = bool(r[i] > cfg.noise_factor)  # inf included: a station begins here
        if starts and math.isfinite(r[i]) and ref >= 0 and registered[i] and registered[ref]:
            length = float(np.linalg.norm(positions[i] - positions[ref]))
            if length > 0:
                gains.append(math.sqrt(r[i] ** 2 - 1.0) / length)
        if starts:
            ref = i
    return float(np.median(gains)) if gains else math.nan


def hidden_steps(ratio: np.ndarray, moved: np.ndarray, gain: float) -> np.ndarray:
    """(N,) the longest step (mm) each stationary frame may have made unseen: the length
    whose ratio (:func:`texture_gain`'s model) is its own plus
    :data:`HIDDEN_RATIO_MARGIN`; 0 for moving frames and where the ratio is unknown, inf
    for stationary frames of a run whose gain is unknown."""
    r = np.asarray(ratio, float)
    stationary = ~np.asarray(moved, bool) & np.isfinite(r)
    out = np.zeros(len(r))
    if not math.isfinite(gain) or gain <= 0:
        out[stationary] = math.inf
        return out
    rr = r[stationary] + HIDDEN_RATIO_MARGIN
    out[stationary] = np.sqrt(np.maximum(rr**2 - 1.0, 0.0)) / gain
    return out


def unverified_stations(
    hidden_mm: np.ndarray, moved: np.ndarray, keyframes: list[int] | None = None
) -> list[tuple[int, int, float]]:
    """(first, last, longest hidden step mm) of every station one of whose stationary
    frames may have moved more than :data:`HIDDEN_STEP_MM` unseen (``hidden_mm`` (N,),
    :func:`hidden_steps`): from its first frame to the next moving frame (or the run's
    last frame), widened to the keyframes around it (``keyframes``: their frame indices;
    the frames between them are placed by a split of their step that took the missed
    frames for standing). ``moved`` (N,): the stationary test's result."""
    m = np.asarray(moved, bool)
    h = np.asarray(hidden_mm, float)
    starts = np.flatnonzero(m)
    kfs = np.asarray(sorted(keyframes or []), int)
    out = []
    for j, f in enumerate(starts):
        end = int(starts[j + 1]) if j + 1 < len(starts) else len(m) - 1
        worst = float(h[f + 1 : end + (j + 1 == len(starts))].max(initial=0.0))
        if not worst > HIDDEN_STEP_MM:
            continue
        before, after = kfs[kfs <= f], kfs[kfs >= end]
        out.append(
            (int(before[-1]) if len(before) else int(f), int(after[0]) if len(after) else end, worst)
        )
    return out


# The flow test's bound (:func:`flow_hidden_steps`): its fraction of the reference step
# is the median over the tracked points plus this many of its standard errors.
FLOW_SIGMAS = 3.0
# ... and its fraction is taken this much larger: Lucas-Kanade reads a plain wall's
# faint texture short (random-wide seed 25: 0.45 of a 2 mm step for 0.50, 0.82 for 1.01).
FLOW_REL_MARGIN = 0.2
# Fewest tracked points (with a reference flow of at least FLOW_MIN_PX) for a bound.
FLOW_MIN_POINTS = 30
FLOW_MIN_PX = 1.0
# Largest forward-backward error (px) of a kept track.
FLOW_FB_PX = 0.5
# The reference step must be at least this long (mm): its flow is the ruler.
FLOW_MIN_REF_MM = 1.0
# The images are high-passed before tracking (their Gaussian blur of this sigma, px,
# removed): the rig's own light shades a plain wall alike in every frame, and a
# tracker following that shading reads a step 3 times short (seed 25).
FLOW_HIGHPASS_PX = 5.0
# The ruler is checked on the step before it (frame f-2 against the station's first
# frame f, whose fraction the positions tell): the measured fraction must lie within
# this log of the positions' one (seed 3, joints: 0.55 of it, not used).
FLOW_CHECK_LOG = 0.25


def flow_fraction(
    before: np.ndarray, ref: np.ndarray, frames: Iterable[np.ndarray], mask: np.ndarray
) -> list[tuple[float, float]]:
    """How far each of ``frames`` moved from ``ref`` as a fraction of the step
    ``before`` -> ``ref``, measured by the tracked flow of the wall's texture.

    The images are high-passed (:data:`FLOW_HIGHPASS_PX`). Corners of ``ref`` (inside
    ``mask``) are followed by pyramidal Lucas-Kanade into ``before`` and into each
    frame (kept when the flow back returns within :data:`FLOW_FB_PX`). A point's
    reference flow r (``before`` -> ``ref``) and its flow f into a frame give its
    fraction ``f . r / |r|^2``; for a step along the same direction (the robot's axial
    creep) every point gives about the same fraction, the noise of the flow scatters it.

    Args:
        before, ref: (H, W) grey images of the frame before the station and of the
            station's first frame.
        frames: (H, W) grey images of the station's other frames (read one at a time:
            an iterator need not hold them all).
        mask: (H, W) bool, the pixels that see the wall.

    Returns:
        per frame (median fraction, its standard error); (NaN, NaN) with fewer than
        :data:`FLOW_MIN_POINTS` points.
    """
    frames = iter(frames)
    r8, b8 = _high_passed(ref), _high_passed(before)
    inner = cv2.erode(mask.astype(np.uint8), np.ones((15, 15), np.uint8))  # off the rim
    pts = cv2.goodFeaturesToTrack(r8, 2000, 0.01, 5, mask=inner)
    if pts is None or len(pts) < FLOW_MIN_POINTS:
        return [(math.nan, math.nan) for _ in frames]
    back_flow, ok = _tracked(r8, b8, pts)
    r = -back_flow  # before -> ref
    rn2 = np.sum(r * r, axis=1)
    ok &= rn2 >= FLOW_MIN_PX**2
    out = []
    for frame in frames:
        f, fok = _tracked(r8, _high_passed(frame), pts)
        use = ok & fok
        if use.sum() < FLOW_MIN_POINTS:
            out.append((math.nan, math.nan))
            continue
        s = np.sum(f[use] * r[use], axis=1) / rn2[use]
        med = float(np.median(s))
        # The median's standard error: 1.2533 sigma / sqrt(n), sigma from the MAD.
        sigma = 1.4826 * float(np.median(np.abs(s - med)))
        out.append((med, 1.2533 * sigma / math.sqrt(len(s))))
    return out


def _high_passed(gray: np.ndarray) -> np.ndarray:
    """(H, W) uint8: ``gray`` less its Gaussian blur (:data:`FLOW_HIGHPASS_PX`), x4 about 128."""
    g = np.asarray(gray, np.float32)
    return np.clip(128.0 + 4.0 * (g - cv2.GaussianBlur(g, (0, 0), FLOW_HIGHPASS_PX)), 0, 255).astype(np.uint8)


def _tracked(a: np.ndarray, b: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) flow of ``pts`` (M, 1, 2) from ``a`` into ``b`` and (M,) bool, kept."""
    lk = dict(winSize=(21, 21), maxLevel=3, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(a, b, pts, None, **lk)
    p0, st0, _ = cv2.calcOpticalFlowPyrLK(b, a, p1, None, **lk)
    fb = np.linalg.norm((p0 - pts).reshape(-1, 2), axis=1)
    ok = (st1.ravel() == 1) & (st0.ravel() == 1) & (fb < FLOW_FB_PX)
    return (p1 - pts).reshape(-1, 2), ok


def flow_hidden_steps(
    hidden_mm: np.ndarray,
    moved: np.ndarray,
    positions: np.ndarray,
    registered: np.ndarray,
    read_gray: Callable[[int], np.ndarray],
    mask: np.ndarray,
) -> np.ndarray:
    """(N,) ``hidden_mm`` (:func:`hidden_steps`) lowered by the tracked flow where it
    exceeds :data:`HIDDEN_STEP_MM`: the frames of such a station (first frame f) are
    measured against f with the step f-1 -> f as the ruler (:func:`flow_fraction`),
    checked on frame f-2 (:data:`FLOW_CHECK_LOG`; a ruler reading short scales the
    bounds up, never down), and a frame's bound becomes ``((1 + FLOW_REL_MARGIN)
    |fraction| + FLOW_SIGMAS x its standard error) x`` the ruler's length (mm, from
    ``positions`` (N, 3)) when that is lower. On a plain wall the stationary test's
    ratio barely rises with a step, while the few corners there are still tracked to a
    tenth of a pixel.

    Args:
        moved: (N,) the stationary test's result.
        registered: (N,) True where the position is valid.
        read_gray: frame index -> its (H, W) grey image without the laser.
        mask: (H, W) bool, the pixels that see the wall.
    """
    h = np.asarray(hidden_mm, float).copy()
    m = np.asarray(moved, bool)
    p = np.asarray(positions, float)
    starts = np.flatnonzero(m)
    for j, f in enumerate(starts):
        end = int(starts[j + 1]) if j + 1 < len(starts) else len(m)
        frames = list(range(f + 1, end))
        if f < 2 or not frames or not (h[frames].max() > HIDDEN_STEP_MM):
            continue
        if not registered[f - 2 : f + 1].all():
            continue
        ruler = p[f] - p[f - 1]
        ref_mm = float(np.linalg.norm(ruler))
        if ref_mm < FLOW_MIN_REF_MM or np.linalg.norm(p[f - 2] - p[f - 1]) < FLOW_MIN_REF_MM:
            continue
        expected = float(np.dot(p[f - 2] - p[f], ruler)) / ref_mm**2
        fractions = flow_fraction(
            read_gray(f - 1), read_gray(f), [read_gray(f - 2)] + [read_gray(i) for i in frames], mask
        )
        check = fractions[0][0]
        if not (check < 0 and expected < 0 and abs(math.log(check / expected)) <= FLOW_CHECK_LOG):
            continue
        gain = max(expected / check, 1.0)
        for i, (s, se) in zip(frames, fractions[1:], strict=True):
            if math.isfinite(s):
                bound = ((1.0 + FLOW_REL_MARGIN) * abs(s) + FLOW_SIGMAS * se) * gain * ref_mm
                h[i] = min(h[i], bound)
    return h
