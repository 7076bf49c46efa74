"""The tight elbow's acceptance (issue 30): camera motion through it and the bend reported.

    python benchmarks/bench_elbow.py [--dataset DIR | --size WxH --keep DIR] [--out DIR]
        [--reuse] [--workers N]

Reconstructs the ``elbow`` scenario (200 mm pipe, a 90 deg elbow of radius 1.5 D, straight
again after it; ``omnipipe simulate --scenario elbow``), or a dataset rendered before
(``--dataset``, read only), with the defaults of ``omnipipe reconstruct``; evaluates it and
prints against the issue's acceptance:

* ATE (SE(3)-aligned) per 300 mm of travel <= 1 mm;
* the reported bend's radius within 3 % and its turn within 1 deg of the scene's (the turn
  the rings swept: a bend truncated by the run's ends is compared with the part of it
  inside the measured stations);
* the elbow reported as a feature and no bulge or dent inside it.

``--reuse`` takes the reconstruction already in ``--out`` (only evaluates and scores).
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from omnipipe.dataset import open_dataset
from omnipipe.evaluation import EvaluationConfig, EvaluationInputs
from omnipipe.evaluation import run as evaluate
from omnipipe.evaluation.trajectory import TrajectoryErrors
from omnipipe.pipeline import ReconstructConfig, run, write
from omnipipe.sim import make_scenario
from omnipipe.sim import run as simulate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", type=Path, help="an elbow dataset rendered before (read only)")
    ap.add_argument("--size", default=None, help="WxH of a new render (default: the scenario's)")
    ap.add_argument("--keep", type=Path, help="where a new render goes (default: a temporary folder)")
    ap.add_argument("--out", type=Path, help="reconstruction folder (default: beside the render)")
    ap.add_argument("--reuse", action="store_true", help="score the reconstruction already in --out")
    ap.add_argument("--workers", type=int, default=None)
    args = ap.parse_args()
    root = args.keep or Path(tempfile.mkdtemp(prefix="omnipipe-elbow-"))
    data = args.dataset
    if data is None:
        size = tuple(int(v) for v in args.size.split("x")) if args.size else None
        data = root / "dataset"
        if not (data / "ground_truth" / "scene.json").is_file():
            simulate(make_scenario("elbow", size=size), data, force=True, workers=2)
    out = args.out or root / "reconstruction"
    t0 = time.perf_counter()
    if not args.reuse:
        config = replace(ReconstructConfig.default(), workers=args.workers)
        write(run(config, open_dataset(data)), out, force=True)
    elapsed = time.perf_counter() - t0
    ev = evaluate(EvaluationConfig(), EvaluationInputs(out, data))
    report = json.loads((out / "report.json").read_text())
    scene = json.loads((data / "ground_truth" / "scene.json").read_text())
    print(f"elbow: {ev.frames_registered}/{ev.frames} frames, {data}" + ("" if args.reuse else f", {elapsed:.0f} s"))
    print(score(report, scene, ev.trajectory))


def score(report: dict, scene: dict, traj: TrajectoryErrors | None) -> str:
    """The acceptance lines of one run (``report.json``, ``scene.json``)."""
    lines = []
    ok = True
    if traj is not None:
        per300 = traj.ate_rmse_mm * 300.0 / max(traj.path_length_mm, 1.0)
        ok &= per300 <= 1.0
        lines.append(
            f"ATE {traj.ate_rmse_mm:.3f} mm (max {traj.ate_max_mm:.3f}) over {traj.path_length_mm:.0f} mm: "
            f"{per300:.3f} mm per 300 mm (<= 1); scale {100 * traj.scale_error:.2f} %, "
            f"rotation {traj.rotation_rmse_deg:.3f} deg"
        )
    truth = next(f for f in scene["features"] if f["kind"] == "bend")
    stations = [s["axial_mm"] for s in report.get("stations", [])]
    lo, hi = (min(stations), max(stations)) if stations else (math.nan, math.nan)
    # The part of the true bend the stations swept (its turn per mm is constant).
    a, b = max(truth["axial_from_mm"], lo), min(truth["axial_to_mm"], hi)
    swept = max(b - a, 0.0) / truth["radius_mm"]
    lines.append(
        f"truth: bend {truth['axial_from_mm']:.1f}..{truth['axial_to_mm']:.1f} mm, R {truth['radius_mm']:.1f} mm, "
        f"turn {truth['turn_deg']:.2f} deg; stations {lo:.1f}..{hi:.1f} mm sweep {math.degrees(swept):.2f} deg of it"
    )
    bends = [f for f in report.get("features", []) if f["kind"] == "bend"]
    if not bends:
        ok = False
        lines.append("no bend reported")
    for f in bends:
        r_err = 100.0 * (f["radius_mm"] / truth["radius_mm"] - 1.0)
        t_err = f["turn_deg"] - math.degrees(swept)
        ok &= abs(r_err) <= 3.0 and abs(t_err) <= 1.0
        lines.append(
            f"bend {f['axial_from_mm']:.1f}..{f['axial_to_mm']:.1f} mm: R {f['radius_mm']:.1f} +- "
            f"{f.get('radius_sigma_mm') or math.nan:.1f} mm ({r_err:+.2f} %, <= 3), turn {f['turn_deg']:.2f} +- "
            f"{f.get('turn_sigma_deg') or math.nan:.2f} deg ({t_err:+.2f} deg, <= 1)"
            + (", truncated" if f.get("truncated") else "")
        )
    ok &= len(bends) == 1
    inside = [
        d for d in report.get("defects", [])
        if truth["axial_from_mm"] - 50 <= d["axial_start_mm"] <= truth["axial_to_mm"] + 50
    ]
    ok &= not inside
    lines.append(
        f"defects: {len(report.get('defects', []))} reported, {len(inside)} in the elbow (0 expected); "
        f"features: {', '.join(f['kind'] for f in report.get('features', []))}"
    )
    lines.append("acceptance: " + ("met" if ok else "NOT met"))
    return "\n".join(lines)


if __name__ == "__main__":
    main()
