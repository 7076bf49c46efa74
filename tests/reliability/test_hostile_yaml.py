"""Hostile YAML (issue 15, "memory blow-ups"): every YAML file omnipipe reads is bounded.

An alias bomb ("billion laughs": 9 levels of 9 aliases, 9^9 leaves once expanded) as
a rig.yaml field, as laser.plane, inside a --config section and as baseline --rig is
refused with one line naming the file, exit code 1, nothing written, and a Python
heap peak below 20 MB (tracemalloc; the unbounded loader needed > 6 GB).
"""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import pytest
import yaml

from omnipipe.cli import main
from omnipipe.errors import ConfigError
from omnipipe.safe_yaml import MAX_BYTES, load_yaml_file
from omnipipe.sim import paper_rig

PEAK_LIMIT_BYTES = 20_000_000


def bomb(levels: int = 9, width: int = 9) -> str:
    """One YAML flow value whose alias expansion has width**levels leaves."""
    value = "&l0 [" + ", ".join(['"lol"'] * width) + "]"
    for i in range(1, levels):
        value = f"&l{i} [{value}, " + ", ".join([f"*l{i - 1}"] * (width - 1)) + "]"
    return value


def rig_text(**fields: str) -> str:
    """The 64x48 paper rig as YAML text, with ``fields`` (camera_f, plane) replaced verbatim."""
    rig = paper_rig(64, 48).to_dict()
    cam = rig["camera"]
    f = fields.get("camera_f", repr(cam["f"]))
    plane = fields.get("plane", "[0.0, 0.0, 1.0, 82.0]")
    return (
        f"camera: {{width: 64, height: 48, cx: {cam['cx']}, cy: {cam['cy']}, f: {f}, "
        f"radius_min: {cam['radius_min']}, radius_max: {cam['radius_max']}}}\n"
        f"mirror: {{a: {rig['mirror']['a']}, b: {rig['mirror']['b']}}}\n"
        f"laser: {{plane: {plane}, channel: red}}\n"
    )


def run_cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, int]:
    """Exit code, stderr and the Python heap peak (bytes) of one in-process command."""
    capsys.readouterr()
    tracemalloc.start()
    try:
        code = main(argv)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return code, capsys.readouterr().err, peak


def assert_one_line_refusal(code: int, err: str, peak: int, *needles: str) -> None:
    assert code == 1
    assert err.count("\n") == 1 and err.startswith("omnipipe "), err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in err, err
    assert peak < PEAK_LIMIT_BYTES, f"heap peak {peak / 1e6:.1f} MB"


def copy_dataset(src: Path, dst: Path, rig: str) -> Path:
    dst.mkdir()
    (dst / "frames").mkdir()
    for p in (src / "frames").iterdir():
        (dst / "frames" / p.name).write_bytes(p.read_bytes())
    (dst / "rig.yaml").write_text(rig, encoding="utf-8")
    return dst


@pytest.mark.parametrize(
    ("fields", "name"),
    [({"camera_f": bomb()}, "rig field camera.f"), ({"plane": bomb()}, "laser.plane")],
)
def test_alias_bomb_in_rig_yaml_is_refused(
    tiny_dataset: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    fields: dict[str, str],
    name: str,
) -> None:
    ds = copy_dataset(tiny_dataset, tmp_path / "ds", rig_text(**fields))
    out = tmp_path / "out"
    code, err, peak = run_cli(["reconstruct", str(ds), "--out", str(out), "--quiet"], capsys)
    assert_one_line_refusal(code, err, peak, "rig.yaml", "alias")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"], "nothing may be written"


def test_alias_bomb_in_config_section_is_refused(
    tiny_dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "c.yaml"
    config.write_text(f"sfm:\n  keyframe_min_parallax_deg: {bomb()}\n", encoding="utf-8")
    out = tmp_path / "out"
    argv = ["reconstruct", str(tiny_dataset), "--out", str(out), "--config", str(config)]
    code, err, peak = run_cli([*argv, "--quiet"], capsys)
    assert_one_line_refusal(code, err, peak, "c.yaml", "alias")
    assert not out.exists()


def test_alias_bomb_as_baseline_rig_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = tmp_path / "rig.yaml"
    rig.write_text(rig_text(camera_f=bomb()), encoding="utf-8")
    plot = tmp_path / "fig9.png"
    code, err, peak = run_cli(["baseline", "--rig", str(rig), "--plot", str(plot)], capsys)
    assert_one_line_refusal(code, err, peak, "rig.yaml", "alias")
    assert not plot.exists()


def test_aliases_within_the_budget_are_read(tmp_path: Path) -> None:
    """Sharing a block with an anchor is legitimate and still works."""
    p = tmp_path / "c.yaml"
    p.write_text("a: &shared {k: 1, m: [1, 2]}\nb: *shared\n", encoding="utf-8")
    assert load_yaml_file(p, "config") == {"a": {"k": 1, "m": [1, 2]}, "b": {"k": 1, "m": [1, 2]}}
    # A small bomb (3 levels of 3: 27 leaves) is within the budget and expands as YAML says.
    p.write_text(f"x: {bomb(3, 3)}\n", encoding="utf-8")
    data = load_yaml_file(p, "config")
    assert len(data["x"]) == 3 and len(data["x"][2]) == 3 and data["x"][2][2] == ["lol"] * 3


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("a: &a [1, *a]\n", "recursive alias"),
        ("x: " + "[" * 200 + "]" * 200 + "\n", "nested deeper"),
        ("x: " + "[" * 5000 + "]" * 5000 + "\n", "nested deeper"),
        ("x: [" + ", ".join(["1"] * 12000) + "]\n", "more than"),
        ("date: 2024-13-45\n", "cannot be read"),
    ],
    ids=["recursive", "deep", "very-deep", "too-many-values", "impossible-date"],
)
def test_degenerate_documents_are_refused(tmp_path: Path, text: str, reason: str) -> None:
    p = tmp_path / "rig.yaml"
    p.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError, match=reason) as err:
        load_yaml_file(p, "rig")
    assert err.value.source == str(p)


def test_oversized_file_is_refused_unread(tmp_path: Path) -> None:
    p = tmp_path / "rig.yaml"
    p.write_text("# " + "x" * MAX_BYTES + "\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="too large"):
        load_yaml_file(p, "rig")


def test_safe_loader_semantics_are_kept(tmp_path: Path) -> None:
    """Only safe tags: a Python object tag is a YAML error, not code execution."""
    p = tmp_path / "c.yaml"
    p.write_text("x: !!python/object/apply:os.system ['true']\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_yaml_file(p, "config")
    p.write_text(yaml.safe_dump({"a": [1.5, "b", None, True]}), encoding="utf-8")
    assert load_yaml_file(p, "config") == {"a": [1.5, "b", None, True]}
