"""How long `omnipipe --help` (and `omnipipe reconstruct --help`) take, in fresh processes.

    python benchmarks/bench_cli.py [--repeat 5]

Prints the median and best wall time of each. For the import breakdown:
`python -X importtime -m omnipipe.cli --help`.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time


def _time(argv: list[str], repeat: int) -> list[float]:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        subprocess.run(
            [sys.executable, "-m", "omnipipe.cli", *argv],
            check=True,
            stdout=subprocess.DEVNULL,
        )
        times.append(time.perf_counter() - t0)
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    for argv in (["--help"], ["reconstruct", "--help"], ["simulate", "--help"]):
        times = _time(argv, args.repeat)
        print(
            f"omnipipe {' '.join(argv):20s} median {statistics.median(times):.3f} s, "
            f"best {min(times):.3f} s over {len(times)} runs"
        )


if __name__ == "__main__":
    main()
