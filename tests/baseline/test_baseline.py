"""Baseline error model (Sec. IV): derivative, consistency with the camera, paper's optima."""

from __future__ import annotations

import json

import numpy as np
import pytest

from omnipipe.baseline import (
    dr_dd,
    error_rate,
    image_radius,
    optimal_baseline,
    quantisation_error_px,
)
from omnipipe.camera import OmniCamera
from omnipipe.cli import main
from omnipipe.rig import CameraIntrinsics, Mirror

PAPER = Mirror(21.57, 32.49)


def test_image_radius_is_the_camera_projection() -> None:
    cam = OmniCamera(CameraIntrinsics(1600, 1200, 799.5, 599.5, 1730.14), PAPER)
    rng = np.random.default_rng(0)
    l = rng.uniform(20, 300, 200)
    d = rng.uniform(50, 300, 200)
    px, _ = cam.project(np.stack([d, np.zeros_like(d), -l], axis=1))
    assert np.allclose(image_radius(l, d, PAPER, 1730.14), px[:, 0] - cam.cx, atol=1e-9)


def test_derivative_matches_finite_differences_of_the_projection() -> None:
    rng = np.random.default_rng(1)
    l = rng.uniform(10, 400, 500)
    d = rng.uniform(30, 400, 500)
    h = 1e-4
    fd = (image_radius(l, d + h, PAPER, 1000.0) - image_radius(l, d - h, PAPER, 1000.0)) / (2 * h)
    assert np.allclose(dr_dd(l, d, PAPER, 1000.0), fd, rtol=1e-6)


def test_optima_match_the_paper() -> None:
    # Paper Fig. 9: 156 mm at d = 200 and 235 mm at d = 300 (within 2 mm).
    assert optimal_baseline(200.0, PAPER) == pytest.approx(156.0, abs=2.0)
    assert optimal_baseline(300.0, PAPER) == pytest.approx(235.0, abs=2.0)
    # The optimum scales with d and does not depend on f (docs/baseline.md on d = 100).
    assert optimal_baseline(100.0, PAPER, 500.0) == pytest.approx(
        optimal_baseline(200.0, PAPER, 2000.0) / 2, rel=1e-4
    )
    assert quantisation_error_px() == pytest.approx(np.sqrt(0.5))
    # A minimum: rates grow on both sides.
    lo = optimal_baseline(200.0, PAPER)
    r = error_rate(np.array([0.8 * lo, lo, 1.2 * lo]), 200.0, PAPER, 1730.0)
    assert r[1] < r[0] and r[1] < r[2]


def test_cli(tmp_path, capsys) -> None:
    from omnipipe.rig_yaml import save_rig
    from omnipipe.sim import paper_rig

    save_rig(paper_rig(), tmp_path / "rig.yaml")
    assert (
        main(
            [
                "baseline",
                "--rig",
                str(tmp_path / "rig.yaml"),
                "--distance",
                "200",
                "300",
                "--json",
                "--plot",
                str(tmp_path / "fig9.png"),
            ]
        )
        == 0
    )
    data = json.loads(capsys.readouterr().out)
    assert set(data["optimal_baseline_mm"]) == {"200", "300"}
    assert (tmp_path / "fig9.png").stat().st_size > 1000
    assert main(["baseline", "--rig", str(tmp_path / "missing.yaml")]) == 1
    assert "rig" in capsys.readouterr().err
