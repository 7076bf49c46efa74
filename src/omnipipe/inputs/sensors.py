"""The robot's own sensors: odometry and IMU (contract section 1), read and validated.

``odometry.txt``: ``<time s> <distance_mm> [sigma_mm]`` per line, the cumulative travel
along the pipe. ``imu.txt``: ``<time s> ax ay az [wx wy wz]``, specific force (m/s^2,
gravity included: about +9.81 m/s^2 "up" at rest) and angular rate (rad/s) in the rig
frame. Blank lines and ``#`` comments are skipped; every line of a file has the same
columns; times increase strictly. A bad line is refused with ``file:line`` in a
one-line :class:`~omnipipe.errors.DatasetError`.

Odometry may go backwards only within its noise: a reading below the one before by
more than ``BACKSTEP_SIGMAS`` x the smaller of their sigmas is refused. Without a
sigma column each reading gets ``DEFAULT_SIGMA_REL`` x |distance| (+) ``DEFAULT_SIGMA_MM``
(a typical counter's specification) and ``Odometry.sigma_given`` is False.

:func:`odometry_at` and :func:`gravity_at` give the readings at frame times with
their 1-sigma uncertainties; a time outside what the sensor covers gets NaN with an
infinite sigma, never an extrapolated value.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omnipipe.errors import DatasetError

DEFAULT_SIGMA_MM = 1.0
DEFAULT_SIGMA_REL = 0.03
BACKSTEP_SIGMAS = 3.0
STANDARD_GRAVITY = 9.80665  # m/s^2
GRAVITY_WINDOW_S = 1.0
ACCEL_BIAS_SIGMA = 0.05  # m/s^2: an uncalibrated MEMS accelerometer's bias, 1 sigma
MIN_WINDOW_SAMPLES = 5


@dataclass(frozen=True)
class Odometry:
    """Cumulative travel along the pipe.

    Attributes:
        source: where it was read (file or ``bag topic``).
        timestamps: (N,) seconds, strictly increasing.
        distance_mm: (N,) cumulative travel (mm).
        sigma_mm: (N,) 1-sigma uncertainty of each reading (mm).
        sigma_given: False when the source states no sigma (defaults used).
    """

    source: str
    timestamps: np.ndarray
    distance_mm: np.ndarray
    sigma_mm: np.ndarray
    sigma_given: bool = True

    def __len__(self) -> int:
        return len(self.timestamps)


@dataclass(frozen=True)
class Imu:
    """Accelerometer and optional gyro in the rig frame.

    Attributes:
        source: where it was read (file or ``bag topic``).
        timestamps: (N,) seconds, strictly increasing.
        accel: (N, 3) specific force (m/s^2), gravity included.
        gyro: (N, 3) angular rate (rad/s), or None when the source has none.
    """

    source: str
    timestamps: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray | None

    def __len__(self) -> int:
        return len(self.timestamps)


def _read_table(path: Path, columns: tuple[int, ...], form: str) -> tuple[np.ndarray, np.ndarray]:
    """Rows of numbers of a text file (every row with the same count, one of
    ``columns``) and (rows,) each row's line number. Refuses bad lines with file:line.
    Read :data:`TABLE_BLOCK_LINES` lines at a time: the Python numbers of a block are
    held, not the whole file's (which grows with the run)."""
    blocks: list[np.ndarray] = []
    numbers: list[np.ndarray] = []
    first: tuple[int, int] | None = None  # (line, columns) of the first row
    done = 0
    try:
        with path.open("rb") as fh:
            while lines := list(itertools.islice(fh, TABLE_BLOCK_LINES)):
                # Lines as bytes.splitlines() splits them (a lone CR ends one too).
                lines = [piece for raw in lines for piece in (raw.splitlines() or [b""])]
                rows, at, first = _table_block(lines, done, first, path, columns, form)
                done += len(lines)
                if rows:
                    blocks.append(np.array(rows))
                    numbers.append(np.array(at, np.int64))
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror})") from None
    if not blocks:
        raise DatasetError(f"{path}: no readings")
    return np.concatenate(blocks), np.concatenate(numbers)


