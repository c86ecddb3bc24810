"""Wall time of the 1D demo (goal: ≤ 3 minutes on 2 cores) and its accuracy figures.

Run: ``python benchmarks/bench_demo1d.py [--seeds 0 1 2] [--out runs/bench_demo1d]``. Prints
one line per seed (its wall time, learned/DP return ratio and coverage per parameter), then
the median wall time; each seed's figures (``dp_comparison.png`` among them) land in
``OUT/seed_N``.
"""

from __future__ import annotations

import argparse
import statistics
import time

from _common import integer

from irc_torchrl.algorithms.demo import run_demo
from irc_torchrl.config import load_config


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=integer(0), nargs="+", default=[0])
    parser.add_argument("--out", default="runs/bench_demo1d")
    args = parser.parse_args()
    walls = []
    for seed in args.seeds:
        start = time.perf_counter()
        config = load_config(overrides=[f"seed={seed}"])
        summary = run_demo(config, f"{args.out}/seed_{seed}", show_progress=False)
        walls.append(time.perf_counter() - start)
        coverage = ", ".join(f"{n} {p['coverage']:.2f}" for n, p in summary["parameters"].items())
        timings = ", ".join(f"{k} {v:.1f}" for k, v in summary["timings"].items())
        print(
            f"seed {seed}: wall {walls[-1]:.1f} s ({walls[-1] / 180:.2f} of the 3-minute budget); "
            f"DP ratio {summary['dp_ratio']:.4f}; coverage {coverage}; {timings}"
        )
    print(f"median wall {statistics.median(walls):.1f} s over {len(walls)} seed(s)")


if __name__ == "__main__":
    main()
