"""Bad values (issue 15, "tracebacks" and "nonsense accepted silently").

Non-finite numbers in rig.yaml, impossible laser planes, bad timestamps, NaN/inf on
the command line and a --config section that is a list: each is refused with one
line naming the field, option or file:line, exit code 1, nothing written.
"""

from __future__ import annotations

import math
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import yaml

from omnipipe.cli import main
from omnipipe.dataset import open_dataset
from omnipipe.errors import ConfigError, DatasetError
from omnipipe.rig import MIN_LASER_DISTANCE_MM
from omnipipe.rig_yaml import rig_from_dict
from omnipipe.sim import paper_rig


def copy_dataset(src: Path, dst: Path) -> Path:
    """A writable copy (rig.yaml, frames/, timestamps.txt) of ``src``."""
    (dst / "frames").mkdir(parents=True)
    for p in (src / "frames").iterdir():
        (dst / "frames" / p.name).write_bytes(p.read_bytes())
    for name in ("rig.yaml", "timestamps.txt"):
        (dst / name).write_bytes((src / name).read_bytes())
    return dst


def cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    capsys.readouterr()
    code = main(argv)
    return code, capsys.readouterr().err


def assert_refused(code: int, err: str, *needles: str) -> None:
    assert code == 1
    assert err.count("\n") == 1 and err.startswith("omnipipe "), err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in err, err


def rig_dict() -> dict:
    return paper_rig(64, 48).to_dict()


# -- rig.yaml: finite numbers, possible laser planes ---------------------------------


@pytest.mark.parametrize(
    ("section", "key", "value", "field"),
    [
        ("camera", "f", math.nan, "camera.f"),
        ("camera", "cx", math.inf, "camera.cx"),
        ("camera", "radius_max", -math.inf, "camera.radius_max"),
        ("mirror", "a", math.nan, "mirror.a"),
        ("laser", "plane", [0.0, 0.0, math.nan, 82.0], "laser.plane[2]"),
        ("laser", "plane", [0.0, 0.0, 1.0, math.inf], "laser.plane[3]"),
    ],
)
def test_non_finite_rig_numbers_are_named(section: str, key: str, value, field: str) -> None:
    data = rig_dict()
    data[section][key] = value
    with pytest.raises(ConfigError) as err:
        rig_from_dict(data, "rig.yaml")
    assert err.value.field == field
    assert "finite" in str(err.value)


def plane_tilted(deg: float, offset_mm: float = 82.0) -> list[float]:
    """A plane whose normal is tilted ``deg`` from the mirror axis, |k4| / |k| = offset."""
    t = math.radians(deg)
    return [math.sin(t), 0.0, math.cos(t), offset_mm]


@pytest.mark.parametrize(
    ("plane", "reason"),
    [
        ([0.0, 0.0, 0.0, 82.0], "must not be zero"),
        ([0.0, 0.0, 1.0, 0.0], "from the mirror focus"),
        ([0.0, 0.0, 1.0, 1e-6], "from the mirror focus"),
        ([0.0, 0.0, 1e6, 1.0], "from the mirror focus"),  # 1e-6 mm once normalised
        ([1.0, 0.0, 0.0, 82.0], "parallel to the mirror axis"),
        (plane_tilted(80.0), "tilted 80.0 deg"),
        (plane_tilted(60.0), "tilted 60.0 deg"),
    ],
    ids=["zero-normal", "through-focus", "1e-6mm", "1e-6mm-scaled", "parallel", "80deg", "60deg"],
)
def test_impossible_laser_planes_are_refused_with_the_reason(plane: list, reason: str) -> None:
    data = rig_dict()
    data["laser"]["plane"] = plane
    with pytest.raises(ConfigError, match=reason) as err:
        rig_from_dict(data, "rig.yaml")
    assert err.value.field == "laser.plane"


@pytest.mark.parametrize(
    "plane",
    [
        [0.0, 0.0, 1.0, 82.0],  # the paper's
        [0.0, 0.0, 2.0, 164.0],  # the same plane, unnormalised
        [0.0, 0.0, 1.0, -82.0],  # on the mirror's side of the focus
        plane_tilted(20.0),
        plane_tilted(30.0),
        [0.0, 0.0, 1.0, MIN_LASER_DISTANCE_MM],
    ],
)
def test_possible_laser_planes_are_accepted(plane: list) -> None:
    data = rig_dict()
    data["laser"]["plane"] = plane
    rig = rig_from_dict(data, "rig.yaml")
    assert rig.laser.distance_mm == pytest.approx(abs(plane[3]) / np.linalg.norm(plane[:3]))


