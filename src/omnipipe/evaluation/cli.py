"""``omnipipe evaluate``: a reconstruction against the dataset's ground truth."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from omnipipe.evaluation import EvaluationConfig, EvaluationInputs, EvaluationResult, run


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``evaluate`` sub-command."""
    p = sub.add_parser(
        "evaluate",
        help="compare a reconstruction with the dataset's ground truth",
        description="Trajectory error (ATE after SE(3) alignment, scale, rotation), point-to-wall "
        "error, inner diameter and per-defect errors of OUT against DATASET/ground_truth.",
    )
    p.add_argument("out", help="reconstruction directory (omnipipe reconstruct --out)")
    p.add_argument("dataset", help="dataset directory with ground_truth/")
    p.add_argument("--json", action="store_true", help="print the errors as JSON")
    p.set_defaults(func=_main)


def format_result(res: EvaluationResult) -> str:
    """Human-readable table of an evaluation."""
    lines = [f"frames registered: {res.frames_registered} / {res.frames}"]
    if res.trajectory is not None:
        t = res.trajectory
        lines.append(
            f"trajectory: ATE {t.ate_rmse_mm:.3f} mm RMS (max {t.ate_max_mm:.3f}), scale error "
            f"{100 * t.scale_error:.3f} %, rotation {t.rotation_rmse_deg:.3f} deg RMS over {t.path_length_mm:.0f} mm"
        )
    if res.wall:
        w = res.wall
        lines.append(
            f"wall points: {w['points']}, radial error RMS {w['rmse_mm']:.3f} mm, bias {w['bias_mm']:+.3f} mm, "
            f"95 % within {w['p95_abs_mm']:.3f} mm"
        )
    if res.diameter:
        d = res.diameter
        if "measured_mm" in d:
            lines.append(
                f"inner diameter: measured {d['measured_mm']:.2f} mm, true {d['true_mm']:.2f} mm, "
                f"error {d['error_mm']:+.2f} mm"
            )
        else:
            lines.append(f"inner diameter: not measured (true {d['true_mm']:.2f} mm)")
    for row in res.defects:
        t, m = row.true, row.measured
        if t is None:
            if m is not None:
                lines.append(
                    f"defect not in ground truth: {m.kind} {m.height_mm:.1f} mm at {m.angle_deg:.0f} deg"
                )
            continue
        head = f"{t.kind} {t.height_mm:g}x{t.width_mm:g}x{t.length_mm:g} mm"
        place = {
            "outside": "outside the measured stretch",
            "partly": "runs past the measured stretch",
        }.get(row.coverage)
        if not row.found:
            lines.append(
                f"{head}: outside the measured stretch (no run could measure it)"
                if row.coverage == "outside"
                else f"{head}: NOT FOUND"
                + (f" ({place})" if place else "")
                + (
                    f" (below the run's detection limit {res.detection_limit_mm:.2f} mm)"
                    if res.detection_limit_mm is not None and t.height_mm < res.detection_limit_mm
                    else ""
                )
            )
            continue
        e = row.errors()
        cut = m is not None and m.truncated
        lines.append(
            f"{head}: height {e['height_mm']:+.2f}, width {e['width_mm']:+.2f}, length {e['length_mm']:+.2f}, "
            f"start {e['axial_start_mm']:+.2f} mm, angle {e['angle_deg']:+.2f} deg"
            + (f" ({place}; measured part {'flagged truncated' if cut else 'NOT flagged truncated'})"
               if row.coverage != "inside" and place else "")
        )
    if res.not_evaluated:
        lines.append(f"not evaluated: {', '.join(res.not_evaluated)}")
    for w in res.warnings:
        lines.append(f"warning: {w}")
    return "\n".join(lines)


def _main(args: argparse.Namespace) -> int:
    res = run(EvaluationConfig(), EvaluationInputs(Path(args.out), Path(args.dataset)))
    if args.json:
        print(json.dumps(res.to_dict(), indent=1))
    else:
        print(format_result(res))
    return 0
