"""Camera models behind one interface: round trips, rig.yaml, conversion, reconstruction."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from omnipipe.camera import CameraModel, OcamCamera, OmniCamera, UnifiedCamera, camera_from_rig
from omnipipe.camera.convert import rig_in_model
from omnipipe.cli import main
from omnipipe.errors import ConfigError
from omnipipe.rig import OcamParams, Rig, UnifiedParams
from omnipipe.rig_yaml import load_rig, rig_from_dict, save_rig
from omnipipe.sim import paper_rig


def _unified_rig() -> Rig:
    base = paper_rig(400, 300)
    cam = replace(base.camera, cx=201.3, cy=148.2, f=79.6)  # f: (fx + fy) / 2
    params = UnifiedParams(0.97, 80.0, 79.2, 0.3, -0.05, 0.01, 0.002, -0.001)
    return Rig(camera=cam, mirror=None, laser=base.laser, model=params)


def _ocam_rig() -> Rig:
    base = paper_rig(400, 300)
    cam = replace(base.camera, cx=198.7, cy=151.1, f=39.4)  # f: |a0|
    params = OcamParams((-39.4, 0.0, 6.3e-3, 1e-7, -9.6e-9), None, 1.002, 0.001, -0.0007)
    return Rig(camera=cam, mirror=None, laser=base.laser, model=params)


@pytest.mark.parametrize("make", [lambda: paper_rig(400, 300), _unified_rig, _ocam_rig])
def test_round_trip_and_interface(make) -> None:
    rig = make()
    cam = camera_from_rig(rig)
    px = np.argwhere(cam.valid_mask())[:, ::-1].astype(float)[::7]  # (col, row), row-major
    rays = cam.unproject(px)
    assert np.allclose(np.linalg.norm(rays, axis=1), 1.0)
    back, valid = cam.project(rays)
    assert valid.mean() > 0.99
    np.testing.assert_allclose(back[valid], px[valid], atol=1e-6)  # px
    # points at any range project like their direction
    back2, _ = cam.project(rays * 123.0)
    np.testing.assert_allclose(back2[valid], px[valid], atol=1e-6)
    # rig frame: column grows with x, row with y, the centre sees -z
    centre = cam.unproject(np.array([[cam.cx, cam.cy + 1e-3]]))[0]
    assert centre[2] < -0.99
    right = cam.unproject(np.array([[cam.cx + 0.6 * cam.radius_max, cam.cy]]))[0]
    down = cam.unproject(np.array([[cam.cx, cam.cy + 0.6 * cam.radius_max]]))[0]
    assert right[0] > 0.3 and abs(right[1]) < 0.05 and down[1] > 0.3 and abs(down[0]) < 0.05
    lo, hi = cam.elevation_range()
    assert -np.pi / 2 < lo < hi < np.pi / 2
    assert cam.valid_mask().shape == (300, 400)


def test_factory_picks_the_model() -> None:
    assert isinstance(camera_from_rig(paper_rig(400, 300)), OmniCamera)
    assert isinstance(camera_from_rig(_unified_rig()), UnifiedCamera)
    assert isinstance(camera_from_rig(_ocam_rig()), OcamCamera)


@pytest.mark.parametrize("make", [lambda: paper_rig(400, 300), _unified_rig, _ocam_rig])
def test_rig_yaml_round_trip(make, tmp_path: Path) -> None:
    rig = make()
    save_rig(rig, tmp_path / "rig.yaml")
    loaded = load_rig(tmp_path / "rig.yaml")
    assert loaded == rig


def test_rig_without_laser_loads_and_reconstruct_refuses(small_dataset: Path, tmp_path: Path, capsys) -> None:
    data = paper_rig(400, 300).to_dict()
    del data["laser"]
    rig = rig_from_dict(data)
    assert rig.laser is None and rig.camera_model == "hyperboloid"
    ds = tmp_path / "ds"
    shutil.copytree(small_dataset, ds)
    save_rig(rig, ds / "rig.yaml")
    assert main(["reconstruct", str(ds), "--out", str(tmp_path / "out"), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no laser section" in err[0]
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda d: d["camera"].update(model="fisheye"), "camera.model"),
        (lambda d: d["camera"]["unified"].pop("xi"), "camera.unified.xi"),
        (lambda d: d["camera"]["unified"].update(distortion=[0, 0]), "camera.unified.distortion"),
        (lambda d: d["camera"]["unified"].update(fy=-1.0), "camera.unified.fy"),
        (lambda d: d["camera"].pop("unified"), "camera.unified"),
    ],
)
def test_bad_unified_fields_are_named(edit, field: str) -> None:
    data = _unified_rig().to_dict()
    edit(data)
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        rig_from_dict(data)


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda d: d["camera"]["ocam"].update(polynomial=[39.0, 0.0, 1e-3]), "camera.ocam.polynomial"),
        (lambda d: d["camera"]["ocam"].update(affine=[1.0, 1.0, 1.0]), "camera.ocam.affine"),
        (lambda d: d["camera"]["ocam"].update(polynomial=[-39.0, "x"]), r"camera.ocam.polynomial\[1\]"),
    ],
)
def test_bad_ocam_fields_are_named(edit, field: str) -> None:
    data = _ocam_rig().to_dict()
    edit(data)
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        rig_from_dict(data)


def test_conversion_reproduces_the_hyperboloid_rays() -> None:
    rig = paper_rig(400, 300)
    src = camera_from_rig(rig)
    px = np.argwhere(src.valid_mask())[:, ::-1].astype(float)[::5]  # (col, row), row-major
    for model, tol_px in (("unified", 1e-6), ("ocam", 1e-3)):
        converted, rms = rig_in_model(rig, model)
        assert converted.camera_model == model and rms < tol_px
        dst = camera_from_rig(converted)
        # every valid pixel sees the same ray (0.001 px at the rim's ~0.5 deg/px)
        cos = np.sum(src.unproject(px) * dst.unproject(px), axis=1)
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 1e-3
        back, valid = dst.project(src.unproject(px))
        np.testing.assert_allclose(back[valid], px[valid], atol=10 * tol_px)


@pytest.mark.slow  # 7 s: three reconstructions; the pipeline stays covered by tests/pipeline
def test_every_model_reconstructs_alike(eight_frames: Path, tmp_path: Path) -> None:
    """A paper-small run written in each model: diameters within 0.3 mm of each other."""
    base = eight_frames  # read only: the other models' rigs go beside copies of its frames
    diam = {}
    for model in ("hyperboloid", "unified", "ocam"):
        ds = base
        if model != "hyperboloid":
            ds = tmp_path / model
            shutil.copytree(base, ds)
            converted, _ = rig_in_model(load_rig(base / "rig.yaml"), model)
            save_rig(converted, ds / "rig.yaml")
            assert load_rig(ds / "rig.yaml").camera_model == model
        out = tmp_path / f"out-{model}"
        assert main(["reconstruct", str(ds), "--out", str(out), "--quiet"]) == 0
        diam[model] = json.loads((out / "report.json").read_text())["inner_diameter_mm"]
    truth = json.loads((base / "ground_truth" / "scene.json").read_text())["inner_diameter_mm"]
    assert abs(diam["hyperboloid"] - truth) < 1.5  # the small-image band of test_reconstruct
    for model in ("unified", "ocam"):
        assert abs(diam[model] - diam["hyperboloid"]) < 0.3, diam


def test_baseline_needs_the_hyperboloid_mirror(tmp_path: Path, capsys) -> None:
    """A unified-model rig has no mirror a, b: the baseline command says so in one line."""
    from dataclasses import replace

    from omnipipe.cli import main

    save_rig(replace(_unified_rig(), mirror=None), tmp_path / "rig.yaml")
    assert main(["baseline", "--rig", str(tmp_path / "rig.yaml"), "--distance", "100"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "mirror" in err[0]


@pytest.mark.parametrize("make", [lambda: paper_rig(400, 300), _unified_rig, _ocam_rig])
def test_analytic_jacobian_matches_the_central_differences(make) -> None:
    """Each model's ``project_jacobian`` against the interface's generic central
    differences (:meth:`CameraModel.project_jacobian`, error ~1e-10 relative)."""
    cam = camera_from_rig(make())
    assert type(cam).project_jacobian is not CameraModel.project_jacobian  # analytic
    px = np.argwhere(cam.valid_mask())[:, ::-1].astype(float)[::11]  # (col, row)
    depth = np.random.default_rng(3).uniform(20.0, 2000.0, size=(len(px), 1))
    q = cam.unproject(px) * depth
    J = cam.project_jacobian(q)
    fd = CameraModel.project_jacobian(cam, q)
    assert J.shape == fd.shape == (len(q), 2, 3)
    scale = np.abs(fd).max(axis=(1, 2))[:, None, None]
    assert np.isfinite(J).all()
    assert (np.abs(J - fd) / scale).max() < 1e-7
    # Only the direction matters: no derivative along the point's own ray.
    assert np.abs(np.einsum("nij,nj->ni", J, q)).max() < 1e-6 * np.abs(J).max()


def test_camera_model_is_abstract_and_pixel_angle_is_the_ray_angle() -> None:
    with pytest.raises(TypeError):
        CameraModel()  # type: ignore[abstract]
    cam = camera_from_rig(paper_rig(400, 300))
    px = np.array([[cam.cx + 60.0, cam.cy + 5.0], [cam.cx - 30.0, cam.cy + 40.0]])
    for step in ((0.0, 1.0), (1.0, 0.0)):
        r0, r1 = cam.unproject(px), cam.unproject(px + np.array(step))
        want = np.arctan2(np.linalg.norm(np.cross(r0, r1), axis=1), np.sum(r0 * r1, axis=1))
        np.testing.assert_allclose(cam.pixel_angle(px, step), want, rtol=1e-6)
    mid = cam.cx + 0.5 * (cam.radius_min + cam.radius_max)
    assert cam.angular_resolution() == cam.pixel_angle(np.array([[mid, cam.cy]]))[0]
    assert 1e-3 < cam.angular_resolution() < 0.1  # rad/px of a 400x300 omni image


@pytest.mark.parametrize("make", [_unified_rig, _ocam_rig])
def test_models_without_a_compiled_projection_say_so(make) -> None:
    assert camera_from_rig(make()).compiled_projection() is None
    proj = camera_from_rig(paper_rig(400, 300)).compiled_projection()
    assert proj is not None and all(isinstance(v, float) for v in proj.params)