def test_parallel_plane_is_refused_before_any_heavy_work(
    tiny_dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The plane that drove memory past 6 GB: refused at rig validation, small heap."""
    ds = copy_dataset(tiny_dataset, tmp_path / "ds")
    data = yaml.safe_load((ds / "rig.yaml").read_text())
    data["laser"]["plane"] = [1.0, 0.0, 0.0, 82.0]
    (ds / "rig.yaml").write_text(yaml.safe_dump(data))
    tracemalloc.start()
    try:
        code, err = cli(["reconstruct", str(ds), "--out", str(tmp_path / "out"), "--quiet"], capsys)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert_refused(code, err, "rig.yaml", "laser.plane", "parallel")
    assert peak < 20_000_000
    assert not (tmp_path / "out").exists()


def test_plane_near_focus_via_cli(
    tiny_dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ds = copy_dataset(tiny_dataset, tmp_path / "ds")
    text = (ds / "rig.yaml").read_text()
    (ds / "rig.yaml").write_text(text.replace("82.0]", "1.0e-06]"))
    code, err = cli(["reconstruct", str(ds), "--out", str(tmp_path / "out"), "--quiet"], capsys)
    assert_refused(code, err, "laser.plane", "1e-06 mm")
    assert not (tmp_path / "out").exists()


# -- timestamps.txt -----------------------------------------------------------------


def write_stamps(ds: Path, lines: list[str] | bytes) -> None:
    data = lines if isinstance(lines, bytes) else ("\n".join(lines) + "\n").encode()
    (ds / "timestamps.txt").write_bytes(data)


@pytest.mark.parametrize(
    ("values", "line", "reason"),
    [
        (["0.0", "nan", "0.2", "0.3"], 2, "finite"),
        (["0.0", "0.1", "inf", "0.3"], 3, "finite"),
        (["0.0", "0.2", "0.1", "0.3"], 3, "not after 0.2 s"),
        (["0.0", "0.1", "0.1", "0.3"], 3, "not after 0.1 s"),
        (["0.3", "0.2", "0.1", "0.0"], 2, "increase strictly"),
    ],
    ids=["nan", "inf", "backwards", "repeated", "reversed"],
)
def test_bad_timestamps_are_refused_naming_file_and_line(
    tiny_dataset: Path, tmp_path: Path, values: list[str], line: int, reason: str
) -> None:
    ds = copy_dataset(tiny_dataset, tmp_path / "ds")
    write_stamps(ds, [f"{i:06d}.png {v}" for i, v in enumerate(values)])
    with pytest.raises(DatasetError, match=reason) as err:
        open_dataset(ds)
    assert f"timestamps.txt:{line}:" in str(err.value)


def test_non_utf8_comment_is_ignored(tiny_dataset: Path, tmp_path: Path) -> None:
    ds = copy_dataset(tiny_dataset, tmp_path / "ds")
    body = b"".join(f"{i:06d}.png {0.5 * i}\n".encode() for i in range(4))
    write_stamps(ds, b"# recorded by \xff\xfe rig \xe9\n" + body)
    np.testing.assert_allclose(open_dataset(ds).timestamps, [0.0, 0.5, 1.0, 1.5])


def test_non_utf8_data_line_is_refused(tiny_dataset: Path, tmp_path: Path) -> None:
    ds = copy_dataset(tiny_dataset, tmp_path / "ds")
    write_stamps(ds, b"000000.png 0\n000001\xff.png 1\n")
    with pytest.raises(DatasetError, match=r"timestamps.txt:2: not UTF-8"):
        open_dataset(ds)


def test_duplicate_timestamp_entry_is_refused(tiny_dataset: Path, tmp_path: Path) -> None:
    ds = copy_dataset(tiny_dataset, tmp_path / "ds")
    write_stamps(ds, [f"{i:06d}.png {i}" for i in range(4)] + ["000001.png 7"])
    with pytest.raises(DatasetError, match=r"timestamps.txt:5: second timestamp.*line 2"):
        open_dataset(ds)


def test_backwards_timestamps_via_cli_write_nothing(
    tiny_dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ds = copy_dataset(tiny_dataset, tmp_path / "ds")
    write_stamps(ds, [f"{i:06d}.png {3 - i}" for i in range(4)])
    code, err = cli(["reconstruct", str(ds), "--out", str(tmp_path / "out"), "--quiet"], capsys)
    assert_refused(code, err, "timestamps.txt:2:")
    assert not (tmp_path / "out").exists()


# -- command-line numbers and --config shape ----------------------------------------


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "-1", "0"])
def test_keyframe_parallax_must_be_finite_and_positive(
    tiny_dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], value: str
) -> None:
    out = tmp_path / "out"
    argv = ["reconstruct", str(tiny_dataset), "--out", str(out), "--quiet"]
    code, err = cli([*argv, f"--keyframe-parallax={value}"], capsys)
    assert_refused(code, err, "--keyframe-parallax")
    assert not out.exists()


@pytest.mark.parametrize("value", ["inf", "nan", "-inf", "0", "-5", "1e300"])
def test_baseline_distance_must_be_finite_positive_and_bounded(
    tiny_dataset: Path, capsys: pytest.CaptureFixture[str], value: str
) -> None:
    rig = str(tiny_dataset / "rig.yaml")
    code, err = cli(["baseline", "--rig", rig, f"--distance={value}"], capsys)
    assert_refused(code, err, "--distance")


def test_baseline_plot_into_missing_folder(
    tiny_dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plot = tmp_path / "missing" / "fig9.png"
    rig = str(tiny_dataset / "rig.yaml")
    code, err = cli(["baseline", "--rig", rig, "--plot", str(plot)], capsys)
    assert_refused(code, err, "--plot", "does not exist")
    assert not (tmp_path / "missing").exists()


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("sfm: [1, 2]\n", "sfm"),
        ("model: 3\n", "model"),
        ("analysis: [[min_height_mm, 1.0]]\n", "analysis"),
        ("sfm: {keyframe_min_parallax_deg: .nan}\n", "sfm.keyframe_min_parallax_deg"),
        ("analysis: {min_height_mm: .inf}\n", "analysis.min_height_mm"),
        ("analysis: {grid_mm: 0}\n", "analysis.grid_mm"),
        ("sfm: {bundle: {max_tracks: -5}}\n", "sfm.bundle.max_tracks"),
        ("sfm: {bundle: {window_keyframes: -3}}\n", "sfm.bundle.window_keyframes"),
    ],
)
def test_config_sections_and_values_are_checked(
    tiny_dataset: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    text: str,
    field: str,
) -> None:
    config = tmp_path / "c.yaml"
    config.write_text(text)
    out = tmp_path / "out"
    argv = ["reconstruct", str(tiny_dataset), "--out", str(out), "--config", str(config)]
    code, err = cli([*argv, "--quiet"], capsys)
    assert_refused(code, err, f"c.yaml: {field}:")
    assert not out.exists()
