"""omnipipe batch: two tiny simulated runs and a broken one, on local processes and on a
Dask LocalCluster: same report.json values, the failure listed, exit code 1."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from omnipipe.cli import main
from omnipipe.output import MANIFEST_NAME
from omnipipe.pipeline.batch import run_names

# Wall-clock values and how they were obtained: the only keys allowed to differ.
_VOLATILE = ("timings_s", "frames_per_s", "executor")


@pytest.fixture(scope="module")
def runs(two_tiny_runs: list[Path], tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Copies of the two tiny runs, the first with a survey header, and a broken one."""
    root = tmp_path_factory.mktemp("batch")
    out = [root / r.name for r in two_tiny_runs]
    for src, dst in zip(two_tiny_runs, out, strict=True):
        shutil.copytree(src, dst)
    (out[0] / "survey.yaml").write_text("site: Main St\nasset_id: SW-7\nstart_node: MH-1\n", encoding="utf-8")
    broken = root / "broken"
    shutil.copytree(out[0], broken)
    (broken / "rig.yaml").unlink()
    return [out[0], broken, out[1]]


@pytest.fixture(scope="module")
def local_batch(runs: list[Path], tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int]:
    out = tmp_path_factory.mktemp("local") / "batch"
    code = main(["batch", *map(str, runs), "--out", str(out), "--workers", "2", "--quiet"])
    return out, code


def _reports(out: Path) -> dict[str, dict]:
    reports = {}
    for row in json.loads((out / "index.json").read_text())["runs"]:
        if row["status"] == "ok":
            report = json.loads((out / row["name"] / "report.json").read_text())
            reports[row["name"]] = {k: v for k, v in report.items() if k not in _VOLATILE}
    return reports


def test_every_run_listed_and_the_failure_does_not_stop_the_others(
    local_batch: tuple[Path, int], runs: list[Path]
) -> None:
    out, code = local_batch
    assert code == 1  # one run failed
    rows = json.loads((out / "index.json").read_text())["runs"]
    assert [r["name"] for r in rows] == ["pipe-3", "broken", "pipe-4"]
    assert [r["status"] for r in rows] == ["ok", "failed", "ok"]
    assert "rig.yaml" in rows[1]["error"] and "\n" not in rows[1]["error"]
    assert not (out / "broken").exists()
    for row, path in zip(rows, runs, strict=True):
        if row["status"] != "ok":
            continue
        truth = json.loads((path / "ground_truth" / "scene.json").read_text())
        report = json.loads((out / row["name"] / "report.json").read_text())
        # 320x240, 6 frames: the diameter within 1.5 mm (as tests/pipeline/test_reconstruct.py).
        assert abs(row["inner_diameter_mm"] - truth["inner_diameter_mm"]) < 1.5
        assert row["inner_diameter_mm"] == report["inner_diameter_mm"]
        assert row["defects"] == len(report["defects"]) and row["warnings"] == len(report["warnings"])
        # Every stage's frames/s; startup (input checks, the pool's tables) is no stage.
        # Both are rounded to 3 decimals: a slow run's 0.019 frames/s is 0.0187 +- 0.0005.
        assert set(report["frames_per_s"]) == set(report["timings_s"]) - {"startup"}
        assert report["frames_per_s"]["total"] == pytest.approx(
            report["frames"] / report["timings_s"]["total"], rel=0.01, abs=1e-3
        )
        for name in ("report.html", "mesh.ply", "trajectory.txt", MANIFEST_NAME):
            assert (out / row["name"] / name).is_file(), name
        # The batch's executor (2 local processes), not the worker's inline one.
        assert report["executor"]["kind"] == "processes" and report["executor"]["workers"] == 2
    page = (out / "index.html").read_text()
    assert 'href="pipe-3/report.html"' in page and "FAILED" in page and "rig.yaml" in page
    # The survey header of the run that has one, and every run's executor.
    assert "Main St" in page and "asset SW-7" in page and "from MH-1" in page
    assert page.count("processes x 2") == 2
    assert (out / MANIFEST_NAME).is_file()


@pytest.mark.slow  # 5 s: a local Dask cluster; the batch itself stays covered by the tests above
def test_dask_cluster_gives_the_same_reports(
    local_batch: tuple[Path, int], runs: list[Path], tmp_path: Path
) -> None:
    distributed = pytest.importorskip("distributed")
    cluster = distributed.LocalCluster(
        host="127.0.0.1", processes=True, n_workers=1, threads_per_worker=2, dashboard_address=None
    )
    try:
        out = tmp_path / "dask"
        code = main(
            ["batch", *map(str, runs), "--out", str(out), "--scheduler", cluster.scheduler_address, "--quiet"]
        )
    finally:
        cluster.close()
    assert code == 1
    local = _reports(local_batch[0])
    assert sorted(local) == ["pipe-3", "pipe-4"]
    assert _reports(out) == local
    for name in local:
        assert json.loads((out / name / "report.json").read_text())["executor"]["kind"] == "dask"
    for name in local:  # the trajectory is the same to the last digit written
        assert (out / name / "trajectory.txt").read_text() == (
            local_batch[0] / name / "trajectory.txt"
        ).read_text()


def test_force_replaces_only_a_batch_output(local_batch: tuple[Path, int], runs: list[Path], capsys) -> None:
    out, _ = local_batch
    args = ["batch", str(runs[1]), "--out", str(out), "--workers", "1", "--quiet"]
    assert main(args) == 1
    assert "already exists" in capsys.readouterr().err
    (out / "notes.txt").write_text("mine")
    assert main([*args, "--force"]) == 1
    assert "notes.txt" in capsys.readouterr().err
    assert (out / "pipe-3" / "report.json").is_file()  # untouched


def test_run_names_are_distinct_and_safe(tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    video = tmp_path / "b c.mp4"
    video.write_bytes(b"")
    (tmp_path / "index.json").mkdir()  # would collide with the batch's own index.json
    names = run_names([tmp_path / "a", tmp_path / "a", video, tmp_path / "index.json"])
    assert names == ["a", "a-2", "b_c", "index.json-2"]
