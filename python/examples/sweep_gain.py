"""Sweep one gain over 20 seeds and plot Table II's ASIF/KF ratio against it.

Table II of the paper is the velocity RMSE of the KF and the ASIF after the
model fault at t = 10 s; the ratio ASIF/KF below 1 is the ASIF's gain. This
sweeps the ASIF's limit ``asif.rho_max`` (ρ_max, both channels; docs/scenarios.md)
over a range, runs both filters over 20 seeds at each value (the runs
``formation paper`` makes for Table II), and plots the mean ratio per channel
with the paper's beside it.

    pip install ./python matplotlib
    python python/examples/sweep_gain.py --key asif.rho_max --values 0.02,0.04,0.08,0.16,0.32 --out ratio.png

Any number-valued scenario key works as --key (``backstepping.c1``,
``robot.mass`` …); a key holding a pair per channel gets the value twice.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import formation


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenario", default="paper")
    ap.add_argument("--key", default="asif.rho_max", help="the scenario key to sweep [asif.rho_max]")
    ap.add_argument("--values", default="0.02,0.04,0.08,0.16,0.32", help="comma-separated values")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--out", default="asif_kf_ratio.png", help="the figure (png, svg, pdf)")
    a = ap.parse_args()
    values = [float(v) for v in a.values.split(",")]
    base = formation.Scenario.load(a.scenario)
    print(f"{a.key} = {base.get(a.key)} in {base.name}; sweeping {values} over {a.seeds} seeds")

    ratios = []  # (values, followers, 2): linear, angular
    t = time.perf_counter()
    for v in values:
        s = base.copy()
        # The same checks as --set: a bad value raises ValueError.
        s[a.key] = [v] * len(base[a.key]) if isinstance(base[a.key], list) else v
        table2 = formation.paper(s, seeds=a.seeds, claims=False).table2
        ratios.append(table2.ratio())
        lin, ang = table2.ratio().mean(axis=0)
        print(f"  {a.key} = {v:<8g} ASIF/KF linear {lin:.3f}, angular {ang:.3f}")
    ratios = np.array(ratios)
    paper = table2.paper_ratio().mean(axis=0)
    print(f"{len(values) * 2 * a.seeds} runs in {time.perf_counter() - t:.1f} s; the paper's ratios: "
          f"linear {paper[0]:.3f}, angular {paper[1]:.3f}")

    import matplotlib  # only for the figure

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for ch, (name, colour) in enumerate([("linear", "tab:blue"), ("angular", "tab:orange")]):
        mean = ratios[:, :, ch].mean(axis=1)
        lo, hi = ratios[:, :, ch].min(axis=1), ratios[:, :, ch].max(axis=1)
        ax.plot(values, mean, "o-", color=colour, label=f"{name} (mean of followers; band: min–max)")
        ax.fill_between(values, lo, hi, color=colour, alpha=0.2)
        ax.axhline(paper[ch], color=colour, ls="--", lw=1, label=f"{name}, the paper's")
    ax.set_xlabel(a.key)
    ax.set_ylabel("velocity RMSE, ASIF / KF (Table II)")
    ax.set_xscale("log" if min(values) > 0 and max(values) / min(values) > 20 else "linear")
    ax.set_title(f"{base.name}: Table II's ASIF/KF ratio, {a.seeds} seeds per value")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(a.out, dpi=150)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
