"""False-alarm rate of the residual-structure naming (forensics.check.structure) on null data.

``.venv/bin/python benchmarks/structure_null.py 100 124`` checks ``make_hidden('none', rng=s)`` for s in
[100, 124), prints one JSON line per seed (named structure or null, the smallest Holm-adjusted p, every raw
p) and, at the end, the number of seeds with a structure named and a KS test of all raw p-values against
uniform.
"""
from __future__ import annotations

import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
from forensics.fixtures.hidden import make_hidden
from scipy import stats

from forensics.check import check


def main(first: int, last: int) -> None:
    rows = []
    for s in range(first, last):
        tmp = Path(tempfile.mkdtemp())
        try:
            data = make_hidden("none", tmp / "none", rng=s)
            r = check(data.out, rng=s)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        st = r.structure
        best = min(st.tests, key=lambda t: t.p_holm)
        rows.append({"seed": s, "named": st.named.summary() if st.named else None, "min_p_holm": best.p_holm,
                     "best": best.label, "flagged": r.flagged, "p": {t.label: t.p for t in st.tests}})
        print(json.dumps(rows[-1]), flush=True)
    raw = [p for row in rows for p in row["p"].values()]
    print(json.dumps({"seeds": len(rows), "named": sum(row["named"] is not None for row in rows),
                      "raw_p_below_0.05": float(np.mean(np.array(raw) < 0.05)),
                      "ks_uniform_p": float(stats.kstest(raw, "uniform").pvalue)}))


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 100, int(sys.argv[2]) if len(sys.argv) > 2 else 124)
