"""PRNU on real cameras: four Nikon devices of the Dresden Image Database (two D70, two D70s).

Fingerprints come from each device's 10 flat-field JPEGs; every natural image is
scored against every fingerprint by zero-shift PCE on the 1024×1024 centre crop.
Two devices of the same model are the hard case: only the device's own PRNU
tells them apart.

Reference (data README, public NumPy implementation, same protocol, 1024 crops):
all matching and non-matching pairs separate, the highest non-matching PCE is
about 11, most matching pairs exceed 60.

Skipped when ``../shared/data/dresden-nikon`` (beside the repository) is absent.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from forensics.prnu.fingerprint import Fingerprint, FingerprintBuilder
from forensics.prnu.match import PCE_THRESHOLD, score_matrix

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "dresden-nikon"
REGION = "center:1024"

pytestmark = [
    pytest.mark.realdata,
    pytest.mark.skipif(not (DATA / "flat").is_dir(), reason=f"real-camera data not found at {DATA}"),
]


def device_of(path: Path) -> str:
    """``MODEL_DEVICEINDEX_NUMBER.JPG`` → ``MODEL_DEVICEINDEX``."""
    return path.stem.rsplit("_", 1)[0]


def read(path: Path) -> np.ndarray:
    """Pixels as stored (no EXIF rotation), native dtype."""
    try:
        from forensics.io.images import read_image
    except ImportError:  # pragma: no cover - before forensics.io.images existed
        import OpenImageIO as oiio

        return oiio.ImageBuf(str(path)).get_pixels(oiio.UINT8)
    return read_image(path)


@pytest.fixture(scope="module")
def fingerprints() -> dict[str, Fingerprint]:
    flats = sorted((DATA / "flat").glob("*.JPG"))
    by_device: dict[str, list[Path]] = {}
    for path in flats:
        by_device.setdefault(device_of(path), []).append(path)
    result = {}
    for device, paths in sorted(by_device.items()):
        builder = FingerprintBuilder(region=REGION, sigma=3.0)
        for path in paths:
            builder.add(read(path), source=path.name)
        result[device] = builder.result()
    return result


@pytest.fixture(scope="module")
def scores(fingerprints) -> tuple[np.ndarray, list[str], list[str]]:
    naturals = sorted((DATA / "natural").glob("*.JPG"))
    devices = list(fingerprints)
    # 'auto' rotations: a portrait-stored frame (2000 wide, 3008 high) is turned both
    # ways and the better orientation kept; landscape frames are used as they are.
    matrix = score_matrix([fingerprints[d] for d in devices], (read(p) for p in naturals), metric="pce")
    return matrix, devices, [device_of(p) for p in naturals]


def test_dataset_layout(fingerprints):
    assert len(fingerprints) == 4
    for fp in fingerprints.values():
        assert fp.n_images == 10 and fp.K.shape == (1024, 1024) and fp.frame_shape == (2000, 3008)


def test_each_natural_image_is_attributed_to_its_camera(scores):
    matrix, devices, truth = scores
    predicted = [devices[j] for j in np.argmax(matrix, axis=0)]
    assert predicted == truth


def test_no_non_matching_pair_reaches_the_threshold(scores):
    matrix, devices, truth = scores
    genuine = np.array([[d == t for t in truth] for d in devices])
    impostor = matrix[~genuine]
    assert impostor.max() < PCE_THRESHOLD
    # and, as with the reference implementation, the two sets separate completely
    assert matrix[genuine].min() > impostor.max()


def test_most_matching_pairs_exceed_the_threshold(scores):
    matrix, devices, truth = scores
    genuine = matrix[np.array([[d == t for t in truth] for d in devices])]
    assert np.mean(genuine > PCE_THRESHOLD) > 0.5


def _report(regions: tuple[str, ...] = ("center:512", "center:1024")) -> None:  # pragma: no cover - manual
    """Print the score matrices and separation figures (``python tests/test_prnu_realdata.py``)."""
    import time

    if not (DATA / "flat").is_dir():
        print(f"real-camera data not found at {DATA}")
        return
    flats = sorted((DATA / "flat").glob("*.JPG"))
    naturals = sorted((DATA / "natural").glob("*.JPG"))
    devices = sorted({device_of(p) for p in flats})
    for region in regions:
        t0 = time.perf_counter()
        fps = []
        for device in devices:
            builder = FingerprintBuilder(region=region)
            for path in flats:
                if device_of(path) == device:
                    builder.add(read(path), source=path.name)
            fps.append(builder.result())
        t1 = time.perf_counter()
        matrix = score_matrix(fps, (read(p) for p in naturals))
        t2 = time.perf_counter()
        truth = [device_of(p) for p in naturals]
        genuine_mask = np.array([[d == t for t in truth] for d in devices])
        g, i = matrix[genuine_mask], matrix[~genuine_mask]
        auc = (np.sum(g[:, None] > i[None, :]) + 0.5 * np.sum(g[:, None] == i[None, :])) / (g.size * i.size)
        print(f"\n## {region}: fingerprints {t1 - t0:.1f} s (40 flats), scoring {t2 - t1:.1f} s (14 images x 4)")
        print("| natural image | " + " | ".join(devices) + " |")
        print("|---|" + "---|" * len(devices))
        for j, path in enumerate(naturals):
            cells = [f"**{v:.1f}**" if d == truth[j] else f"{v:.1f}" for d, v in zip(devices, matrix[:, j])]
            print(f"| {path.name} | " + " | ".join(cells) + " |")
        attributed = np.mean([devices[k] == t for k, t in zip(np.argmax(matrix, axis=0), truth)])
        print(f"\nAUC {auc:.3f}; attributed correctly {attributed:.0%}; matching min {g.min():.1f}, "
              f"median {np.median(g):.1f}, > 60: {np.sum(g > 60)}/{g.size}; non-matching max {i.max():.1f}")


if __name__ == "__main__":  # pragma: no cover
    _report()
