"""odometry.txt and imu.txt: parsed, validated (bad lines named file:line), read at frame
times with their uncertainty."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from omnipipe.errors import DatasetError
from omnipipe.inputs.sensors import (
    DEFAULT_SIGMA_MM,
    gravity_at,
    make_imu,
    odometry_at,
    read_imu,
    read_odometry,
)


def _write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_odometry_parsed_with_and_without_sigma(tmp_path: Path) -> None:
    p = _write(tmp_path, "odometry.txt", "# t d s\n0.0 0.0 0.5\n\n0.5 10.0 0.6\n1.0 9.9 0.6\n1.5 30 0.9\n")
    odo = read_odometry(p)
    assert odo.sigma_given and len(odo) == 4
    np.testing.assert_array_equal(odo.distance_mm, [0.0, 10.0, 9.9, 30.0])
    d, s = odometry_at(odo, np.array([0.25, 1.25, 2.0, -0.1]))
    np.testing.assert_allclose(d[:2], [5.0, 19.95])
    np.testing.assert_allclose(s[:2], [0.55, 0.75])
    assert np.isnan(d[2:]).all() and np.isinf(s[2:]).all()  # outside the readings: no value
    plain = read_odometry(_write(tmp_path, "o2.txt", "0 0\n1 100\n"))
    assert not plain.sigma_given
    assert plain.sigma_mm[0] == pytest.approx(DEFAULT_SIGMA_MM) and plain.sigma_mm[1] > 3.0


@pytest.mark.parametrize(
    "text,line,match",
    [
        ("0 0 1\n1 x 1\n", 2, "expected"),
        ("0 0 1\n1 2 3 4\n", 2, "expected"),
        ("0 0 1\n1 nan 1\n", 2, "finite"),
        ("0 0 1\n# c\n1 2\n", 3, "columns"),
        ("0 0 1\n1 2 1\n1 3 1\n", 3, "increase strictly"),
        ("0 0 1\n1 2 0\n", 2, "sigma_mm must be > 0"),
        ("0 0 0.3\n1 10 0.3\n2 5 0.3\n", 3, "backwards only within its noise"),
    ],
    ids=["word", "columns4", "nan", "mixed", "time", "sigma", "backstep"],
)
def test_bad_odometry_lines_are_refused_with_file_and_line(
    tmp_path: Path, text: str, line: int, match: str
) -> None:
    p = _write(tmp_path, "odometry.txt", text)
    with pytest.raises(DatasetError, match=match) as info:
        read_odometry(p)
    msg = str(info.value)
    assert f"{p}:{line}:" in msg and "\n" not in msg


def test_odometry_may_step_back_within_its_noise(tmp_path: Path) -> None:
    odo = read_odometry(_write(tmp_path, "o.txt", "0 0 0.3\n1 10 0.3\n2 9.2 0.3\n3 20 0.3\n"))
    assert odo.distance_mm[2] == 9.2


@pytest.mark.parametrize(
    "text,line,match",
    [
        ("0 0 9.8 0\n1 0 9.8\n", 2, "expected"),
        ("0 0 9.8 0 0 0 0\n1 0 9.8 0\n", 2, "columns"),
        ("0 0 9.8 0\n0 0 9.8 0\n", 2, "increase strictly"),
        ("0 0 9.8 0\n1 0 inf 0\n", 2, "finite"),
    ],
    ids=["short", "mixed", "time", "inf"],
)
def test_bad_imu_lines_are_refused_with_file_and_line(
    tmp_path: Path, text: str, line: int, match: str
) -> None:
    p = _write(tmp_path, "imu.txt", text)
    with pytest.raises(DatasetError, match=match) as info:
        read_imu(p)
    assert f"{p}:{line}:" in str(info.value)


def test_empty_or_missing_files_are_refused(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="no readings"):
        read_imu(_write(tmp_path, "imu.txt", "# nothing\n"))
    with pytest.raises(DatasetError, match="cannot read"):
        read_odometry(tmp_path / "absent.txt")


def test_gravity_direction_from_a_noisy_tilted_accelerometer(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    t = np.arange(0.0, 10.0, 0.01)
    down = np.array([0.2, 0.95, 0.1])
    down /= np.linalg.norm(down)
    # At rest: the specific force is "up" (-down) x g, plus noise, a bias and a gait's
    # acceleration bursts along z (which average out over the window).
    f = -9.80665 * down + rng.normal(0, 0.02, (len(t), 3)) + [0.02, -0.01, 0.03]
    f[:, 2] += 0.3 * np.sin(2 * np.pi * t / 0.5)
    rows = np.column_stack([t, f, np.zeros((len(t), 3))])
    path = tmp_path / "imu.txt"
    np.savetxt(path, rows, fmt="%.6f")
    imu = read_imu(path)
    assert imu.gyro is not None and imu.accel.shape == (len(t), 3)
    g, sigma = gravity_at(imu, np.array([1.0, 5.0, 9.4, 0.2]))
    err = np.degrees(np.arccos(np.clip(g[:3] @ down, -1, 1)))
    print("gravity error deg", err, "sigma deg", np.degrees(sigma[:3]))
    assert np.all(err < 1.0) and np.all(err <= 3 * np.degrees(sigma[:3]))
    assert np.all(np.degrees(sigma[:3]) < 1.0)
    assert np.isnan(g[3]).all() and np.isinf(sigma[3])  # its window starts before the recording
    no_gyro = make_imu("x", t[:3], f[:3], None, str)
    assert no_gyro.gyro is None


def test_imu_read_a_block_of_lines_at_a_time_is_the_file_read_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """imu.txt parsed a few lines at a time (its Python numbers a block's, not the
    file's): the same readings as the whole file's lines (blank and comment lines, CRLF
    and a lone CR ending a line), and a bad line named by its own line number however
    the blocks fall."""
    from omnipipe.inputs import sensors

    rng = np.random.default_rng(4)
    values = rng.normal(size=(40, 7))
    values[:, 0] = np.arange(40) * 0.01
    lines = ["# t ax ay az wx wy wz"]
    for i, row in enumerate(values):
        lines += [""] * (i % 7 == 0) + ["# c"] * (i % 11 == 0) + [" ".join(f"{v:.6f}" for v in row)]
    text = "\r\n".join(lines[:-1]) + "\r" + lines[-1] + "\n"
    path = tmp_path / "imu.txt"
    path.write_bytes(text.encode())
    whole = read_imu(path)
    assert np.allclose(whole.accel, values[:, 1:4], atol=1e-6) and np.allclose(whole.gyro, values[:, 4:], atol=1e-6)
    bad_line = len(lines) - 3
    lines[bad_line - 1] = "0.5 1 2"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    for block in (3, 5, 1 << 13):
        monkeypatch.setattr(sensors, "TABLE_BLOCK_LINES", block)
        path.write_bytes(text.encode())
        imu = read_imu(path)
        assert np.array_equal(imu.timestamps, whole.timestamps) and np.array_equal(imu.gyro, whole.gyro)
        path.write_text("\n".join(lines) + "\n", encoding="utf-8")
        with pytest.raises(DatasetError, match=rf"imu.txt:{bad_line}: expected"):
            read_imu(path)
