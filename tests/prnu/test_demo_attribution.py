"""The demo's attribution section: cluster an anonymous collection, build a database from the clusters,
identify new images against it.

Its simulated cameras have PRNU σ = 1 % on 240×320 smooth scenes: matching images reach PCE in the hundreds
(crops ≈ 450–900, whole and turned images ≈ 1,100–1,800, seed 0) against thresholds of about 30, and the
clustering's merge threshold sits far below the pair z of one camera, so anything but a perfect result is a
bug, not noise.
"""
from __future__ import annotations

from forensics._shared.parallel import Executor
from forensics._shared.progress import no_progress
from forensics.demo import attribution


def test_attribution_demo_recovers_the_cameras(tmp_path):
    # on worker processes, as `forensics demo` runs it (they read every query from its file)
    with Executor("processes", workers=2) as executor:
        section = attribution.run(tmp_path, 0, no_progress, executor)
    data = section.data
    assert data["images"] == attribution.CAMERAS * attribution.PER_CAMERA + attribution.STRANGERS
    assert data["clusters"] == attribution.CAMERAS
    assert data["unattributed"] == attribution.STRANGERS  # the single images of other cameras match nothing
    assert data["ari"] == 1.0 and data["purity"] == 1.0
    assert data["identified"] == data["known_queries"] == 3 * attribution.CAMERAS
    assert data["false_attributions"] == 0
    kinds = {q["kind"] for q in data["queries"]}
    assert kinds == {"whole", "crop", "turned 90°", "unseen camera"}
    assert len(section.summary) == 2 and "ARI 1.000" in section.summary[0]