TABLE_BLOCK_LINES = 1 << 13
"""Lines :func:`_read_table` parses at a time."""


def _table_block(
    lines: list[bytes], done: int, first: tuple[int, int] | None, path: Path, columns: tuple[int, ...], form: str
) -> tuple[list[list[float]], list[int], tuple[int, int] | None]:
    """The rows and line numbers of ``lines`` (the file's lines after its first ``done``),
    and the first row's (line, columns) of the file so far."""
    rows: list[list[float]] = []
    at: list[int] = []
    for n, raw_line in enumerate(lines, start=done + 1):
        line = raw_line.decode("utf-8", errors="replace").strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        try:
            if len(parts) not in columns:
                raise ValueError
            values = [float(v) for v in parts]
        except ValueError:
            raise DatasetError(f"{path}:{n}: expected '{form}', got {line[:80]!r}") from None
        if not all(math.isfinite(v) for v in values):
            raise DatasetError(f"{path}:{n}: values must be finite numbers, got {line[:80]!r}")
        if first is None:
            first = (n, len(values))
        elif len(values) != first[1]:
            raise DatasetError(
                f"{path}:{n}: {len(values)} columns, but line {first[0]} has {first[1]}; "
                "every line needs the same columns"
            )
        rows.append(values)
        at.append(n)
    return rows, at, first


def _check_times(t: np.ndarray, where: Callable[[int], str]) -> None:
    bad = np.flatnonzero(np.diff(t) <= 0)
    if len(bad):
        i = int(bad[0]) + 1
        raise DatasetError(
            f"{where(i)}: time {t[i]:.6f} s is not after {t[i - 1]:.6f} s of the reading "
            "before; times must increase strictly"
        )


def make_odometry(
    source: str,
    timestamps: np.ndarray,
    distance_mm: np.ndarray,
    sigma_mm: np.ndarray | None,
    where: Callable[[int], str],
) -> Odometry:
    """Validated :class:`Odometry` from arrays; ``where(i)`` names reading i in errors."""
    t = np.asarray(timestamps, float)
    d = np.asarray(distance_mm, float)
    given = sigma_mm is not None
    s = (
        np.asarray(sigma_mm, float)
        if given
        else np.hypot(DEFAULT_SIGMA_REL * np.abs(d), DEFAULT_SIGMA_MM)
    )
    _check_times(t, where)
    bad = np.flatnonzero(~(s > 0))
    if len(bad):
        raise DatasetError(f"{where(int(bad[0]))}: sigma_mm must be > 0, got {s[bad[0]]:g}")
    back = -np.diff(d)
    tol = BACKSTEP_SIGMAS * np.minimum(s[:-1], s[1:])
    bad = np.flatnonzero(back > tol)
    if len(bad):
        i = int(bad[0]) + 1
        raise DatasetError(
            f"{where(i)}: distance {d[i]:.3f} mm is {back[i - 1]:.3f} mm below the reading "
            f"before ({d[i - 1]:.3f} mm), more than {BACKSTEP_SIGMAS:g} sigma "
            f"({tol[i - 1]:.3f} mm): odometry may go backwards only within its noise"
        )
    return Odometry(source, t, d, s, given)


def make_imu(
    source: str,
    timestamps: np.ndarray,
    accel: np.ndarray,
    gyro: np.ndarray | None,
    where: Callable[[int], str],
) -> Imu:
    """Validated :class:`Imu` from arrays; ``where(i)`` names sample i in errors."""
    t = np.asarray(timestamps, float)
    _check_times(t, where)
    a = np.asarray(accel, float).reshape(-1, 3)
    w = None if gyro is None else np.asarray(gyro, float).reshape(-1, 3)
    return Imu(source, t, a, w)


