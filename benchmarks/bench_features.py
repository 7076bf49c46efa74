"""Joints and laterals on random-features seeds: recall, false defects, position errors
and size coverage (|error| <= 3 sigma) against scene.json's ground truth.

    PYTHONPATH=src nice python benchmarks/bench_features.py --seeds 0-29 --work /tmp/bf

Each seed: ``omnipipe simulate --scenario random-features-small`` then ``omnipipe
reconstruct``; seeds already reconstructed in --work are reused. Counted: joints with
offset >= 1 mm or gap >= 3 mm, laterals >= 0.2 x the diameter; a match lies within
max(15 mm, 0.6 x the lateral's diameter) axially. A defect within 10 mm of a joint or
inside a hole counts as a feature reported as a defect.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path


def _seeds(text: str) -> list[int]:
    a, _, b = text.partition("-")
    return list(range(int(a), int(b or a) + 1))


def _run(seed: int, work: Path) -> tuple[dict, dict] | None:
    data, out = work / f"s{seed}", work / f"s{seed}-out"
    if not (out / "report.json").exists():
        for cmd in (
            ["omnipipe", "simulate", "--scenario", "random-features-small", "--seed", str(seed),
             "--out", str(data), "--quiet", "--workers", "1", "--force"],
            ["omnipipe", "reconstruct", str(data), "--out", str(out), "--force"],
        ):
            if subprocess.run(cmd, capture_output=True).returncode != 0:
                return None
    truth = json.loads((data / "ground_truth" / "scene.json").read_text())
    return json.loads((out / "report.json").read_text()), truth


def _score(report: dict, truth: dict, rows: dict) -> None:
    d = truth.get("pipe", {}).get("inner_diameter_mm") or report.get("inner_diameter_mm", 200.0)
    found = report.get("features") or []
    for t in truth.get("features", []):
        kind = t["kind"]
        if kind == "joint" and not (t.get("offset_mm", 0) >= 1 or t.get("gap_mm", 0) >= 3):
            continue
        if kind == "lateral" and t["diameter_mm"] < 0.2 * d:
            continue
        if kind not in ("joint", "lateral"):
            continue
        r = rows.setdefault(kind, {"n": 0, "found": 0, "ax": [], "ang": [], "size_in": 0, "size_n": 0})
        r["n"] += 1
        tol = 15.0 if kind == "joint" else max(15.0, 0.6 * t["diameter_mm"])
        cand = [f for f in found if f["kind"] == kind and abs(f["axial_mm"] - t["axial_mm"]) <= tol]
        if not cand:
            continue
        f = min(cand, key=lambda f: abs(f["axial_mm"] - t["axial_mm"]))
        r["found"] += 1
        r["ax"].append(abs(f["axial_mm"] - t["axial_mm"]))
        size = "gap_mm" if kind == "joint" else "diameter_mm"
        if kind == "lateral":
            r["ang"].append(abs((f["angle_deg"] - t["angle_deg"] + 180) % 360 - 180))
        sig = f.get(size.replace("_mm", "_sigma_mm"))
        if sig:
            r["size_n"] += 1
            r["size_in"] += abs(f[size] - t[size]) <= 3 * sig
    bad = 0
    for dfx in report.get("defects", []):
        a = dfx["axial_start_mm"] + 0.5 * dfx["length_mm"]
        for t in truth.get("features", []):
            if t["kind"] == "joint" and abs(a - t["axial_mm"]) < 10 + 0.5 * t["gap_mm"]:
                bad += 1
            elif t["kind"] == "lateral" and abs(a - t["axial_mm"]) < 0.6 * t["diameter_mm"]:
                bad += 1
    rows.setdefault("false", {"defects": 0})["defects"] += bad


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", default="0-29")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_features"))
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    rows: dict = {}
    done = []
    for seed in _seeds(args.seeds):
        got = _run(seed, args.work)
        if got is None:
            print(f"seed {seed}: failed", flush=True)
            continue
        done.append(seed)
        _score(*got, rows)
        print(f"seed {seed}: done ({len(done)} seeds)", flush=True)
    print(f"\n{len(done)} seeds: {done}")
    print(f"{'kind':8} {'n':>4} {'recall':>7} {'ax<=3mm':>8} {'ang<=3deg':>9} {'size in 3sig':>12}")
    for kind in ("joint", "lateral"):
        r = rows.get(kind)
        if not r:
            continue
        n = r["found"] or 1
        ax = sum(e <= 3 for e in r["ax"]) / n
        ang = sum(e <= 3 for e in r["ang"]) / len(r["ang"]) if r["ang"] else float("nan")
        size = r["size_in"] / r["size_n"] if r["size_n"] else float("nan")
        print(f"{kind:8} {r['n']:>4} {r['found'] / max(r['n'], 1):>7.2f} {ax:>8.2f} {ang:>9.2f} {size:>12.2f}")
    print(f"defects within a joint's or a hole's reach: {rows.get('false', {}).get('defects', 0)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
