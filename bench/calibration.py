"""Calibration of the intervals codearcade prints: coverage, false positives and power at 2-10 episodes.

The return distributions of tests/test_calibration.py (Pong-like clustered, Breakout-like skewed counts, a bimodal
mixture, many ties), with the project's own functions (``store.statistics``) beside the percentile bootstrap it
printed before issue 37:

1. coverage of the true mean by one version's 95% interval (share of the intervals given; all-equal samples
   get none), Student t against the percentile bootstrap, n = 2, 3, 5, 10; and, for t, shapes beyond the
   test's (strongly skewed counts, modes far apart, one-life counts, a rare collapse), where its promise ends;
2. how often two samples of one distribution are called different, Welch t against the two-sample percentile
   bootstrap, n = 2, 3, 4, 6, 10 a side;
3. coverage of the true interquartile mean by the stratified bootstrap (rliable's), over eight games with n
   values each and over one game's n values, n = 3, 5, 10, 20, 30 (the project gives the interval only from
   ``IQM_MIN_PER_STRATUM`` values a stratum);
4. power: the smallest difference of means (a shift of one side) Welch's test calls different 80% of the time,
   n = 3, 5, 10 a side, in return points and in standard deviations of the returns.

    .venv/bin/python bench/calibration.py [--replicates 10000] [--iqm-replicates 1000]

Seeds are fixed: the same figures every time (docs/benchmarks.md, "Calibration of the intervals").
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from store import statistics  # noqa: E402
from tests.test_calibration import (SHAPES, covers, draw, games, mixture, old_percentile_difference,  # noqa: E402
                                    old_percentile_mean, true_iqm, true_mean)


def _pct(x: float) -> str:
    return f"{100 * x:.1f}%"


def coverage_table(replicates: int) -> list[str]:
    rows = ["| shape | n | t (project) | percentile bootstrap (before) | samples all equal (no interval) |",
            "|---|---|---|---|---|"]
    for index, (name, shape) in enumerate(SHAPES.items()):
        for n in (2, 3, 5, 10):
            samples = draw(shape, (replicates, n), (n, index))
            t_cov, given = covers(*statistics.mean_bounds(samples), true_mean(shape))
            varying = samples.min(axis=1) != samples.max(axis=1)
            old = np.full((2, replicates), np.nan)
            old[:, varying] = old_percentile_mean(samples[varying])
            p_cov, _ = covers(old[0], old[1], true_mean(shape))
            rows.append(f"| {name} | {n} | {_pct(t_cov)} | {_pct(p_cov)} | {_pct(1 - given)} |")
    return rows


def limits_table(replicates: int) -> list[str]:
    """Where the promise ends: shapes beyond those the test holds the project to."""
    from scipy import stats

    from tests.test_calibration import _table

    counts, court = np.arange(0, 3001), np.arange(-21, 22)
    beyond = {"counts, skewness 1.6 (negative binomial, shape 1.5, mean 40)":
              _table(counts, stats.nbinom.pmf(counts, 1.5, 1.5 / 41.5)),
              "modes 30 apart (half around -15, half around +15, sd 4)":
              _table(court, stats.norm.pdf(court, -15, 4) + stats.norm.pdf(court, 15, 4)),
              # a simple Breakout policy's lives (--one-life) were about this: 400 games, mean 5.6, skewness 2.0
              "one-life counts, skewness 2 (geometric, mean 5.6)": _table(counts, stats.geom.pmf(counts + 1, 1 / 6.6)),
              "a rare collapse: a winning policy (18-21) that loses a game -21 one time in 20":
              _table([-21, 18, 19, 20, 21], [0.05, 0.2375, 0.2375, 0.2375, 0.2375])}
    rows = ["| shape | n = 3 | n = 5 | n = 10 |", "|---|---|---|---|"]
    for index, (name, shape) in enumerate(beyond.items()):
        cells = [covers(*statistics.mean_bounds(draw(shape, (replicates, n), (n, index, 31))), true_mean(shape))[0]
                 for n in (3, 5, 10)]
        rows.append(f"| {name} | " + " | ".join(_pct(c) for c in cells) + " |")
    return rows


def false_positive_table(replicates: int) -> list[str]:
    rows = ["| shape | n a side | Welch t (project) | percentile bootstrap (before) |", "|---|---|---|---|"]
    for index, (name, shape) in enumerate(SHAPES.items()):
        for n in (2, 3, 4, 6, 10):
            a = draw(shape, (replicates, n), (n, index, 1))
            b = draw(shape, (replicates, n), (n, index, 2))
            low, high = statistics.difference_bounds(a, b)
            decided = ~np.isnan(low)
            welch = float(np.mean((low[decided] > 0) | (high[decided] < 0)))
            varying = (a.min(axis=1) != a.max(axis=1)) | (b.min(axis=1) != b.max(axis=1))
            old = float(np.mean(old_percentile_difference(a[varying], b[varying])))
            rows.append(f"| {name} | {n} | {_pct(welch)} | {_pct(old)} |")
    return rows


def _iqm_cover(strata_draws: list[np.ndarray], truth: float, n: int) -> float:
    bounds = []
    for r in range(strata_draws[0].shape[0]):
        found = statistics.iqm_interval([d[r] for d in strata_draws], resamples=999, minimum=0)
        bounds.append((np.nan, np.nan) if found.low is None else (found.low, found.high))
    low, high = np.array(bounds).T
    return covers(low, high, truth)[0]


def iqm_table(replicates: int) -> list[str]:
    eight = games()
    header = "| n a stratum | 8 games (stratified) | " + " | ".join(f"one stratum, {name}" for name in SHAPES) + " |"
    rows = [header, "|" + "---|" * (2 + len(SHAPES))]
    for n in (3, 5, 10, 20, 30):
        cells = [_iqm_cover([draw(g, (replicates, n), (n, i, 14)) for i, g in enumerate(eight)],
                            true_iqm(mixture(eight)), n)]
        for index, shape in enumerate(SHAPES.values()):
            cells.append(_iqm_cover([draw(shape, (replicates, n), (n, index, 15))], true_iqm(shape), n))
        rows.append(f"| {n} | " + " | ".join(_pct(c) for c in cells) + " |")
    return rows


def power_table(replicates: int) -> list[str]:
    rows = ["| shape (sd of returns) | n a side | difference detected 80% of the time | in sd |", "|---|---|---|---|"]
    for index, (name, shape) in enumerate(SHAPES.items()):
        values, probs = shape
        sd = float(np.sqrt(((values - true_mean(shape)) ** 2) @ probs))
        for n in (3, 5, 10):
            a = draw(shape, (replicates, n), (n, index, 21))
            b = draw(shape, (replicates, n), (n, index, 22))
            found = None
            for steps in range(1, 161):  # a shift of B by 0.05 sd at a time
                shift = steps * 0.05 * sd
                low, high = statistics.difference_bounds(a, b + shift)
                power = float(np.mean(np.nan_to_num(high, nan=1.0) < 0))
                if power >= 0.8:
                    found = shift
                    break
            shown = "more than 8 sd" if found is None else f"{found:.1f}"
            in_sd = "" if found is None else f"{found / sd:.2f}"
            rows.append(f"| {name} ({sd:.1f}) | {n} | {shown} | {in_sd} |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--replicates", type=int, default=10_000)
    parser.add_argument("--iqm-replicates", type=int, default=1000)
    args = parser.parse_args()
    began = time.monotonic()
    for title, rows in (("coverage of the true mean, 95% intervals", coverage_table(args.replicates)),
                        ("where t's promise ends (coverage of the true mean)", limits_table(args.replicates)),
                        ("identical policies called different (5% meant)", false_positive_table(args.replicates)),
                        ("power of Welch's test", power_table(args.replicates)),
                        ("coverage of the true IQM, stratified bootstrap", iqm_table(args.iqm_replicates))):
        print(f"\n{title}\n")
        print("\n".join(rows), flush=True)
    print(f"\n{time.monotonic() - began:.0f} s")


if __name__ == "__main__":
    main()
