"""Detection rate of bulges and dents by height and width, and false detections per metre.

    python benchmarks/bench_detection.py [--cache DIR] [--seeds N] [--trials T] [--length MM]

Walls: the measured deviation maps of simulated runs (rendered, reconstructed: real
light-section noise, ring spacing and gaps; ``bench_metrology.py``'s random straight
pipes, cached in ``--cache``, rendered there when missing). Into each map a defect of
the simulator's shape (raised-cosine plateau, flanks a third of its extent) of every
height x width of the sweep is added at a random place away from the run's own
defects, and the detector of ``omnipipe reconstruct`` (``find_defects`` with the
default analysis settings) runs on it. A defect counts as detected when a reported
defect of its kind lies within 25 mm and 10 deg of it. Any other reported defect
that is none of the run's true ones is a false detection. Printed: detection rate
per (height, width), false detections per metre of measured pipe, and each run's
stated detection limit (for the reference defect of ``analysis.limit_*``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

HEIGHTS = (0.2, 0.5, 0.8, 1.0, 1.5, 2.0, 3.0, 5.0)
WIDTHS = (3.0, 5.0, 10.0, 20.0, 40.0)


def _walls(cache: Path, seeds: int, size: tuple[int, int], frames: int) -> list[tuple[dict, dict]]:
    """(wall, scene) per run: wall = unrolled coordinates and deviations of every point."""
    import bench_metrology as bm

    from omnipipe import analysis

    out = []
    for seed in range(seeds):
        root = cache / f"seed{seed}"
        if not (root / "analysis_inputs.npz").is_file():
            bm._reconstruct(bm.random_scenario(seed, size, frames, 4), root, False)
        z = np.load(root / "analysis_inputs.npz")
        inputs = analysis.AnalysisInputs(z["points"], z["frame"], z["poses"], z["reference_from_world"])
        res = analysis.run(analysis.AnalysisConfig(), inputs)
        scene = json.loads((root / "dataset" / "ground_truth" / "scene.json").read_text())
        ok = res.point_deviation_mm != 0.0
        wall = {
            "sigma": res.point_sigma_mm[ok],
            "arc": (res.point_theta_rad[ok] % (2 * np.pi)) * res.radius_mm,
            "dev": res.point_deviation_mm[ok],
            "ring": np.asarray(z["frame"])[ok],
            "circ": 2 * np.pi * res.radius_mm,
            "limit": res.detection_limit_mm,
            "length": float(np.ptp(res.stations_axial_mm)),
            "z_range": (float(np.min(res.stations_axial_mm)), float(np.max(res.stations_axial_mm))),
        }
        out.append((wall, scene))
    return out


def _near(a: dict, b: dict, ax_mm: float, ang_deg: float) -> bool:
    ca = a["axial_start_mm"] + 0.5 * a["length_mm"]
    cb = b["axial_start_mm"] + 0.5 * b["length_mm"]
    d_ang = abs((a["angle_deg"] - b["angle_deg"] + 180) % 360 - 180)
    return a["kind"] == b["kind"] and abs(ca - cb) <= ax_mm and d_ang <= ang_deg


def main() -> None:
    from omnipipe.analysis import AnalysisConfig
    from omnipipe.analysis.defects import find_defects
    from omnipipe.analysis.sizing import plateau
    from omnipipe.analysis.wall_profile import WallSamples

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", default=None, help="bench_metrology --cache directory")
    parser.add_argument("--seeds", type=int, default=3, help="runs (walls) to use")
    parser.add_argument("--trials", type=int, default=4, help="placements per height x width and wall")
    parser.add_argument("--length", type=float, default=30.0, help="defect length at half height (mm)")
    parser.add_argument("--size", default="800x600", help="image size of runs rendered here")
    parser.add_argument("--frames", type=int, default=60)
    args = parser.parse_args()
    cache = Path(args.cache) if args.cache else Path(tempfile.mkdtemp(prefix="omnipipe-detect-"))
    size = tuple(int(v) for v in args.size.lower().split("x"))
    cfg = AnalysisConfig()
    walls = _walls(cache, args.seeds, size, args.frames)
    rng = np.random.default_rng(0)
    rate = np.zeros((len(HEIGHTS), len(WIDTHS)))
    false_count, metres = 0, 0.0
    for wall, scene in walls:
        circ = wall["circ"]
        truth = scene["defects"]
        for i, h in enumerate(HEIGHTS):
            for j, w in enumerate(WIDTHS):
                for _ in range(args.trials):
                    # A place at least 30 deg and its own size away from the run's defects.
                    for _attempt in range(100):
                        angle = float(rng.uniform(0, 360))
                        z0, z1 = wall["z_range"]
                        start = float(rng.uniform(z0 + 10, max(z0 + 10, z1 - 10 - args.length)))
                        cand = {"kind": "dent", "axial_start_mm": start, "length_mm": args.length, "angle_deg": angle}
                        clear = all(
                            abs((angle - t["angle_deg"] + 180) % 360 - 180)
                            > 30 + math.degrees((w + t["width_mm"]) / circ * math.pi)
                            for t in truth
                        )
                        if clear:
                            break
                    kind = "dent" if rng.random() < 0.5 else "bulge"
                    cand["kind"] = kind
                    uc = angle / 360 * circ
                    u = (wall["arc"] - uc + 0.5 * circ) % circ - 0.5 * circ
                    zc = start + 0.5 * args.length
                    sign = 1.0 if kind == "dent" else -1.0
                    dev = wall["dev"] + sign * h * plateau(u, w, w / 3) * plateau(
                        wall["sigma"] - zc, args.length, args.length / 3
                    )
                    search = find_defects(
                        WallSamples(wall["sigma"], wall["arc"], dev, wall["ring"], circ),
                        min_height_mm=cfg.min_height_mm,
                        noise_factor=cfg.noise_factor,
                        min_points=cfg.min_points,
                        grid_mm=cfg.grid_mm,
                        limit_width_mm=cfg.limit_width_mm,
                        limit_length_mm=cfg.limit_length_mm,
                    )
                    found = [d.to_contract() for d in search.defects]
                    hit = any(_near(d, cand, 25.0, 10.0) for d in found)
                    rate[i, j] += hit
                    false_count += sum(
                        1
                        for d in found
                        if not _near(d, cand, 25.0, 10.0)
                        and not any(_near(d, t, 60.0, 25.0) for t in truth)
                    )
                    metres += wall["length"] / 1000.0
    n = len(walls) * args.trials
    rate /= n
    print(
        f"{len(walls)} walls (800x600 renders, {args.frames} frames), {args.trials} placements each; "
        f"defect length {args.length:g} mm; {n} trials per cell"
    )
    print("detection rate by height (rows, mm) and width (columns, mm):")
    print("height " + "".join(f"{w:>7g}" for w in WIDTHS))
    for i, h in enumerate(HEIGHTS):
        print(f"{h:6.1f} " + "".join(f"{100 * rate[i, j]:6.0f}%" for j in range(len(WIDTHS))))
    print(f"false detections: {false_count} in {metres:.2f} m of pipe = {false_count / max(metres, 1e-9):.2f} per m")
    limits = [wall["limit"] for wall, _ in walls]
    print(
        "stated detection limit (reference defect "
        f"{cfg.limit_width_mm:g} x {cfg.limit_length_mm:g} mm): "
        + ", ".join(f"{v:.2f}" for v in limits)
        + " mm"
    )


if __name__ == "__main__":
    main()
