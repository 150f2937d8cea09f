"""``forensics impact`` and ``forensics simulate irises`` from the command line."""
from __future__ import annotations

import json
import textwrap

import numpy as np

from forensics.io.dataset import open_dataset, write_manifest
from forensics.io.images import write_image

# A user's matcher in one small file: normalised correlation of 8×8 block means.
USER_MATCHER = textwrap.dedent('''
    """A user's own matcher: correlation of 8×8 block means (higher = more similar)."""
    import numpy as np


    class BlockCorrelation:
        name = "blocks"
        higher_is_similar = True

        def encode(self, image):
            image = np.asarray(image, dtype=np.float64)
            if image.ndim == 3:
                image = image.mean(axis=2)
            h, w = (image.shape[0] // 8) * 8, (image.shape[1] // 8) * 8
            blocks = image[:h, :w].reshape(h // 8, 8, w // 8, 8).mean(axis=(1, 3)).ravel()
            blocks = blocks - blocks.mean()
            return blocks / (np.linalg.norm(blocks) or 1.0)

        def compare(self, a, b):
            return float(np.dot(a, b))
''')


def _labelled_set(root, classes=6, samples=3, subjects=True):
    rng = np.random.default_rng(0)
    root.mkdir()
    rows = []
    for c in range(classes):
        base = rng.normal(128, 30, (32, 48))
        for s in range(samples):
            name = f"{c}_{s}.png"
            write_image(root / name, np.clip(base + rng.normal(0, 40, base.shape), 0, 255).astype(np.uint8))
            rows.append({"file": name, "subject": f"eye{c}" if subjects else ""})
    write_manifest(root / "manifest.csv", rows)
    return root


def test_user_matcher_file_runs_through_impact_with_json_and_report(cli, tmp_path):
    assert len(USER_MATCHER.strip().splitlines()) <= 30
    matcher = tmp_path / "my_matcher.py"
    matcher.write_text(USER_MATCHER)
    src = _labelled_set(tmp_path / "src")
    code, out, err = cli("impact", src, "--sensors", "A,H*500", "--years", "0,48,96", "--matcher",
                         f"{matcher}:BlockCorrelation", "--boot", "200", "--seed", "3", "--json",
                         "--report", tmp_path / "rep")
    assert code == 0, err
    result = json.loads(out)
    assert result["matchers"] == ["blocks"] and set(result["protocols"]) == {"same-age", "enrol-0"}
    assert len(result["units"]) == 2 * 3 * 2  # sensors × ages × protocols
    assert result["n_genuine"] == 6 * 3 and result["n_impostor"] == 18 * 17 // 2 - 18
    for unit in result["units"]:
        assert unit["ci"][0] <= unit["eer"] <= unit["ci"][1] and unit["resampled"] == "classes"
    assert {t["sensor"] for t in result["trends"]} == {"A", "H×500"}
    page = (tmp_path / "rep" / "index.html").read_text()
    assert "figure 6" in page and "same-age" in page and "enrol-0" in page
    assert len(list((tmp_path / "rep").glob("*.png"))) >= 4
    # The readable summary names the protocol and the trend verdict.
    code, out, _ = cli("impact", src, "--sensors", "A", "--years", "0,96", "--matcher", f"{matcher}:BlockCorrelation",
                       "--boot", "200", "--protocol", "same-age", "--quiet")
    assert code == 0 and "protocol same-age" in out and "trend" in out


def test_bad_input_and_usage_exit_codes(cli, tmp_path):
    unlabelled = _labelled_set(tmp_path / "unlabelled", subjects=False)
    code, _, err = cli("impact", unlabelled, "--sensors", "A", "--years", "0", "--boot", "200", "--quiet")
    assert code == 3 and "subject" in err and len(err.strip().splitlines()) == 1
    src = _labelled_set(tmp_path / "src")
    assert cli("impact", src, "--boot", "10")[0] == 2
    code, _, err = cli("impact", src, "--matcher", "nosuch", "--quiet")
    assert code == 2 and "matcher" in err
    code, _, err = cli("impact", src, "--sensors", "Q")
    assert code == 2 and "sensors" in err
    code, _, err = cli("impact", src, "--years", "8,16", "--matcher", "masek")
    assert code == 2 and "age 0" in err


def test_simulate_irises_writes_a_labelled_dataset(cli, tmp_path):
    code, out, err = cli("simulate", "irises", tmp_path / "ir", "--classes", "4", "--samples", "2", "--seed", "1",
                         "--json")
    assert code == 0, err
    ds = open_dataset(tmp_path / "ir")
    assert len(ds) == 8 and len({f.subject for f in ds.frames}) == 4
    image = ds.frames[0].load()
    assert image.dtype == np.uint8 and image.shape == (240, 320)
    assert cli("simulate", "irises", tmp_path / "ir", "--classes", "4", "--samples", "2")[0] != 0  # never overwrites


def test_workers_change_nothing_but_the_execution_record(cli, tmp_path):
    matcher = tmp_path / "my_matcher.py"
    matcher.write_text(USER_MATCHER)
    src = _labelled_set(tmp_path / "src")
    runs = {}
    for workers in ("1", "2"):
        code, out, err = cli("impact", src, "--sensors", "B,H*500", "--years", "0,96", "--matcher",
                             f"{matcher}:BlockCorrelation", "--boot", "200", "--seed", "4", "--workers", workers,
                             "--allow-outside", "--json")
        assert code == 0, err
        runs[workers] = json.loads(out)
    assert runs["1"]["execution"]["backend"] == "in-process"
    assert runs["2"]["execution"] == {"backend": "processes", "workers": 2, "scheduler": None, "dashboard": None}
    for run in runs.values():
        for key in ("execution", "elapsed_s"):
            run.pop(key)
    assert runs["1"] == runs["2"]
    assert cli("impact", src, "--workers", "0", "--quiet")[0] == 2


def test_checkpoint_resumes_and_refuses_other_settings(cli, tmp_path):
    matcher = tmp_path / "my_matcher.py"
    matcher.write_text(USER_MATCHER)
    src = _labelled_set(tmp_path / "src")
    base = ("impact", src, "--sensors", "A,H*500", "--years", "0,48", "--matcher", f"{matcher}:BlockCorrelation",
            "--boot", "200", "--checkpoint", tmp_path / "ck", "--json")
    first, again = (cli(*base, "--seed", "2") for _ in range(2))
    assert first[0] == again[0] == 0, first[2] + again[2]
    one, two = json.loads(first[1]), json.loads(again[1])
    # Everything from the checkpoint: the computed units resumed, the others reused from identical aged images
    # (A's and H×500's age 0 are both the source images), as in the first run.
    assert one["resumed_units"] == 0 and two["reused_units"] == one["reused_units"] > 0
    assert two["resumed_units"] + two["reused_units"] == 2 * 2 * 2
    assert one["units"] == two["units"] and one["trends"] == two["trends"] and one["spreads"] == two["spreads"]
    code, _, err = cli(*base, "--seed", "3")
    assert code == 2 and "other settings" in err
