"""Local processes against a Dask cluster: the same outputs, and how long each took.

    python benchmarks/bench_cluster.py [--seeds 1 2 4] [--frames 40] [--size 800x600]
        [--workers 2] [--keep DIR]

Simulates the random scenarios of ``--seeds`` (the default three have textured walls:
steel, tiles, joints; a smooth wall is refused, which batch lists as failed), then

1. ``omnipipe batch`` of all runs on ``--workers`` local processes and on a Dask
   ``LocalCluster`` (``--workers`` worker processes on 127.0.0.1, one thread each);
2. ``omnipipe reconstruct`` of the first run with its frame-parallel work on local
   processes and on the same cluster (``--scheduler``);

and prints, per run, whether report.json (every value but the wall-clock keys
``timings_s``, ``frames_per_s`` and ``executor``) and trajectory.txt are identical, with
the wall times. Issue 13's acceptance: a batch of 3 runs on a local Dask cluster gives
the same report.json values as the local runs. It only measures; exit code 1 if any
output differs.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

from omnipipe.cli import main as omnipipe

VOLATILE = ("timings_s", "frames_per_s", "executor")


def _report(path: Path) -> dict:
    data = json.loads((path / "report.json").read_text())
    return {k: v for k, v in data.items() if k not in VOLATILE}


def _same(a: Path, b: Path) -> tuple[bool, bool]:
    return _report(a) == _report(b), (a / "trajectory.txt").read_bytes() == (
        b / "trajectory.txt"
    ).read_bytes()


def _timed(args: list[str]) -> tuple[int, float]:
    t0 = time.perf_counter()
    code = omnipipe(args)
    return code, time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--size", default="800x600")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--keep", default=None, help="keep datasets and outputs here")
    args = parser.parse_args()
    try:
        import distributed
    except ImportError:
        sys.exit("needs Dask: pip install 'omnipipe[dask]'")
    from omnipipe.sim import make_scenario
    from omnipipe.sim import run as simulate

    size = tuple(int(v) for v in args.size.split("x"))
    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="omnipipe-cluster-"))
    root.mkdir(parents=True, exist_ok=True)
    runs = []
    for seed in args.seeds:
        path = root / f"random-{seed}"
        if not (path / "rig.yaml").is_file():
            simulate(make_scenario("random", frames=args.frames, size=size, seed=seed), path, force=True, workers=2)
        runs.append(path)
    cluster = distributed.LocalCluster(
        host="127.0.0.1", n_workers=args.workers, threads_per_worker=1, processes=True,
        dashboard_address=None,
    )
    differ = 0
    try:
        address = cluster.scheduler_address
        common = ["--quiet", "--force"]
        code_l, t_l = _timed(["batch", *map(str, runs), "--out", str(root / "batch-local"),
                              "--workers", str(args.workers), *common])
        code_d, t_d = _timed(["batch", *map(str, runs), "--out", str(root / "batch-dask"),
                              "--scheduler", address, *common])
        print(f"batch of {len(runs)} runs ({args.frames} frames at {args.size}): local processes "
              f"{t_l:.1f} s (exit {code_l}), Dask LocalCluster {t_d:.1f} s (exit {code_d})")
        index = json.loads((root / "batch-local" / "index.json").read_text())["runs"]
        for row in index:
            if row["status"] != "ok":
                print(f"  {row['name']}: {row['status']} locally ({row.get('error', '')})")
                continue
            rep, traj = _same(root / "batch-local" / row["name"], root / "batch-dask" / row["name"])
            differ += not (rep and traj)
            print(f"  {row['name']}: report.json values {'identical' if rep else 'DIFFER'}, "
                  f"trajectory.txt {'identical' if traj else 'DIFFERS'}")
        first = str(runs[0])
        code_l, t_l = _timed(["reconstruct", first, "--out", str(root / "rec-local"),
                              "--workers", str(args.workers), *common])
        code_d, t_d = _timed(["reconstruct", first, "--out", str(root / "rec-dask"),
                              "--scheduler", address, *common])
        if code_l == 0 and code_d == 0:
            rep, traj = _same(root / "rec-local", root / "rec-dask")
            differ += not (rep and traj)
            print(f"reconstruct {runs[0].name}: local processes {t_l:.1f} s, --scheduler {t_d:.1f} s; "
                  f"report.json values {'identical' if rep else 'DIFFER'}, "
                  f"trajectory.txt {'identical' if traj else 'DIFFERS'}")
        else:
            print(f"reconstruct {runs[0].name}: exit {code_l} locally, {code_d} on the cluster")
    finally:
        cluster.close()
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)
    sys.exit(1 if differ else 0)


if __name__ == "__main__":
    main()
