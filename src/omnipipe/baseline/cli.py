"""``omnipipe baseline``: the optimal camera-to-laser distance (Sec. IV, Fig. 9)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from omnipipe import cli_values
from omnipipe.baseline import BaselineConfig, plot_fig9, run
from omnipipe.config import finite_option
from omnipipe.errors import ConfigError, OutputError
from omnipipe.rig_yaml import load_rig

# Largest wall distance accepted (mm): 1 km, far beyond any pipe; beyond ~1e300 the
# optimisation overflows.
MAX_DISTANCE_MM = 1e6


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``baseline`` sub-command."""
    p = sub.add_parser(
        "baseline",
        help="optimal baseline (camera-to-laser distance) for given wall distances",
        description="Minimises the light section's depth error rate (paper Sec. IV, Eq. 6-9) for each "
        "wall distance, with the mirror and f of RIG, and can draw the paper's Fig. 9.",
    )
    p.add_argument("--rig", required=True, help="rig.yaml (mirror a, b and f are used)")
    p.add_argument(
        "--distance",
        type=cli_values.number("--distance", 0.0, MAX_DISTANCE_MM, open_lo=True, unit="mm"),
        nargs="+",
        default=[100.0, 200.0, 300.0],
        help="wall distances d (mm)",
    )
    p.add_argument("--json", action="store_true", help='print {"optimal_baseline_mm": {d: l}}')
    p.add_argument("--plot", help="write Fig. 9 (error rate against baseline) to this PNG")
    p.set_defaults(func=_main)


def _main(args: argparse.Namespace) -> int:
    for d in args.distance:
        finite_option(d, "--distance", positive=True)
        if d > MAX_DISTANCE_MM:
            raise ConfigError("--distance", f"must be at most {MAX_DISTANCE_MM:g} mm, got {d:g}")
    if args.plot:
        folder = Path(args.plot).parent
        if not folder.is_dir():
            raise ConfigError("--plot", f"folder {folder} does not exist")
        if Path(args.plot).is_dir():
            raise ConfigError("--plot", f"{args.plot} is a directory, not a PNG file name")
    rig = load_rig(args.rig)
    if rig.mirror is None:
        raise ConfigError(
            "mirror", "the baseline optimisation (Sec. IV) needs the hyperboloid mirror's a and b", args.rig
        )
    result = run(BaselineConfig(rig.mirror, rig.camera.f, tuple(args.distance)))
    if args.plot:
        try:
            plot_fig9(result, args.plot)
        except OSError as exc:
            raise OutputError(f"{args.plot}: cannot write ({exc.strerror or exc})") from None
    if args.json:
        print(
            json.dumps(
                {
                    "optimal_baseline_mm": {
                        f"{d:g}": round(v, 3) for d, v in result.optimal_mm.items()
                    }
                }
            )
        )
        return 0
    print(
        f"mirror a = {rig.mirror.a:g} mm, b = {rig.mirror.b:g} mm; current baseline "
        + ("(no laser in rig.yaml)" if rig.laser is None else f"{rig.laser.distance_mm:g} mm")
    )
    print(f"{'wall distance d (mm)':>22s} {'optimal l (mm)':>15s} {'l/d':>6s} {'error rate':>11s}")
    for d, l in result.optimal_mm.items():
        rate = float(result.rates[d].min())
        print(f"{d:22g} {l:15.1f} {l / d:6.3f} {100 * rate:10.3f}%")
    if args.plot:
        print(f"Fig. 9 written to {args.plot}")
    return 0