def read_odometry(path: str | Path) -> Odometry:
    """odometry.txt: ``<time s> <distance_mm> [sigma_mm]`` per line.

    Raises:
        DatasetError: unreadable file, a bad line, times not increasing, a sigma <= 0,
            or a backward step beyond the noise (each naming file:line).
    """
    path = Path(path)
    rows, lines = _read_table(path, (2, 3), "<time s> <distance_mm> [sigma_mm]")
    sigma = rows[:, 2] if rows.shape[1] == 3 else None
    return make_odometry(str(path), rows[:, 0], rows[:, 1], sigma, lambda i: f"{path}:{lines[i]}")


def read_imu(path: str | Path) -> Imu:
    """imu.txt: ``<time s> ax ay az [wx wy wz]`` per line (m/s^2, rad/s, rig frame).

    Raises:
        DatasetError: unreadable file, a bad line or times not increasing (file:line).
    """
    path = Path(path)
    rows, lines = _read_table(path, (4, 7), "<time s> ax ay az [wx wy wz]")
    gyro = rows[:, 4:7] if rows.shape[1] == 7 else None
    return make_imu(str(path), rows[:, 0], rows[:, 1:4], gyro, lambda i: f"{path}:{lines[i]}")


def read_dataset_sensors(root: Path) -> tuple[Odometry | None, Imu | None]:
    """The optional odometry.txt and imu.txt of a dataset directory (None when absent)."""
    odo = root / "odometry.txt"
    imu = root / "imu.txt"
    return (
        read_odometry(odo) if odo.is_file() else None,
        read_imu(imu) if imu.is_file() else None,
    )


def odometry_at(odometry: Odometry, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Travel (mm) and its 1-sigma (mm) at ``times_s`` (M,), linear between readings.

    Times outside the readings' span get NaN and an infinite sigma.
    """
    t = np.asarray(times_s, float)
    ts = odometry.timestamps
    d = np.interp(t, ts, odometry.distance_mm)
    s = np.interp(t, ts, odometry.sigma_mm)
    outside = (t < ts[0]) | (t > ts[-1])
    d[outside] = np.nan
    s[outside] = np.inf
    return d, s


def gravity_at(
    imu: Imu,
    times_s: np.ndarray,
    window_s: float = GRAVITY_WINDOW_S,
    bias_sigma: float = ACCEL_BIAS_SIGMA,
) -> tuple[np.ndarray, np.ndarray]:
    """Gravity direction in the rig frame at ``times_s`` (M,), from the accelerometer
    averaged over ``window_s`` centred on each time.

    Returns:
        directions: (M, 3) unit vectors pointing down (the mean specific force reversed).
        sigma_rad: (M,) 1-sigma angle uncertainty: the samples' scatter / sqrt(count),
            the accelerometer bias (``bias_sigma`` m/s^2 per axis across the direction) and
            the mean's deviation from standard gravity (acceleration that did not average
            out), over the mean's length. NaN and inf where the window holds fewer than
            5 samples or lies partly outside the recording.
    """
    t = np.asarray(times_s, float)
    ts = imu.timestamps
    lo = np.searchsorted(ts, t - 0.5 * window_s, side="left")
    hi = np.searchsorted(ts, t + 0.5 * window_s, side="right")
    out = np.full((len(t), 3), np.nan)
    sig = np.full(len(t), np.inf)
    # A window may pass the recording's ends by one sample period (the sampling grid).
    slack = float(np.median(np.diff(ts))) if len(ts) > 1 else 0.0
    inside = (t - 0.5 * window_s >= ts[0] - slack) & (t + 0.5 * window_s <= ts[-1] + slack)
    for k in range(len(t)):
        n = hi[k] - lo[k]
        if n < MIN_WINDOW_SAMPLES or not inside[k]:
            continue
        f = imu.accel[lo[k] : hi[k]]
        mean = f.mean(axis=0)
        norm = float(np.linalg.norm(mean))
        if norm <= 0:
            continue
        scatter = float(np.linalg.norm(f.std(axis=0))) / math.sqrt(n)
        excess = abs(norm - STANDARD_GRAVITY)
        out[k] = -mean / norm
        sig[k] = math.sqrt(scatter**2 + 2.0 * bias_sigma**2 + excess**2) / norm
    return out, sig
