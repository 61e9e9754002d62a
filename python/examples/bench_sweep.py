"""What a sweep costs from Python against the command line.

A seed sweep of the paper scenario (30 s, 4 followers) run three ways:

- ``formation sim SCENARIO --set seed=S --no-csv`` once per run, as a shell
  loop or a MATLAB script would call it (a process per run);
- ``formation.sim(s, columns=False)`` from Python (the summary only, as
  ``--no-csv``);
- ``formation sim SCENARIO --set seed=S`` writing its CSVs;
- ``formation.sim(s)`` from Python with every column as numpy arrays.

Prints runs per second for each (the median of --repeat sweeps) and the
ratio to the command line. Build both in release first:

    cargo build --release && pip install ./python
    python python/examples/bench_sweep.py --cli target/release/formation
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import tempfile
import time

import formation


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cli", default="target/release/formation", help="the formation binary (a release build)")
    ap.add_argument("--scenario", default="paper", help="scenario file or built-in name [paper]")
    ap.add_argument("--runs", type=int, default=40, help="runs per sweep [40]")
    ap.add_argument("--repeat", type=int, default=5, help="sweeps of each kind; the median is shown [5]")
    a = ap.parse_args()
    if not os.access(a.cli, os.X_OK):
        ap.error(f"--cli {a.cli}: not an executable (cargo build --release)")
    base = formation.Scenario.load(a.scenario)
    scenarios = [base.with_(seed=s) for s in range(1, a.runs + 1)]

    with tempfile.TemporaryDirectory() as tmp:

        def cli() -> None:
            for s in range(1, a.runs + 1):
                subprocess.run(
                    [a.cli, "sim", a.scenario, "--set", f"seed={s}", "--no-csv", "-q", "--out", f"{tmp}/run"],
                    check=True,
                )

        def cli_csv() -> None:
            for s in range(1, a.runs + 1):
                subprocess.run(
                    [a.cli, "sim", a.scenario, "--set", f"seed={s}", "-q", "--out", f"{tmp}/run"], check=True
                )

        def summary_only() -> None:
            for s in scenarios:
                formation.sim(s, columns=False)

        def arrays() -> None:
            for s in scenarios:
                formation.sim(s)

        rates = {}
        kinds = [
            ("command line, --no-csv", cli),
            ("Python, columns=False", summary_only),
            ("command line, CSVs", cli_csv),
            ("Python, numpy arrays", arrays),
        ]
        for name, sweep in kinds:
            times = []
            for _ in range(a.repeat):
                t = time.perf_counter()
                sweep()
                times.append(time.perf_counter() - t)
            rates[name] = a.runs / statistics.median(times)
            print(f"{name:<24} {rates[name]:8.1f} runs/s (median of {a.repeat} sweeps of {a.runs})", flush=True)
    cli_rate = rates["command line, --no-csv"]
    for name, r in rates.items():
        print(f"{name:<24} {r / cli_rate:6.2f} × the command line")
    print(f"one run: {base.steps} steps × {len(base.follower_ids)} followers, os.cpu_count() = {os.cpu_count()}")


if __name__ == "__main__":
    main()
