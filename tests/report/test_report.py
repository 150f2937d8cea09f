"""The report layer: science modules draw nothing; report functions take results and lay them out."""
from __future__ import annotations

import subprocess
import sys

import numpy as np

from forensics.report.defects import detection_report, growth_report
from forensics.report.html import Report


def test_science_packages_import_neither_report_nor_matplotlib():
    code = ("import sys, forensics.io, forensics.sensor, forensics.prnu, forensics.defects, forensics.stats, "
            "forensics.validate; bad = [m for m in sys.modules if m.startswith(('forensics.report', 'matplotlib'))]; "
            "print(bad); sys.exit(1 if bad else 0)")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stdout + run.stderr


def test_growth_report_with_epochs(tmp_path):
    from forensics.defects.detection import MaskSpec, detect
    from forensics.defects.growth import Epoch, estimate_growth
    from forensics.io.stack import StackAccumulator

    rng = np.random.default_rng(0)
    epochs = []
    for k, year in enumerate((2000.0, 2004.0, 2008.0)):
        acc = StackAccumulator()
        for _ in range(12):
            frame = rng.normal(1000.0, 5.0, (40, 40))
            frame[5:5 + 3 * k:3, 20] += 90.0  # k defects by epoch k
            acc.add(frame.astype(np.float32))
        epochs.append(Epoch(year, detect(acc.result(), q=9, sigma=6.0, mask=MaskSpec("all"), threads=1), f"e{k}"))
    rep = growth_report(estimate_growth(epochs), epochs=epochs)
    assert isinstance(rep, Report)
    path = rep.write(tmp_path / "growth")
    names = sorted(p.name for p in path.parent.glob("*.png"))
    assert names == ["growth_counts.png", "histogram_0.png", "histogram_1.png", "histogram_2.png", "map_0.png",
                     "map_1.png", "map_2.png"]
    assert "Epoch 2008.00: e2" in path.read_text()
    det_page = detection_report(epochs[-1].detection, source="x").write(tmp_path / "det")
    assert (det_page.parent / "accumulated_histogram.png").exists()
