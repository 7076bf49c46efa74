"""omnipipe evaluate on a simulated dataset with a synthetic reconstruction."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from omnipipe.cli import main
from omnipipe.contract import CORE_KEYS
from omnipipe.dataset import read_tum, write_tum
from omnipipe.evaluation import EvaluationConfig, EvaluationInputs, run
from omnipipe.geometry import apply, invert
from omnipipe.sim.scene import Pipe


def _fake_reconstruction(
    dataset: Path, out: Path, *, shift_mm: float, diameter_error: float
) -> None:
    """A reconstruction made from ground truth: world = first rig frame, wall points
    on the true wall pushed outwards by ``shift_mm``."""
    out.mkdir()
    stamps, poses = read_tum(dataset / "ground_truth" / "poses.txt")
    first_from_world = invert(poses[0])
    write_tum(out / "trajectory.txt", stamps, first_from_world[None] @ poses)
    scene = json.loads((dataset / "ground_truth" / "scene.json").read_text())
    pipe = Pipe.from_dict(scene["pipe"])
    rng = np.random.default_rng(0)
    sigma = rng.uniform(150.0, 250.0, 2000)
    theta = rng.uniform(-np.pi, np.pi, 2000)
    centre, n, b, _ = pipe.frame_at(sigma)
    radius = pipe.wall_radius(sigma, theta) + shift_mm
    pts = centre + radius[:, None] * (np.cos(theta)[:, None] * n + np.sin(theta)[:, None] * b)
    trimesh.PointCloud(apply(first_from_world, pts)).export(out / "points.ply")
    defects = [dict(d, height_mm=d["height_mm"] + 0.2) for d in scene["defects"]]
    report = {
        "frames": 24,
        "inner_diameter_mm": scene["inner_diameter_mm"] + diameter_error,
        "defects": defects,
    }
    (out / "report.json").write_text(json.dumps(report))


def test_evaluation_measures_known_errors(small_dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "rec"
    _fake_reconstruction(small_dataset, out, shift_mm=0.5, diameter_error=0.3)
    res = run(EvaluationConfig(), EvaluationInputs(out, small_dataset))
    assert res.frames_registered == 24
    assert res.trajectory.ate_rmse_mm < 1e-6 and res.trajectory.rotation_rmse_deg < 1e-5
    assert res.wall["bias_mm"] == pytest.approx(0.5, abs=1e-6)
    assert res.diameter["error_mm"] == pytest.approx(0.3)
    assert len(res.defects) == 1 and res.defects[0].found
    assert res.defects[0].errors()["height_mm"] == pytest.approx(0.2)
    assert res.defects[0].errors()["angle_deg"] == pytest.approx(0.0, abs=1e-9)
    row = res.to_dict()["defects"][0]  # the JSON form: what was read, and the errors
    assert row["found"] and row["true"] == {k: row["true"][k] for k in CORE_KEYS}
    assert row["measured"]["height_mm"] == pytest.approx(row["true"]["height_mm"] + 0.2)


def test_evaluate_cli(
    small_dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "rec"
    _fake_reconstruction(small_dataset, out, shift_mm=0.0, diameter_error=0.0)
    assert main(["evaluate", str(out), str(small_dataset), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["trajectory"]["ate_rmse_mm"] < 1e-6
    assert main(["evaluate", str(out), str(small_dataset)]) == 0
    assert "ATE" in capsys.readouterr().out
    # No ground truth: one line, exit code 1.
    assert main(["evaluate", str(out), str(tmp_path / "missing")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "dataset directory not found" in err


def test_evaluate_says_outside_the_measured_stretch_not_not_found(
    small_dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A true defect no station came near is "outside the measured stretch"; one inside
    the measured stretch that was missed stays "NOT FOUND"."""
    out = tmp_path / "rec"
    _fake_reconstruction(small_dataset, out, shift_mm=0.0, diameter_error=0.0)
    report = json.loads((out / "report.json").read_text())
    for stations, expected in (
        ([{"axial_mm": 1000.0}, {"axial_mm": 1100.0}], "outside the measured stretch"),
        ([{"axial_mm": -1000.0}, {"axial_mm": 1000.0}], "NOT FOUND"),
    ):
        (out / "report.json").write_text(json.dumps(dict(report, defects=[], stations=stations)))
        assert main(["evaluate", str(out), str(small_dataset)]) == 0
        lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("bulge")]
        assert len(lines) == 1 and expected in lines[0], lines
        assert "NOT FOUND" not in lines[0] or expected == "NOT FOUND"
