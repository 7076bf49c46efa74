"""Calibration of report.json's uncertainties: bias, RMS error and +-2 sigma coverage.

    python benchmarks/bench_metrology.py --seeds 10 [--first-seed 0] [--size 800x600]
        [--frames 60] [--defects 4] [--cache DIR] [--reuse]

Each seed simulates a straight pipe (random inner diameter 160-230 mm, random gait
disturbances and texture) with ``--defects`` random bulges and dents (height 1-10 mm,
width 4-40 mm, length 10-80 mm, spread around the pipe), runs ``omnipipe reconstruct``
(defaults) and pairs the reported defects with the true ones (the evaluation's
pairing rule, done here). It prints, per quantity, the mean error (bias), the RMS
error and the fraction of cases whose truth lies within +-2 of the reported sigmas
(ideal: 95 %), plus how many true defects were missed and how many were false.

``--cache DIR`` keeps the datasets and the analysis stage's inputs of each run;
``--reuse`` then re-runs only the analysis on them (seconds, for tuning the estimator;
the truth comes from the cached scene, so runs simulated with another ``--defects``
mix in). Nothing here is tuned per run: the defaults of ``omnipipe reconstruct``.
Tune on one seed range and quote a disjoint one (``--first-seed``) never tuned on.
Station diameters are scored away from the true defects (a ring crossing a defect has
no single true diameter).
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

QUANTITIES = (
    ("inner diameter", "inner_diameter_mm", "inner_diameter_sigma_mm"),
    ("station diameter", "diameter_mm", "diameter_sigma_mm"),
    ("run length", "run_length_mm", "run_length_sigma_mm"),
    ("height", "height_mm", "height_sigma_mm"),
    ("width", "width_mm", "width_sigma_mm"),
    ("length", "length_mm", "length_sigma_mm"),
    ("axial start", "axial_start_mm", "axial_start_sigma_mm"),
    ("angle", "angle_deg", "angle_sigma_deg"),
)


def random_scenario(seed: int, size: tuple[int, int], frames: int, n_defects: int):
    """A straight pipe with random diameter and ``n_defects`` non-overlapping random defects."""
    from omnipipe.sim import make_scenario
    from omnipipe.sim.scene import Defect, Pipe

    rng = np.random.default_rng(1000 + seed)
    scenario = make_scenario("paper-small", frames=frames, size=size, seed=seed)
    # Free rhythm: 3 moving frames per 24 mm stroke (8 mm ring spacing), 2 at rest.
    motion = replace(scenario.motion, moving_frames=3, frames_per_cycle=5, stroke_mm=24.0)
    cycles = frames / motion.frames_per_cycle
    first_ring = motion.start_mm - abs(scenario.rig.laser.k[3])
    last_ring = first_ring + cycles * motion.stroke_mm - motion.stroke_mm
    diameter = float(rng.uniform(160.0, 230.0))
    defects = []
    base = rng.uniform(0, 360)
    for k in range(n_defects):
        h = float(rng.uniform(1.0, 10.0))
        w = float(rng.uniform(max(4.0, 1.5 * h), 40.0))
        length = float(rng.uniform(10.0, 80.0))
        lo, hi = first_ring + 15.0, last_ring - 15.0 - length
        start = float(rng.uniform(lo, max(lo, hi)))
        angle = (base + k * 360.0 / n_defects + rng.uniform(-10, 10)) % 360.0
        kind = "bulge" if rng.random() < 0.5 else "dent"
        defects.append(Defect(kind, h, w, length, start, angle))
    scenario.pipe = Pipe(inner_diameter_mm=diameter, defects=defects)
    scenario.motion = motion
    scenario.name = f"metrology-{seed}"
    return scenario


def _pair(true: list[dict], measured: list[dict]) -> list[tuple[dict, dict | None]]:
    """Pair true and measured defects: same kind, centres within 60 mm and 25 deg."""
    used: set[int] = set()
    out = []
    for t in true:
        tc = t["axial_start_mm"] + 0.5 * t["length_mm"]
        best, cost = None, math.inf
        for j, m in enumerate(measured):
            if j in used or m["kind"] != t["kind"]:
                continue
            d_ax = abs(m["axial_start_mm"] + 0.5 * m["length_mm"] - tc)
            d_an = abs((m["angle_deg"] - t["angle_deg"] + 180) % 360 - 180)
            if d_ax <= 60 and d_an <= 25 and d_ax / 60 + d_an / 25 < cost:
                best, cost = j, d_ax / 60 + d_an / 25
        if best is not None:
            used.add(best)
        out.append((t, None if best is None else measured[best]))
    out += [(None, m) for j, m in enumerate(measured) if j not in used]
    return out


def _near_defect(axial_mm: float, defects: list[dict], margin_mm: float = 2.0) -> bool:
    """Whether a ring at ``axial_mm`` crosses a true defect (its flanks included: the
    simulator's axial ramp is min(length, 2 width) long, centred on each half-height end)."""
    for d in defects:
        ramp = min(d["length_mm"], 2.0 * d["width_mm"])
        half = 0.5 * d["length_mm"] + 0.5 * ramp + margin_mm
        if abs(axial_mm - (d["axial_start_mm"] + 0.5 * d["length_mm"])) <= half:
            return True
    return False


def _blurs(data: Path) -> tuple[float, float]:
    """The light section's blur along the ring and along the axis (mm) from a few frames
    (caches older than them)."""
    from omnipipe import laser
    from omnipipe.camera import camera_from_rig
    from omnipipe.dataset import open_dataset
    from omnipipe.laser.extract import axial_blur_mm, ring_blur_mm
    from omnipipe.pipeline import ReconstructConfig

    ds = open_dataset(data)
    frames = range(0, len(ds), max(1, len(ds) // 5))
    rings = laser.run(ReconstructConfig.default().laser, ds.rig, (ds.read_frame(i) for i in frames))
    return ring_blur_mm(rings.rings), axial_blur_mm(rings.rings, camera_from_rig(ds.rig))


def _reconstruct(scenario, root: Path, reuse: bool) -> tuple[dict, dict]:
    """Simulate (unless cached) and reconstruct; returns (summary, scene)."""
    from omnipipe import analysis
    from omnipipe.dataset import open_dataset
    from omnipipe.pipeline import ReconstructConfig
    from omnipipe.pipeline import run as reconstruct
    from omnipipe.sim import run as simulate

    data = root / "dataset"
    cache = root / "analysis_inputs.npz"
    scene = json.loads((data / "ground_truth" / "scene.json").read_text()) if reuse else None
    if reuse and cache.is_file():
        z = np.load(cache)
        if "axial_blur_mm" in z:
            blur, axial = float(z["ring_blur_mm"]), float(z["axial_blur_mm"])
        else:
            blur, axial = _blurs(data)
        inputs = analysis.AnalysisInputs(
            z["points"], z["frame"], z["poses"], z["reference_from_world"], ring_blur_mm=blur,
            axial_blur_mm=axial,
        )
        res = analysis.run(analysis.AnalysisConfig(), inputs)
        fields, _ = analysis.report_fields(res, float(z["scale_sigma_rel"]))
        return fields, scene
    simulate(scenario, data, force=True, workers=2)
    scene = json.loads((data / "ground_truth" / "scene.json").read_text())
    captured: dict = {}
    original = analysis.run

    def capture(config, inputs, executor=None):
        captured["inputs"] = inputs
        return original(config, inputs, executor)

    analysis.run = capture
    try:
        rec = reconstruct(ReconstructConfig.default(), open_dataset(data))
    finally:
        analysis.run = original
    inp = captured["inputs"]
    np.savez_compressed(
        cache,
        points=inp.points_in_world,
        frame=inp.frame_index,
        poses=inp.world_from_rig,
        reference_from_world=inp.reference_from_world,
        ring_blur_mm=inp.ring_blur_mm,
        axial_blur_mm=inp.axial_blur_mm,
        scale_sigma_rel=rec.summary.get("scale_sigma_rel", math.nan),
    )
    return rec.summary, scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10, help="number of simulated runs")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--size", default="800x600", help="image size WxH")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--defects", type=int, default=4, help="random defects per run")
    parser.add_argument("--cache", default=None, help="keep datasets and analysis inputs here")
    parser.add_argument("--reuse", action="store_true", help="re-run only the analysis on --cache")
    parser.add_argument("--verbose", action="store_true", help="print every defect's errors")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.lower().split("x"))
    base = Path(args.cache) if args.cache else Path(tempfile.mkdtemp(prefix="omnipipe-metro-"))
    errors: dict[str, list[tuple[float, float]]] = {q[0]: [] for q in QUANTITIES}
    missed, false, found = [], [], 0
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        scenario = random_scenario(seed, size, args.frames, args.defects)
        root = base / f"seed{seed}"
        if args.reuse and not (root / "analysis_inputs.npz").is_file():
            print(f"seed {seed}: not in the cache, skipped")
            continue
        summary, scene = _reconstruct(scenario, root, args.reuse)
        d_true = scene["inner_diameter_mm"]
        errors["inner diameter"].append(
            (summary["inner_diameter_mm"] - d_true, summary["inner_diameter_sigma_mm"])
        )
        for st in summary["stations"]:
            # Stations away from the defects measure the round pipe (a ring crossing a
            # defect has no single true diameter): outside every defect's flanks.
            if st.get("inner_diameter_sigma_mm") is not None and not _near_defect(st["axial_mm"], scene["defects"]):
                errors["station diameter"].append((st["inner_diameter_mm"] - d_true, st["inner_diameter_sigma_mm"]))
        for t, m in _pair(scene["defects"], summary["defects"]):
            if m is None:
                missed.append(t)
                continue
            if t is None:
                false.append(m)
                continue
            found += 1
            if args.verbose:
                print(
                    "  " + t["kind"][:5] + " " + " ".join(
                        f"{key[:-3]} {t[key]:.2f}{m[key] - t[key]:+.2f}/{m.get(skey) or math.nan:.2f}"
                        for _, key, skey in QUANTITIES[3:]
                    )
                )
            for name, key, skey in QUANTITIES[3:]:
                err = m[key] - t[key]
                if key == "angle_deg":
                    err = (err + 180) % 360 - 180
                errors[name].append((err, m.get(skey, math.nan)))
        print(
            f"seed {seed}: D {summary['inner_diameter_mm']:.3f} +- {summary['inner_diameter_sigma_mm']:.3f} "
            f"(true {d_true:.3f}), {len(summary['defects'])} defects reported of {len(scene['defects'])}, "
            f"limit {summary.get('detection_limit_mm')} mm",
            flush=True,
        )
    n_true = found + len(missed)
    print(f"\n{len(errors['inner diameter'])} runs at {args.size}, {args.frames} frames, {n_true} true defects")
    print(f"{'quantity':18s} {'n':>5s} {'bias':>9s} {'RMS':>9s} {'med sigma':>10s} {'cover 2s':>9s}")
    for name, key, _ in QUANTITIES:
        e = np.array(errors[name], float).reshape(-1, 2)
        if not len(e):
            continue
        unit = "deg" if key.endswith("deg") else "mm"
        ok = np.isfinite(e[:, 1])
        cover = np.mean(np.abs(e[ok, 0]) <= 2 * e[ok, 1]) if ok.any() else math.nan
        print(
            f"{name:18s} {len(e):5d} {np.mean(e[:, 0]):+9.3f} {np.sqrt(np.mean(e[:, 0] ** 2)):9.3f} "
            f"{np.median(e[ok, 1]) if ok.any() else math.nan:10.3f} {100 * cover:8.1f}%  {unit}"
        )
    h = np.array(errors["height"], float).reshape(-1, 2)
    if len(h):
        se = np.std(h[:, 0]) / math.sqrt(len(h))
        print(f"height bias {np.mean(h[:, 0]):+.3f} +- {se:.3f} mm (1 sigma of the mean) over {len(h)} defects")
    print(f"defects found {found}, missed {len(missed)}, false {len(false)}")
    for t in missed:
        print(
            f"  missed {t['kind']} h {t['height_mm']:.2f} w {t['width_mm']:.1f} l {t['length_mm']:.1f} "
            f"at {t['axial_start_mm']:.0f} mm / {t['angle_deg']:.0f} deg"
        )
    for m in false:
        print(f"  false {m['kind']} h {m['height_mm']:.2f} at {m['axial_start_mm']:.0f} mm / {m['angle_deg']:.0f} deg")


if __name__ == "__main__":
    main()
