"""``omnipipe evaluate`` on partial or malformed inputs (issue 15).

Rules (evaluation/__init__.py docstring): fewer ground-truth poses than frames,
a scene.json or report.json that is not a proper object, or defects without their
keys are refused with one line and exit code 1; without scene.json the trajectory is
evaluated and the output says that wall, diameter and defects were not.

The "reconstruction" here is written by hand from the ground truth (trajectory =
true poses, so the ATE is 0), which makes the expected numbers exact.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from omnipipe.cli import main
from omnipipe.dataset import read_tum, write_tum


@pytest.fixture
def case(tiny_dataset: Path, tmp_path: Path) -> tuple[Path, Path]:
    """A writable dataset copy and a reconstruction folder made from its ground truth."""
    ds = tmp_path / "ds"
    shutil.copytree(tiny_dataset, ds)
    rec = tmp_path / "rec"
    rec.mkdir()
    stamps, poses = read_tum(ds / "ground_truth" / "poses.txt")
    write_tum(rec / "trajectory.txt", stamps, poses)
    scene = json.loads((ds / "ground_truth" / "scene.json").read_text())
    measured = [dict(d, height_mm=d["height_mm"] + 0.25) for d in scene["defects"]]
    report = {"frames": 4, "frames_registered": 4, "inner_diameter_mm": 201.5, "defects": measured}
    (rec / "report.json").write_text(json.dumps(report))
    return ds, rec


def evaluate(
    ds: Path, rec: Path, capsys: pytest.CaptureFixture[str], *extra: str
) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(["evaluate", str(rec), str(ds), *extra])
    out, err = capsys.readouterr()
    return code, out, err


def assert_refused(code: int, err: str, *needles: str) -> None:
    assert code == 1
    assert err.count("\n") == 1 and err.startswith("omnipipe evaluate: error: "), err
    for needle in needles:
        assert needle in err, err


def test_complete_inputs_are_evaluated(
    case: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = evaluate(*case, capsys, "--json")
    assert code == 0 and err == ""
    res = json.loads(out)
    assert res["trajectory"]["ate_rmse_mm"] < 1e-3
    assert res["diameter"]["error_mm"] == pytest.approx(-0.5)
    assert res["defects"][0]["errors"]["height_mm"] == pytest.approx(0.25)
    assert res["not_evaluated"] == [] and res["warnings"] == []


@pytest.mark.parametrize(
    ("scene", "needle"),
    [
        ({}, "inner_diameter_mm missing"),
        ([], "must hold a JSON object"),
        ({"inner_diameter_mm": 202.0}, "pipe missing"),
        ({"inner_diameter_mm": 202.0, "pipe": {"foo": 1}}, "not a valid pipe description"),
        ("KEEP-PIPE", "defects[0].height_mm"),
    ],
    ids=["empty", "list", "no-pipe", "bad-pipe", "bad-defect"],
)
def test_malformed_scene_json_is_refused(
    case: tuple[Path, Path], capsys: pytest.CaptureFixture[str], scene: object, needle: str
) -> None:
    ds, rec = case
    path = ds / "ground_truth" / "scene.json"
    if scene == "KEEP-PIPE":
        full = json.loads(path.read_text())
        scene = {**full, "defects": [{**full["defects"][0], "height_mm": "tall"}]}
    path.write_text(json.dumps(scene))
    code, _, err = evaluate(ds, rec, capsys)
    assert_refused(code, err, "scene.json", needle)


@pytest.mark.parametrize(
    ("report", "needle"),
    [
        ([], "must hold a JSON object"),
        ({"inner_diameter_mm": 201.5, "defects": {"kind": "bulge"}}, "defects must be a list"),
        ({"inner_diameter_mm": 201.5, "defects": [{"kind": "bulge"}]}, "defects[0].height_mm"),
    ],
    ids=["list", "defects-not-list", "defect-without-keys"],
)
def test_malformed_report_json_is_refused(
    case: tuple[Path, Path], capsys: pytest.CaptureFixture[str], report: object, needle: str
) -> None:
    ds, rec = case
    (rec / "report.json").write_text(json.dumps(report))
    code, _, err = evaluate(ds, rec, capsys)
    assert_refused(code, err, "report.json", needle)


def test_fewer_true_poses_than_frames_is_refused(
    case: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    ds, rec = case
    poses = ds / "ground_truth" / "poses.txt"
    poses.write_text("".join(poses.read_text().splitlines(keepends=True)[:3]))
    code, _, err = evaluate(ds, rec, capsys)
    assert_refused(code, err, "poses.txt", "3 poses for 4 frames")


def test_missing_scene_json_is_reported_not_hidden(
    case: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    ds, rec = case
    (ds / "ground_truth" / "scene.json").unlink()
    code, out, err = evaluate(ds, rec, capsys)
    assert code == 0 and err == ""
    assert "trajectory: ATE" in out
    assert "not evaluated: wall, diameter, defects" in out
    code, out, _ = evaluate(ds, rec, capsys, "--json")
    res = json.loads(out)
    assert res["not_evaluated"] == ["wall", "diameter", "defects"]
    assert res["diameter"] == {} and res["defects"] == []
    assert any("scene.json" in w for w in res["warnings"])


def test_poses_without_ground_truth_are_counted(
    case: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    ds, rec = case
    stamps, poses = read_tum(rec / "trajectory.txt")
    stamps[-1] += 0.05  # no true pose at this time
    write_tum(rec / "trajectory.txt", stamps, poses)
    code, out, _ = evaluate(ds, rec, capsys, "--json")
    res = json.loads(out)
    assert code == 0 and res["frames_registered"] == 3
    assert any("1 of 4 poses" in w for w in res["warnings"])


def test_non_utf8_comment_in_poses_is_ignored(
    case: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    ds, rec = case
    poses = ds / "ground_truth" / "poses.txt"
    poses.write_bytes(b"# mocap export \xff\xfe\n" + poses.read_bytes())
    code, out, _ = evaluate(ds, rec, capsys, "--json")
    assert code == 0 and json.loads(out)["frames_registered"] == 4
