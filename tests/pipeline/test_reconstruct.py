"""omnipipe reconstruct end to end on a small simulated dataset, and its refusals."""

from __future__ import annotations

import json
import re
import shutil
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest
import trimesh

from omnipipe.cli import main
from omnipipe.laser.ring import LaserRing


@pytest.fixture(scope="module")
def reconstruction(small_dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("rec") / "out"
    assert main(["reconstruct", str(small_dataset), "--out", str(out), "--quiet"]) == 0
    return out


def test_every_contract_output(reconstruction: Path, small_dataset: Path) -> None:
    for name in ("trajectory.txt", "points.ply", "mesh.ply", "report.json", "report.html"):
        assert (reconstruction / name).is_file(), name
    report = json.loads((reconstruction / "report.json").read_text())
    assert report["frames"] == 24 and report["frames_registered"] == 24
    assert set(report["timings_s"]) >= {"laser", "sfm", "model", "analysis", "total"}
    truth = json.loads((small_dataset / "ground_truth" / "scene.json").read_text())
    # 400x300 images: the diameter within 1.5 mm (full size: see benchmarks).
    assert abs(report["inner_diameter_mm"] - truth["inner_diameter_mm"]) < 1.5
    mesh = trimesh.load(reconstruction / "mesh.ply", process=False)
    assert len(mesh.faces) > 1000
    lines = (reconstruction / "trajectory.txt").read_text().splitlines()
    assert len(lines) == 24
    assert [float(v) for v in lines[0].split()[1:4]] == [0.0, 0.0, 0.0]  # world = first rig frame


def test_existing_output_is_refused(reconstruction: Path, small_dataset: Path, capsys) -> None:
    assert main(["reconstruct", str(small_dataset), "--out", str(reconstruction), "--quiet"]) == 1
    assert "already exists" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        ("no_rig", "rig.yaml"),
        ("no_frames", "frames"),
        ("empty", "rig.yaml"),
        ("bad_field", "mirror.b"),
        ("missing_field", "camera.f"),
        ("corrupt", "000004.png"),
        ("truncated", "000007.png"),
        ("other_size", "000009.png"),
        ("no_laser", "no laser ring"),
    ],
)
def test_bad_input_one_line_and_nothing_written(small_dataset: Path, tmp_path: Path, capsys, damage, message) -> None:
    ds = tmp_path / "ds"
    shutil.copytree(small_dataset, ds)
    if damage == "no_rig":
        (ds / "rig.yaml").unlink()
    elif damage == "bad_field":
        (ds / "rig.yaml").write_text((ds / "rig.yaml").read_text().replace("b: 32.49", "b: 0"))
    elif damage == "no_frames":
        shutil.rmtree(ds / "frames")
    elif damage == "empty":
        shutil.rmtree(ds)
        ds.mkdir()
    elif damage == "missing_field":
        text = (ds / "rig.yaml").read_text()
        (ds / "rig.yaml").write_text(re.sub(r"\bf: [0-9.]+,\s*", "", text))
    elif damage == "truncated":
        data = (ds / "frames" / "000007.png").read_bytes()
        (ds / "frames" / "000007.png").write_bytes(data[: len(data) // 2])
    elif damage == "other_size":
        from PIL import Image

        Image.new("RGB", (200, 150)).save(ds / "frames" / "000009.png")
    elif damage == "corrupt":
        (ds / "frames" / "000004.png").write_bytes(b"\x89PNG garbage")
    elif damage == "no_laser":
        (ds / "rig.yaml").write_text((ds / "rig.yaml").read_text().replace("channel: red", "channel: blue"))
    out = tmp_path / "out"
    assert main(["reconstruct", str(ds), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out")]


def test_output_path_that_is_a_file_is_refused(small_dataset: Path, tmp_path: Path, capsys) -> None:
    target = tmp_path / "report.txt"
    target.write_text("keep me")
    assert main(["reconstruct", str(small_dataset), "--out", str(target), "--force", "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert "not a directory" in err and len(err.splitlines()) == 1
    assert target.read_text() == "keep me"


def test_a_black_frame_mid_run_is_not_registered(small_dataset: Path, tmp_path: Path) -> None:
    """A frame with nothing to see (lights failed) keeps the run going, flagged, not faked
    (without the robot's sensors: with odometry the frame is placed by it, flagged)."""
    from PIL import Image

    ds = tmp_path / "ds"
    shutil.copytree(small_dataset, ds)
    for sensor in ("odometry.txt", "imu.txt"):
        (ds / sensor).unlink(missing_ok=True)
    size = Image.open(ds / "frames" / "000012.png").size
    Image.new("RGB", size).save(ds / "frames" / "000012.png")
    out = tmp_path / "out"
    assert main(["reconstruct", str(ds), "--out", str(out), "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["frames"] == 24 and report["frames_registered"] < 24
    assert any("000012" in w or "frame 12" in w or "->12" in w for w in report["warnings"])
    stamps = [float(line.split()[0]) for line in (out / "trajectory.txt").read_text().splitlines()]
    assert 12.0 not in stamps


def test_the_analysis_runs_without_the_stations_rings_held(
    small_dataset: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Under analysis.run the reconstruction holds the integrated points and the rings'
    pixels (the texture's), not the rings (80 bytes a sample: 36 MB at 10,000 frames)."""
    import sys

    from omnipipe import analysis
    from omnipipe.laser.ring import LaserRing

    run = analysis.run
    held: list[str] = []

    def checked(*args: object, **kwargs: object) -> object:
        caller = sys._getframe(1).f_locals
        held.extend(
            name for name, value in caller.items()
            if isinstance(value, list) and any(isinstance(v, LaserRing) for v in value)
        )
        held.append("checked")
        return run(*args, **kwargs)

    monkeypatch.setattr(analysis, "run", checked)
    assert main(["reconstruct", str(small_dataset), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    assert held == ["checked"]


def test_the_stations_rings_wait_in_the_scratch_until_integrated(
    small_dataset: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Before the analysis the stations' rings are integrated from the run's scratch
    (omnipipe.spill), not held in memory all at once; the result is the same."""
    from omnipipe import model
    from omnipipe.pipeline.stage_calls import ring_on_disk
    from omnipipe.spill import Pack, is_on_disk

    integrate = model.integrate
    seen: list[bool] = []

    def checked(poses: np.ndarray, points: list[np.ndarray], in_scratch: bool = False) -> object:
        seen.extend(is_on_disk(p) for p in points if len(p))
        assert in_scratch
        return integrate(poses, points, in_scratch)

    monkeypatch.setattr(model, "integrate", checked)
    assert main(["reconstruct", str(small_dataset), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    assert seen and all(seen)
    ring = LaserRing(
        np.arange(8.0).reshape(4, 2), np.arange(4.0), np.ones(4), np.ones(4, np.float32),
        points_in_rig=np.arange(12.0).reshape(4, 3)[:, ::-1], warnings=["w"],
    )
    held = ring_on_disk(Pack(), ring)
    for f in fields(LaserRing):
        a, b = getattr(ring, f.name), getattr(held, f.name)
        if isinstance(a, np.ndarray):
            assert b.dtype == a.dtype and np.array_equal(a, b) and (is_on_disk(b) or a.size == 0), f.name
        else:
            assert a == b, f.name


def test_results_held_to_the_end_wait_in_the_scratch(small_dataset: Path, reconstruction: Path, tmp_path: Path) -> None:
    """The arrays that grow with the run (model, per-point analysis) are held in scratch
    files (omnipipe.spill), and written out they are the CLI's outputs byte for byte."""
    from dataclasses import replace

    from omnipipe.dataset import open_dataset
    from omnipipe.pipeline import ReconstructConfig, run, write
    from omnipipe.spill import is_on_disk

    rec = run(replace(ReconstructConfig.default(), workers=1), open_dataset(small_dataset))
    mdl, res = rec.model, rec.analysis
    held = {
        "points": mdl.points_in_world, "colours": mdl.colours, "faces": mdl.mesh_faces,
        "textured vertices": mdl.textured_vertices, "textured faces": mdl.textured_faces,
        "uvs": mdl.textured_uvs, "atlas": mdl.texture, "alpha": mdl.unrolled.alpha,
        "axial": res.point_sigma_mm, "angle": res.point_theta_rad, "deviation": res.point_deviation_mm,
    }
    assert [name for name, a in held.items() if not is_on_disk(a)] == []
    w = mdl.unrolled.image.shape[1]
    assert np.shares_memory(mdl.unrolled.image, mdl.texture[:, :w])  # one image, not two
    write(rec, tmp_path / "out")
    for name in ("points.ply", "mesh.ply", "model.glb", "model.obj", "model_texture.png", "unrolled.png", "trajectory.txt"):
        assert (tmp_path / "out" / name).read_bytes() == (reconstruction / name).read_bytes(), name
