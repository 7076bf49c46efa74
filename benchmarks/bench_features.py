"""Features of real pipes on random-features seeds against scene.json's ground truth:
recall per kind (laterals under 0.2 x the diameter on a row of their own,
``lat<0.2D``: a few of the random family's), features reported as defects, position errors, size coverage
(|error| <= 3 sigma), ovality and water depth errors (issue 30's acceptance table).

    PYTHONPATH=src nice python benchmarks/bench_features.py --seeds 0-29 --work /tmp/bf

Each seed: ``omnipipe simulate --scenario random-features-small`` (400x300, 24 frames;
a seed with a lateral 48-188: the run lengthened until its ring sweeps the hole;
``--size WxH`` renders the same scenes at another size) then ``omnipipe reconstruct``;
datasets and reports already in --work are reused (``--fresh`` reconstructs again).
``--motion truth`` reconstructs with the simulator's trajectory
(``sfm.trajectory_from: ground_truth/poses.txt``: the feature detection alone, not the
camera motion), ``--motion both`` prints both tables; ``--list`` then lists each true
joint and lateral: found - true axial (mm), MISS, or why it is not counted.

Counted (the issue's classes): joints with offset >= 1 mm or gap >= 3 mm, laterals >=
0.2 x the diameter, bends of radius <= 3 x the diameter (the elbows), tapers, ovality >=
2 %, water >= 5 % of the diameter, and only where the run's laser ring measured them: a
point feature inside the stations' span (a lateral's whole hole), a stretch overlapping
it by at least 10 mm, a bend whose part inside the span turns at least 10 degrees
(``analysis.bend_min_turn_deg``: the 24-frame runs sweep 20-240 mm of pipe, a 10 mm
piece of an R = 3 D bend turns a degree); truth beyond is listed as "outside", not as
missed. A
point feature matches within max(15 mm, 0.6 x a lateral's diameter) axially, a stretch
by an overlap of at least half the shorter of the two (``STRETCH_MATCH_SHARE``); a
reported feature matching no true one of its kind is false. Sizes of a truncated stretch (it runs past the stations) are lower bounds:
not scored. Ovality and water depth are compared with the truth stations' median over
the reported stretch (depth varies along a taper; a stretch's median includes its
blends), and per station with the truth there (stations dry in both not counted).
A reported defect matching no true defect (axial overlap within 10 mm) is
false; one within 10 mm of a true feature is a feature reported as a defect.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

POINT_KINDS = ("joint", "lateral")
STRETCH_MATCH_SHARE = 0.5
"""Least overlap of a reported and a true stretch, as a share of the shorter one."""
BEND_MIN_TURN_DEG = 10.0  # analysis.bend_min_turn_deg's default
KINDS = ("joint", "lateral", "bend", "taper", "ovality", "water")
SMALL_LATERAL = "lat<0.2D"  # laterals under the class, tallied apart (not in its acceptance)
SIZES = {
    "joint": ("gap_mm", "offset_mm"),
    "lateral": ("diameter_mm",),
    "bend": ("radius_mm", "turn_deg"),
    "taper": ("diameter_from_mm", "diameter_to_mm"),
    "ovality": ("percent",),
    "water": ("depth_mm",),
}


@dataclass
class Row:
    """Tallies of one feature kind."""

    n: int = 0
    found: int = 0
    outside: int = 0
    ax: list[float] = field(default_factory=list)
    ang: list[float] = field(default_factory=list)
    size_in: int = 0
    size_n: int = 0
    err: list[float] = field(default_factory=list)


def _seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def _run(seed: int, work: Path, size: str | None, fresh: bool, motion: str) -> tuple[dict, dict] | str:
    data = work / f"s{seed}"
    out = work / (f"s{seed}-out" if motion == "estimated" else f"s{seed}-truth-out")
    sim = ["omnipipe", "simulate", "--scenario", "random-features-small", "--seed", str(seed),
           "--out", str(data), "--quiet", "--workers", "1", "--force"]
    if size:
        sim += ["--size", size]
    if not (data / "ground_truth" / "scene.json").exists():
        p = subprocess.run(sim, capture_output=True, text=True)
        if p.returncode != 0:
            return "simulate: " + (p.stderr.strip().splitlines() or ["?"])[-1]
    if fresh or not (out / "report.json").exists():
        cmd = ["omnipipe", "reconstruct", str(data), "--out", str(out), "--force", "--quiet"]
        if motion == "truth":
            cfg = work / "truth-motion.yaml"
            cfg.write_text("sfm:\n  trajectory_from: ground_truth/poses.txt\n")
            cmd += ["--config", str(cfg)]
        p = subprocess.run(cmd, capture_output=True, text=True)
        if p.returncode != 0:
            return "reconstruct: " + (p.stderr.strip().splitlines() or ["?"])[-1]
    truth = json.loads((data / "ground_truth" / "scene.json").read_text())
    return json.loads((out / "report.json").read_text()), truth


def _ring_spans(data: Path, truth: dict) -> list[tuple[float, float, float, float]] | None:
    """Each frame's true laser ring as an axial stretch (contract axial mm, from..to), its
    median axial position and the truth stations' mean diameter around it (mm):
    the rig.yaml laser plane at the true pose (ground_truth/poses.txt) cut with the true
    pipe (a cylinder of the truth stations' diameter about the centreline polyline,
    straight locally); None without the files. Every frame counts (one whose ring was
    lost still covers its stretch here: the unseen stretches are never overstated)."""
    import yaml  # the bench's only use; PyYAML comes with omnipipe's config loading

    poses_f, rig_f = data / "ground_truth" / "poses.txt", data / "rig.yaml"
    line = truth.get("centreline_polyline_mm")
    if not (poses_f.exists() and rig_f.exists() and line and truth.get("stations")):
        return None
    plane = np.array(yaml.safe_load(rig_f.read_text())["laser"]["plane"], float)
    n_rig = plane[:3] / np.linalg.norm(plane[:3])
    p_rig = -plane[3] / np.linalg.norm(plane[:3]) * n_rig
    pts, arc = np.array(line["points"], float), np.array(line["sigma"], float)
    base = float(truth.get("first_station_sigma_mm", 0.0))
    st_x = np.array([s["axial_mm"] for s in truth["stations"]])
    st_d = np.array([s["inner_diameter_mm"] for s in truth["stations"]])
    spans = []
    for row in np.loadtxt(poses_f, ndmin=2):
        x, y, z, w = row[4:8]
        rot = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ])
        n, p0 = rot @ n_rig, rot @ p_rig + row[1:4]
        j = int(np.clip(np.argmin(np.linalg.norm(pts - p0, axis=1)), 0, len(pts) - 2))
        tan = (pts[j + 1] - pts[j]) / np.linalg.norm(pts[j + 1] - pts[j])
        s0 = arc[j] + float((p0 - pts[j]) @ tan)
        c = pts[j] + (s0 - arc[j]) * tan  # the axis point abreast of the plane's centre
        e1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        rad = 0.5 * float(np.interp(s0 - base, st_x, st_d))
        phi = np.linspace(0.0, 2.0 * np.pi, 180, endpoint=False)
        u = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2
        # p0 + s u on the cylinder |(q - c) - ((q - c).tan) tan| = rad: a quadratic in s.
        q0 = (p0 - c) - float((p0 - c) @ tan) * tan
        uu = u - (u @ tan)[:, None] * tan
        a, b, cc = np.sum(uu * uu, axis=1), 2.0 * (uu @ q0), float(q0 @ q0) - rad**2
        s = (-b + np.sqrt(np.maximum(b * b - 4 * a * cc, 0.0))) / (2.0 * np.maximum(a, 1e-12))
        along = s0 + float((p0 - c) @ tan) + s * (u @ tan) - base
        d_ring = float(np.mean(np.interp(along, st_x, st_d)))
        spans.append((float(along.min()), float(along.max()), float(np.median(along)), d_ring))
    return spans


def _unseen(t: dict, spans: list[tuple[float, float, float, float]] | None) -> bool:
    """A joint counted for its gap alone (offset < 1 mm) whose gap no frame's ring
    crossed: nothing of it was measured (a joint with an offset shows it in the wall
    either side, and stays counted)."""
    if t["kind"] != "joint" or spans is None or t.get("offset_mm", 0.0) >= 1.0:
        return False
    a, b = _extent(t)
    return not any(lo <= b and hi >= a for lo, hi, *_ in spans)


def _eligible(t: dict, d: float) -> bool:
    kind = t["kind"]
    if kind == "joint":
        return t.get("offset_mm", 0) >= 1 or t.get("gap_mm", 0) >= 3
    if kind == "lateral":
        return t["diameter_mm"] >= 0.2 * d
    if kind == "bend":
        return t["radius_mm"] <= 3.0 * d
    if kind == "ovality":
        return t["percent"] >= 2.0
    if kind == "water":
        return t["depth_mm"] >= 0.05 * d
    return kind == "taper"


def _extent(t: dict) -> tuple[float, float]:
    if t["kind"] == "lateral":
        half = 0.5 * t["diameter_mm"] / np.sin(np.radians(t.get("branch_angle_deg", 90.0)))
        return t["axial_mm"] - half, t["axial_mm"] + half
    if t["kind"] == "joint":
        return t["axial_mm"] - 0.5 * t["gap_mm"], t["axial_mm"] + 0.5 * t["gap_mm"]
    return t["axial_from_mm"], t["axial_to_mm"]


def _match(t: dict, found: list[dict]) -> dict | None:
    cand = [f for f in found if f["kind"] == t["kind"]]
    if t["kind"] in POINT_KINDS:
        tol = 15.0 if t["kind"] == "joint" else max(15.0, 0.6 * t["diameter_mm"])
        cand = [f for f in cand if abs(f["axial_mm"] - t["axial_mm"]) <= tol]
        return min(cand, key=lambda f: abs(f["axial_mm"] - t["axial_mm"])) if cand else None
    a, b = _extent(t)

    def overlap(f: dict) -> float:
        return min(b, f["axial_to_mm"]) - max(a, f["axial_from_mm"])

    # At least half the shorter of the two: a reported stretch beside the true one,
    # touching it by a few mm, is a false stretch, not a detection.
    cand = [f for f in cand if overlap(f) >= STRETCH_MATCH_SHARE * min(b - a, f["axial_to_mm"] - f["axial_from_mm"])
            and overlap(f) > 0]
    return max(cand, key=overlap) if cand else None


def _truth_over(truth: dict, key: str, a: float, b: float) -> float | None:
    """Median of the truth stations' ``key`` over [a, b] (interpolated at both ends):
    the true value of what a stretch reports (water depth varies along a taper or a
    slope; an ovality stretch's median includes its blends)."""
    st = truth.get("stations") or []
    if not st:
        return None
    x = np.array([s["axial_mm"] for s in st])
    y = np.array([s[key] for s in st])
    grid = np.linspace(a, b, 21)
    return float(np.median(np.interp(grid, x, y)))


def _sizes(t: dict, f: dict, r: Row, d: float, truth: dict) -> None:
    if t["kind"] in ("ovality", "water"):
        key, skey, tkey = (("percent", "percent_sigma", "ovality_pct") if t["kind"] == "ovality"
                           else ("depth_mm", "depth_sigma_mm", "water_depth_mm"))
        true = _truth_over(truth, tkey, f["axial_from_mm"], f["axial_to_mm"])
        true = t[key] if true is None else true
        r.err.append(abs(f[key] - true))
        r.size_n += 1
        r.size_in += bool(f.get(skey)) and abs(f[key] - true) <= 3.0 * f[skey]
        return
    for key in SIZES[t["kind"]]:
        if f.get("truncated") and t["kind"] in ("bend",) and key == "turn_deg":
            continue
        if f.get("truncated") and t["kind"] == "taper":
            continue
        if key == "offset_mm" and t.get("offset_mm", 0.0) == 0.0 and f.get(key) is None:
            continue
        sig = f.get(key.replace("_mm", "_sigma_mm").replace("_deg", "_sigma_deg")
                    if key != "percent" else "percent_sigma")
        if f.get(key) is None or not sig:
            r.size_n += 1  # a size without its sigma counts as not covered
            continue
        r.size_n += 1
        r.size_in += abs(f[key] - t[key]) <= 3.0 * sig


def _headline_truth(truth: dict, spans: list[tuple[float, float, float, float]]) -> float:
    """The true headline (the data contract's definition): the median over the frames'
    true rings of the mean diameter around each; where a true taper lies among the rings
    and one side of its ramp holds at least twice the other's rings, over that side's
    (the constant section most of the run measured). From the true poses, so the camera motion's axial placement of
    the stations does not move the truth."""
    mid = np.array([sp[2] for sp in spans])
    dia = np.array([sp[3] for sp in spans])
    for t in truth.get("features", []):
        if t["kind"] != "taper" or not (mid.min() < t["axial_to_mm"] and mid.max() > t["axial_from_mm"]):
            continue
        before, after = mid < t["axial_from_mm"], mid > t["axial_to_mm"]
        big, small = (before, after) if before.sum() >= after.sum() else (after, before)
        if big.any() and big.sum() >= 2 * small.sum():  # analysis.stations.CLEAR_MAJORITY
            return float(np.median(dia[big]))
    return float(np.median(dia))


def _headline(report: dict, truth: dict, x: np.ndarray, st: list[dict], counts: dict,
              spans: list[tuple[float, float, float, float]] | None = None) -> None:
    """The headline ``inner_diameter_mm`` against the truth (:func:`_headline_truth`
    with the true rings ``spans``; without them, the truth's mean diameter over the
    reported stations, their median), tallied per class of run (out-of-round, reducing,
    partly flooded: truth features overlapping the stations; plain otherwise): (covered
    within 3 sigma, error mm, error in sigmas)."""
    d, sig = report.get("inner_diameter_mm"), report.get("inner_diameter_sigma_mm")
    if d is None:
        return
    at = np.array([s["axial_mm"] for s in st])
    true = float(np.median(np.interp(at, x, [q["inner_diameter_mm"] for q in truth["stations"]])))
    if spans:
        true = _headline_truth(truth, spans)
    span = (float(at.min()), float(at.max()))
    kinds = {t["kind"] for t in truth.get("features", []) if t["kind"] in ("taper", "ovality", "water")
             and min(_extent(t)[1], span[1]) > max(_extent(t)[0], span[0])}
    err = abs(d - true)
    for cls in sorted(kinds) or ["plain"]:
        counts.setdefault("headline", {}).setdefault(cls, []).append(
            (bool(sig) and err <= 3.0 * sig, err, err / sig if sig else np.inf))


def _score(
    report: dict, truth: dict, rows: dict[str, Row], counts: dict,
    spans: list[tuple[float, float, float, float]] | None = None,
) -> None:
    """Tally one run (``spans``: the frames' true ring stretches, :func:`_ring_spans`)."""
    d = truth.get("inner_diameter_mm") or report.get("inner_diameter_mm", 200.0)
    found = report.get("features") or []
    st = report.get("stations") or []
    span = (st[0]["axial_mm"], st[-1]["axial_mm"]) if st else (np.inf, -np.inf)
    for t in truth.get("features", []):
        small = t["kind"] == "lateral" and not _eligible(t, d)
        if t["kind"] not in KINDS or not (_eligible(t, d) or small):
            continue
        r = rows.setdefault(SMALL_LATERAL if small else t["kind"], Row())
        a, b = _extent(t)
        seen = min(b, span[1]) - max(a, span[0])
        inside = (span[0] <= a and b <= span[1]) if t["kind"] in POINT_KINDS else seen >= 10.0
        if t["kind"] == "bend":  # the turn the rings sweep must reach the product's bend_min_turn_deg
            inside = np.degrees(seen / t["radius_mm"]) >= BEND_MIN_TURN_DEG
        if not inside or _unseen(t, spans):
            r.outside += 1
            continue
        r.n += 1
        f = _match(t, found)
        if f is None:
            continue
        r.found += 1
        if t["kind"] in POINT_KINDS:
            r.ax.append(abs(f["axial_mm"] - t["axial_mm"]))
        if t["kind"] == "lateral":
            r.ang.append(abs((f["angle_deg"] - t["angle_deg"] + 180) % 360 - 180))
        _sizes(t, f, r, d, truth)
    tst = truth.get("stations") or []
    if tst and st:
        x = np.array([s["axial_mm"] for s in tst])
        _headline(report, truth, x, st, counts, spans)
        for s in st:
            for key, tkey in (("ovality_pct", "ovality_pct"), ("water_depth_mm", "water_depth_mm")):
                if s.get(key) is not None and x[0] <= s["axial_mm"] <= x[-1]:
                    true = float(np.interp(s["axial_mm"], x, [q[tkey] for q in tst]))
                    if key == "water_depth_mm" and true < 0.05 * d and not s[key]:
                        continue  # dry (or too shallow to count) and reported dry
                    counts.setdefault(key, []).append(abs(s[key] - true))
    for f in found:  # a feature no true one of its kind (in or out of the run) matches
        if not any(
            _match(t, [f]) is not None for t in truth.get("features", []) if t["kind"] == f["kind"]
        ):
            counts.setdefault("false_features", {}).setdefault(f["kind"], 0)
            counts["false_features"][f["kind"]] += 1
    spots = [_extent(t) for t in truth.get("features", []) if t["kind"] in POINT_KINDS]
    for dfx in report.get("defects", []):
        a, b = dfx["axial_start_mm"], dfx["axial_start_mm"] + dfx["length_mm"]
        true = any(min(b, x["axial_start_mm"] + x["length_mm"] + 10) > max(a, x["axial_start_mm"] - 10)
                   for x in truth.get("defects", []))
        if not true:
            counts["false_defects"] += 1
            counts["feature_defects"] += any(min(b, hi + 10) > max(a, lo - 10) for lo, hi in spots)


def _listing(seed: int, report: dict, truth: dict, spans: list[tuple[float, float, float, float]] | None) -> list[str]:
    """One line per true joint / lateral of the run (``--list``): found - true axial (mm;
    a lateral's clock error too), MISS, or why it is not counted (under the issue's class,
    outside the stations' span, a gap no true ring crossed); then the run's false ones."""
    d = truth.get("inner_diameter_mm") or report.get("inner_diameter_mm", 200.0)
    found = report.get("features") or []
    st = report.get("stations") or []
    span = (st[0]["axial_mm"], st[-1]["axial_mm"]) if st else (np.inf, -np.inf)
    out = []
    for t in truth.get("features", []):
        if t["kind"] not in POINT_KINDS:
            continue
        a, b = _extent(t)
        why = ("below the class" if not _eligible(t, d) else "outside" if not span[0] <= a <= b <= span[1]
               else "unseen" if _unseen(t, spans) else "")
        f = _match(t, found)
        got = "MISS" if f is None else f"{f['axial_mm'] - t['axial_mm']:+.1f} mm"
        if f is not None and t["kind"] == "lateral":
            got += f", clock {(f['angle_deg'] - t['angle_deg'] + 180) % 360 - 180:+.1f} deg"
        out.append(f"  s{seed} {t['kind']:7} at {t['axial_mm']:8.1f}: {got}" + (f" (not counted: {why})" if why else ""))
    for f in found:
        if f["kind"] in POINT_KINDS and not any(
            _match(t, [f]) is not None for t in truth.get("features", []) if t["kind"] == f["kind"]
        ):
            out.append(f"  s{seed} {f['kind']:7} at {f['axial_mm']:8.1f}: FALSE")
    return out


def _table(title: str, rows: dict[str, Row], counts: dict, done: list[int], failed: list[int]) -> None:
    print(f"\n{title}: {len(done)} seeds scored: {done}; refused/failed: {failed}")
    print(f"{'kind':8} {'n':>4} {'outside':>7} {'recall':>7} {'ax<=3mm':>8} {'ax med':>7} "
          f"{'ang<=3deg':>9} {'size in 3sig':>12} {'err med/max':>12}")
    for kind in (*KINDS, SMALL_LATERAL):
        r = rows.get(kind)
        if not r:
            continue
        n = r.found or 1
        ax = f"{sum(e <= 3 for e in r.ax) / n:8.2f}" if r.ax else f"{'-':>8}"
        axm = f"{np.median(r.ax):7.1f}" if r.ax else f"{'-':>7}"
        ang = f"{sum(e <= 3 for e in r.ang) / len(r.ang):9.2f}" if r.ang else f"{'-':>9}"
        size = f"{r.size_in / r.size_n:5.2f} ({r.size_n:2d})" if r.size_n else "-"
        err = f"{np.median(r.err):.2f}/{max(r.err):.2f}" if r.err else "-"
        recall = r.found / r.n if r.n else float("nan")
        print(f"{kind:8} {r.n:>4} {r.outside:>7} {recall:>7.2f} {ax} {axm} {ang} {size:>12} {err:>12}")
    for key, unit in (("ovality_pct", "pp"), ("water_depth_mm", "mm")):
        e = np.array(counts.get(key, []))
        if len(e):
            print(f"per station |{key} error|: median {np.median(e):.2f} {unit}, 90th percentile "
                  f"{np.percentile(e, 90):.2f} {unit}, {len(e)} stations")
    for cls, got in sorted(counts.get("headline", {}).items()):
        e = np.array([g[1] for g in got])
        z = np.array([g[2] for g in got])
        print(f"headline inner_diameter_mm, {cls:8} runs: within 3 sigma {sum(g[0] for g in got)} of {len(got)}, "
              f"|error| median {np.median(e):.2f} mm, max {e.max():.2f} mm ({z.max():.1f} sigma)")
    print(f"false features (no true one of the kind within the match tolerance / overlap): {counts.get('false_features', {})}")
    print(f"false defects: {counts['false_defects']} (within 10 mm of a joint or a hole: "
          f"{counts['feature_defects']}); runs with unreliable motion: {counts['unreliable_runs']}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="0-29", help="e.g. 0-29 or 0-9,20-25")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_features"))
    ap.add_argument("--size", default=None, help="WxH (default: the -small scenario's 400x300)")
    ap.add_argument("--fresh", action="store_true", help="reconstruct again even if a report exists")
    ap.add_argument("--motion", choices=("estimated", "truth", "both"), default="estimated",
                    help="camera motion: estimated (the product), truth (ground_truth/poses.txt), both")
    ap.add_argument("--list", action="store_true",
                    help="after the table, each true joint and lateral: found - true axial, MISS, or why not counted")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    motions = ("truth", "estimated") if args.motion == "both" else (args.motion,)
    for motion in motions:
        rows: dict[str, Row] = {}
        counts: dict = {"false_defects": 0, "feature_defects": 0, "unreliable_runs": 0}
        done, failed, listed = [], [], []
        for seed in _seeds(args.seeds):
            got = _run(seed, args.work, args.size, args.fresh, motion)
            if isinstance(got, str):
                failed.append(seed)
                print(f"seed {seed} ({motion} motion): {got}", flush=True)
                continue
            done.append(seed)
            counts["unreliable_runs"] += bool((got[0].get("trajectory_quality") or {}).get("unreliable"))
            spans = _ring_spans(args.work / f"s{seed}", got[1])
            _score(*got, rows, counts, spans)
            listed += _listing(seed, *got, spans) if args.list else []
            print(f"seed {seed} ({motion} motion): done ({len(done)} seeds)", flush=True)
        _table(f"{motion} camera motion", rows, counts, done, failed)
        if listed:
            print(f"joints and laterals, found - true ({motion} camera motion):", *listed, sep="\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
