"""calibrate camera / laser on a simulated calibration set, rig import-ocam, refusals."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from omnipipe.calibrate.ocam_io import read_ocam, write_ocam
from omnipipe.camera import camera_from_rig
from omnipipe.camera.convert import rig_in_model
from omnipipe.cli import main
from omnipipe.rig_yaml import load_rig
from omnipipe.sim import paper_rig
from omnipipe.sim.calibration import write_calibration_set

TARGET = "checkerboard:8x6:12"


@pytest.fixture(scope="module")
def calib_set(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small calibration set: 8 views at 640x480 (seed 2)."""
    out = tmp_path_factory.mktemp("calib") / "set"
    write_calibration_set(out, seed=2, size=(640, 480), views=8)
    return out


def _images(d: Path) -> list[str]:
    return sorted(str(p) for p in (d / "images").glob("*.png"))


def test_calibrate_camera_then_laser(calib_set: Path, tmp_path: Path, capsys) -> None:
    rig_cam = tmp_path / "camera.yaml"
    assert main(["calibrate", "camera", *_images(calib_set), "--target", TARGET, "--out", str(rig_cam)]) == 0
    out = capsys.readouterr().out
    rms = float(out.split("reprojection RMS ")[1].split()[0])
    assert rms <= 0.2  # px: the acceptance bound
    assert out.count(" px\n") >= 4  # one line per used image
    rig = load_rig(rig_cam)
    assert rig.camera_model == "unified" and rig.laser is None
    truth = json.loads((calib_set / "ground_truth" / "calibration.json").read_text())
    # the principal point is the image of the (slightly tilted) mirror axis: within 3 px
    assert abs(rig.camera.cx - truth["camera"]["cx"]) < 3 and abs(rig.camera.cy - truth["camera"]["cy"]) < 3
    rig_full = tmp_path / "rig.yaml"
    assert main(["calibrate", "laser", *_images(calib_set), "--rig", str(rig_cam), "--target", TARGET,
                 "--out", str(rig_full)]) == 0
    k = np.array(load_rig(rig_full).laser.k)
    assert 0.025 <= load_rig(rig_full).laser.offset_sigma_mm < 0.1  # fit and board poses, written
    k_true = np.array(truth["laser"]["plane"])
    k_true /= np.linalg.norm(k_true[:3])
    angle = np.degrees(np.arccos(min(1.0, abs(float(k[:3] @ k_true[:3])))))
    # Loose bounds here (8 small views); the acceptance numbers come from
    # benchmarks/bench_calibration.py.
    assert angle < 1.0 and abs(k[3] - k_true[3]) < 1.0


def test_refusals_one_line_nothing_written(calib_set: Path, tmp_path: Path, capsys) -> None:
    imgs = _images(calib_set)
    out = tmp_path / "rig.yaml"
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((480, 640, 3), 90, np.uint8))
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), cv2.resize(cv2.imread(imgs[0]), (320, 240)))
    cases = [
        ([str(blank)] * 3, TARGET, "no 8x6 checkerboard"),
        (imgs, "checkerboard:5x4:12", "5x4"),
        # issue 27: a wrong size that makes the fit diverge names --target too
        (imgs, "checkerboard:7x3:12", "is the board really 7x3 inner corners (check --target"),
        (imgs[:2], TARGET, "at least 4"),
        ([*imgs[:3], str(small)], TARGET, "small.png"),
        (imgs, "checkerboard:8x6", "--target"),
        (imgs, "checkerboard:8x6:0", "--target"),
    ]
    for images, target, message in cases:
        assert main(["calibrate", "camera", *images, "--target", target, "--out", str(out)]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], (message, err)
        assert not out.exists()


