"""Benchmark of forensics.stats.scores against plain implementations, in the same run.

Run::

    /work/main/.venv/bin/python benchmarks/bench_scores.py [--repeat N]

Cases (the sizes of the reference paper):

* EER of 8,940 genuine vs 5,006,400 impostor scores (float64, N(2,1) vs N(0,1)):
  ``eer`` (sort-free window path), the module's own full-sort path, and a plain
  "roc_curve" style implementation (stable argsort of the pooled scores with
  labels, cumulative sums, crossing), which is what scikit-learn's
  ``roc_curve`` + interpolation does.
* ``roc`` / ``auc`` / ``eer_convex_hull`` on the same data (full curve).
* Bootstrap EER, 1,000 replicates of 800 vs 800: vectorised ``bootstrap_eer``
  against a per-replicate loop calling ``eer``.

Times are the best and the median of ``--repeat`` runs (wall clock,
``time.perf_counter``); each result is checked against the plain one.
"""
from __future__ import annotations

import argparse
import os
import platform

import numpy as np

from _timing import timeit  # benchmarks/ is on sys.path when a script runs

from forensics.stats import scores


def plain_eer(genuine: np.ndarray, impostor: np.ndarray) -> float:
    """roc_curve-style EER: argsort pooled scores with labels, cumsum, interpolate."""
    scores_ = np.concatenate([genuine, impostor])
    labels = np.concatenate([np.ones(genuine.size, bool), np.zeros(impostor.size, bool)])
    order = np.argsort(scores_, kind="stable")
    s, lab = scores_[order], labels[order]
    last = np.flatnonzero(np.append(s[1:] != s[:-1], True))  # last index of each distinct value
    g_le = np.cumsum(lab)[last]  # genuine <= value
    i_le = np.cumsum(~lab)[last]
    # At threshold = distinct value k: FRR = #genuine < v_k, FAR = #impostor >= v_k.
    frr = np.concatenate([[0], g_le]) / genuine.size
    far = 1.0 - np.concatenate([[0], i_le]) / impostor.size
    d = frr - far
    k = int(np.argmax(d > 0))
    x0, x1, y0, y1 = far[k - 1], far[k], frr[k - 1], frr[k]
    return float((x0 * y1 - y0 * x1) / ((y1 - y0) - (x1 - x0)))


def loop_bootstrap(g: np.ndarray, i: np.ndarray, rng: np.random.Generator, n_boot: int) -> np.ndarray:
    out = np.empty(n_boot)
    for b in range(n_boot):
        out[b] = scores.eer(g[rng.integers(0, g.size, g.size)], i[rng.integers(0, i.size, i.size)]).eer
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    rep = args.repeat

    rng = np.random.default_rng(2024)
    genuine = rng.normal(2.0, 1.0, 8_940)
    impostor = rng.normal(0.0, 1.0, 5_006_400)
    scores.eer(genuine, impostor)  # warm-up (page faults of first use)

    rows: list[tuple[str, str, float, float, str]] = []

    best, med, ref = timeit(lambda: plain_eer(genuine, impostor), max(1, rep // 2))
    rows.append(("EER 8,940 vs 5,006,400", "plain: argsort pooled + cumsum", best, med, f"{ref:.10f}"))
    best, med, res = timeit(
        lambda: scores._eer_sorted(np.sort(genuine), np.sort(impostor)), rep
    )
    rows.append(("", "scores full-sort path", best, med, f"{res[0]:.10f}"))
    best, med, res = timeit(lambda: scores.eer(genuine, impostor), rep)
    rows.append(("", "scores.eer (sort-free window)", best, med, f"{res.eer:.10f}"))
    # The plain version forms FAR = 1 - count/n in floats (cancellation ~1e-11 at n = 5e6);
    # the module works in exact integer counts.
    assert abs(res.eer - ref) < 1e-9, (res.eer, ref)

    best, med, res = timeit(lambda: scores.roc(genuine, impostor), rep)
    rows.append(("full curve 8,940 vs 5,006,400", "scores.roc", best, med, f"{res.thresholds.size:,} points"))
    best, med, res = timeit(lambda: scores.auc(genuine, impostor), rep)
    rows.append(("", "scores.auc", best, med, f"{res:.10f}"))
    best, med, res = timeit(lambda: scores.eer_convex_hull(genuine, impostor), rep)
    rows.append(("", "scores.eer_convex_hull", best, med, f"{res.eer:.10f}"))

    g800, i800 = rng.normal(2.0, 1.0, 800), rng.normal(0.0, 1.0, 800)
    best, med, slow = timeit(
        lambda: loop_bootstrap(g800, i800, np.random.default_rng(1), 1000), max(1, rep // 2)
    )
    rows.append(("bootstrap 1,000 x (800 vs 800)", "plain: loop of eer()", best, med,
                 f"mean {slow.mean():.4f} sd {slow.std(ddof=1):.4f}"))
    best, med, fast = timeit(lambda: scores.bootstrap_eer(g800, i800, np.random.default_rng(2), 1000), rep)
    reps = fast.replicates
    rows.append(("", "scores.bootstrap_eer (vectorised)", best, med,
                 f"mean {reps.mean():.4f} sd {reps.std(ddof=1):.4f}"))

    print(f"python {platform.python_version()}, numpy {np.__version__}, {os.cpu_count()} CPUs, "
          f"{platform.processor() or platform.machine()}; best / median of {rep} runs "
          f"(plain EER and loop bootstrap: {max(1, rep // 2)})")
    header = ("case", "implementation", "best s", "median s", "result")
    widths = [max(len(str(r[c])) if c < 2 else 9 for r in rows + [header]) for c in range(2)]
    print(f"| {header[0]:<{widths[0]}} | {header[1]:<{widths[1]}} "
          f"| {header[2]:>8} | {header[3]:>8} | {header[4]}")
    print(f"|{'-' * (widths[0] + 2)}|{'-' * (widths[1] + 2)}|{'-' * 10}|{'-' * 10}|{'-' * 30}")
    for case, impl, b, m, note in rows:
        print(f"| {case:<{widths[0]}} | {impl:<{widths[1]}} | {b:8.4f} | {m:8.4f} | {note}")


if __name__ == "__main__":
    main()