def test_import_ocam(tmp_path: Path, capsys) -> None:
    """An OCamCalib file written by hand from a fitted model converts back to the same rays."""
    rig = paper_rig(400, 300)
    ocam_rig, _ = rig_in_model(rig, "ocam")
    # a realistic file: off-centre centre and a small affine term, rows first
    params = ocam_rig.model
    from dataclasses import replace

    cam_in = replace(ocam_rig.camera, cx=201.25, cy=148.75)
    params = replace(params, c=1.0008, d=0.0004, e=-0.0003)
    path = tmp_path / "calib_results.txt"
    write_ocam(cam_in, params, path)
    text = path.read_text()
    assert "148.750000 201.250000" in text  # row first
    assert "\n300 400\n" in text  # height width
    intr, p2 = read_ocam(path)
    assert (intr.cx, intr.cy) == (201.25, 148.75)
    np.testing.assert_allclose(p2.polynomial, params.polynomial, rtol=1e-6)
    # with the laser of another rig
    other = tmp_path / "other.yaml"
    from omnipipe.rig_yaml import save_rig

    save_rig(rig, other)
    out = tmp_path / "rig.yaml"
    assert main(["rig", "import-ocam", str(path), "--out", str(out), "--laser-from", str(other),
                 "--radius-min", "25", "--radius-max", "149"]) == 0
    imported = load_rig(out)
    assert imported.camera_model == "ocam" and imported.laser == rig.laser
    # OCamCalib's cam2world by hand (rows first, its own frame) -> rig frame (y, x, z)
    cam = camera_from_rig(imported)
    px = np.array([[300.0, 100.0], [120.0, 250.0]])  # (col, row)
    a0 = np.asarray(params.polynomial)
    for (col, row), ray in zip(px, cam.unproject(px), strict=True):
        u, v = row - 148.75, col - 201.25
        inv = 1.0 / (params.c - params.d * params.e)
        xp, yp = inv * (u - params.d * v), inv * (-params.e * u + params.c * v)
        z = np.polynomial.polynomial.polyval(np.hypot(xp, yp), a0)
        ocam_ray = np.array([xp, yp, z]) / np.linalg.norm([xp, yp, z])
        np.testing.assert_allclose(ray, ocam_ray[[1, 0, 2]], atol=1e-12)
    # refusals: existing out, broken file
    assert main(["rig", "import-ocam", str(path), "--out", str(out)]) == 1
    assert "already exists" in capsys.readouterr().err
    bad = tmp_path / "bad.txt"
    bad.write_text(text.replace("300 400", "300"))
    out2 = tmp_path / "rig2.yaml"
    assert main(["rig", "import-ocam", str(bad), "--out", str(out2)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "image size" in err[0] and not out2.exists()
    shutil.rmtree(tmp_path / "nothing", ignore_errors=True)


def test_ring_diameter_through_a_rig() -> None:
    """The true ring of a known pipe, seen through the exact rig, has the pipe's diameter
    (ellipse minor axis, tilted plane, off-centre pipe); a 1 % wrong laser offset shows."""
    from dataclasses import replace

    from omnipipe.calibrate.laser import ring_section_axes
    from omnipipe.sim.calibration import draw_truth, ring_pixels

    tilt = np.radians(1.5)
    k = np.array([np.sin(tilt), 0.0, np.cos(tilt), 82.0])
    truth = replace(draw_truth(4, (400, 300), 3, design=True), laser_k=k)
    cam = camera_from_rig(paper_rig(400, 300))  # the design rig is the exact hyperboloid
    for diameter, centre in ((202.0, (0.0, 0.0)), (160.0, (6.0, -4.0))):
        px = ring_pixels(truth, diameter, centre, angles=180)
        assert len(px) > 150
        minor, major = ring_section_axes(cam, k, px)
        assert abs(minor - diameter) < 0.02 and major >= minor  # mm
        k_far = k * np.array([1, 1, 1, 1.01])
        assert abs(ring_section_axes(cam, k_far, px)[0] - 1.01 * diameter) < 0.03


def test_ocam_roi_and_crop_round_trip(tmp_path: Path, capsys) -> None:
    """The file's ROI radii and crop survive write -> read -> import: the rig has the
    crop's size (so the recorded frames are accepted), the centre moved into it, the same
    rays as the full image's model at the shifted pixels; --laser-from takes a rig of
    another image size (the plane is in mm)."""
    from dataclasses import replace

    from omnipipe.calibrate.ocam_io import OcamCrop, read_ocam_file
    from omnipipe.errors import ConfigError
    from omnipipe.rig_yaml import save_rig

    rig = paper_rig(400, 300)
    ocam_rig, _ = rig_in_model(rig, "ocam")
    full = replace(ocam_rig.camera, cx=201.25, cy=148.75, radius_min=25.5, radius_max=149.0)
    crop = OcamCrop(row=10, col=30, height=280, width=340)
    path = tmp_path / "calib_results.txt"
    write_ocam(full, ocam_rig.model, path, crop)
    intr, params, crop_back = read_ocam_file(path)
    assert crop_back == crop
    assert (intr.width, intr.height, intr.cx, intr.cy) == (400, 300, 201.25, 148.75)
    assert (intr.radius_min, intr.radius_max) == (25.5, 149.0)
    cropped, _ = read_ocam(path)
    assert (cropped.width, cropped.height) == (340, 280)
    assert (cropped.cx, cropped.cy, cropped.radius_min) == (171.25, 138.75, 25.5)
    # The cropped form written and read again is the same camera.
    again = tmp_path / "again.txt"
    write_ocam(cropped, params, again)
    assert read_ocam(again)[0] == cropped
    # Imported with the laser of a full-size (800x600) rig: accepted, plane unchanged.
    big = tmp_path / "big.yaml"
    save_rig(paper_rig(800, 600), big)
    out = tmp_path / "rig.yaml"
    assert main(["rig", "import-ocam", str(path), "--out", str(out), "--laser-from", str(big)]) == 0
    assert "800x600" in capsys.readouterr().out
    imported = load_rig(out)
    assert (imported.camera.width, imported.camera.height) == (340, 280)
    assert (imported.camera.radius_min, imported.camera.radius_max) == (25.5, 149.0)
    assert imported.laser == paper_rig(800, 600).laser
    px = np.array([[100.0, 50.0], [300.0, 250.0], [170.0, 20.0]])
    full_cam = camera_from_rig(replace(ocam_rig, camera=full))
    np.testing.assert_allclose(
        camera_from_rig(imported).unproject(px), full_cam.unproject(px + np.array([30.0, 10.0])), atol=1e-9
    )
    # A crop that leaves the image, and an unknown block, are refused naming the line.
    bad = tmp_path / "bad.txt"
    bad.write_text(path.read_text().replace("10 30 280 340", "10 30 280 380"))
    with pytest.raises(ConfigError, match="leaves the 300x400 image"):
        read_ocam(bad)
    bad.write_text(path.read_text() + "#something else\n1 2 3\n")
    with pytest.raises(ConfigError, match="unexpected data after the image size"):
        read_ocam(bad)
