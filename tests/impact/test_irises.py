"""Synthetic NIR iris images: texture, rendering geometry and levels, class separability, data sets."""
from __future__ import annotations

import csv
import dataclasses

import numpy as np
import pytest
from scipy import ndimage

from forensics._shared.errors import UsageError
from forensics._shared.rng import keyed_generator
from forensics.impact.irises import (
    IrisTruth,
    IrisVariation,
    iris_texture,
    render_iris,
    simulate_irises,
)
from forensics.io.dataset import open_dataset
from forensics.io.images import read_image

#: Everything that is not the iris itself switched off (for testing the warp in isolation).
CLEAN = IrisVariation(iris_radius_jitter=0.0, deformation_radial=0.0, deformation_angular_deg=0.0,
                      poor_probability=0.0, centre_jitter=0.0, pupil_offset=0.0, rotation_std_deg=0.0,
                      blur_sigma=(0.5, 0.5), gain=(1.0, 1.0), gradient=0.0, vignetting=0.0, upper_lid=(0.0, 0.0),
                      lower_lid_probability=0.0, eyelashes=(0, 0), specular_count=(0, 0), noise_std=0.0,
                      level_jitter=0.0)


def unwrap(image: np.ndarray, truth: IrisTruth, u=(0.15, 0.7), degrees=(30.0, 150.0),
           shape=(16, 256)) -> np.ndarray:
    """Daugman's rubber sheet from the truth circles over the lower iris (y points down: 90° is the bottom),
    which eyelids and lashes leave visible; each row's mean is removed."""
    radius = np.linspace(*u, shape[0])[:, None]
    theta = np.radians(np.linspace(*degrees, shape[1]))[None, :]
    xs = (1 - radius) * (truth.pupil_x + truth.pupil_r * np.cos(theta)) + radius * (truth.iris_x + truth.iris_r * np.cos(theta))
    ys = (1 - radius) * (truth.pupil_y + truth.pupil_r * np.sin(theta)) + radius * (truth.iris_y + truth.iris_r * np.sin(theta))
    band = ndimage.map_coordinates(image.astype(float), [ys, xs], order=1)
    return band - band.mean(axis=1, keepdims=True)


def similarity(a: np.ndarray, b: np.ndarray, shifts: int = 14) -> float:
    """The best correlation of two unwrapped bands over angular shifts (rotation), on their common columns."""
    best = -1.0
    for s in range(-shifts, shifts + 1):
        x = a[:, max(s, 0): a.shape[1] + min(s, 0)]
        y = b[:, max(-s, 0): b.shape[1] + min(-s, 0)]
        best = max(best, float(np.corrcoef(x.ravel(), y.ravel())[0, 1]))
    return best


def eye_open(truth: IrisTruth, x: np.ndarray, y: np.ndarray, margin: float = 4.0) -> np.ndarray:
    upper = truth.upper_lid_y + truth.upper_lid_k * (x - truth.lid_x) ** 2
    lower = truth.lower_lid_y - truth.lower_lid_k * (x - truth.lid_x) ** 2
    return (y > upper + margin) & (y < lower - margin)


@pytest.fixture(scope="module")
def renders():
    """3 classes × 3 samples with the default variation: (class, image, truth)."""
    out = []
    for k in range(3):
        class_rng = keyed_generator(21, k)
        texture = iris_texture(class_rng)
        iris_r = float(class_rng.uniform(90, 110))
        for s in range(3):
            image, truth = render_iris(texture, keyed_generator(21, k, s + 1), iris_r=iris_r)
            out.append((k, image, truth))
    return out


def test_texture_is_normalised_periodic_radial_and_seeded():
    tex = iris_texture(np.random.default_rng(3))
    assert tex.shape == (64, 512) and tex.dtype == np.float32
    assert abs(tex.mean()) < 1e-4 and tex.std() == pytest.approx(1.0, abs=1e-3)
    step_angle = np.abs(np.diff(tex, axis=1)).mean()
    assert np.abs(tex[:, 0] - tex[:, -1]).mean() < 1.5 * step_angle  # column 511 neighbours column 0
    # fibres and crypts are elongated along the radius: a row step (1/63 of the band, ≈ 1 px) changes the
    # pattern less than a column step (0.7°, ≈ 0.8 px at mid-iris), and it stays correlated further
    ratios, margins = [], []
    for seed in range(5):
        t = iris_texture(seed)
        ratios.append(np.abs(np.diff(t, axis=0)).mean() / np.abs(np.diff(t, axis=1)).mean())
        margins.append(np.corrcoef(t[4:].ravel(), t[:-4].ravel())[0, 1]
                       - np.corrcoef(np.roll(t, 4, axis=1).ravel(), t.ravel())[0, 1])
    assert np.mean(ratios) < 0.8 and np.mean(margins) > 0.05
    assert np.array_equal(tex, iris_texture(3))
    other = iris_texture(4)
    assert abs(np.corrcoef(tex.ravel(), other.ravel())[0, 1]) < 0.3
    assert iris_texture(5, shape=(32, 256)).shape == (32, 256)


def test_images_have_the_iitd_format_and_levels(renders):
    y, x = np.mgrid[0:240, 0:320]
    in_pupil, spots = 0, 0
    for _, image, truth in renders:
        assert image.dtype == np.uint8 and image.shape == (240, 320)
        assert image.max() == 255 and image.min() < 40  # saturated speculars, dark pupil and lashes
        seen = eye_open(truth, x, y)
        to_pupil = np.hypot(x - truth.pupil_x, y - truth.pupil_y)
        to_iris = np.hypot(x - truth.iris_x, y - truth.iris_y)
        pupil = np.median(image[seen & (to_pupil < truth.pupil_r - 3)])
        iris = np.median(image[seen & (to_pupil > truth.pupil_r + 4) & (to_iris < truth.iris_r - 4)])
        sclera = np.median(image[seen & (to_iris > truth.iris_r + 6)])
        assert 10 <= pupil <= 45 and 70 <= iris <= 150 and 130 <= sclera <= 230
        assert pupil + 30 < iris < sclera - 20
        labels, count = ndimage.label(image == 255)
        centres = np.array(ndimage.center_of_mass(image == 255, labels, range(1, count + 1)))
        spots += count
        in_pupil += int(np.sum(np.hypot(centres[:, 1] - truth.pupil_x, centres[:, 0] - truth.pupil_y) < truth.pupil_r))
    assert in_pupil >= 0.6 * spots  # NIR illuminator reflections, mostly in the pupil


def test_truth_circles_lie_in_the_image_within_the_documented_ranges(renders):
    v = IrisVariation()
    for _, _, truth in renders:
        for cx, cy, r in ((truth.pupil_x, truth.pupil_y, truth.pupil_r), (truth.iris_x, truth.iris_y, truth.iris_r)):
            assert r <= cx <= 319 - r and r <= cy <= 239 - r
        assert v.pupil_radius[0] <= truth.pupil_r <= v.pupil_radius[1]
        assert 90 - 5 <= truth.iris_r <= 110 + 5
        assert np.hypot(truth.pupil_x - truth.iris_x, truth.pupil_y - truth.iris_y) + truth.pupil_r < truth.iris_r
        assert abs(truth.iris_x - 159.5) <= 15 and abs(truth.iris_y - 119.5) <= 15
        assert abs(truth.rotation_deg) <= 8 and truth.dilation == pytest.approx(truth.pupil_r / truth.iris_r)
        assert 0 <= truth.occlusion <= 1 and set(truth.to_dict()) == {f.name for f in dataclasses.fields(IrisTruth)}
    # the class fixes the limbus (± a little); the pupil changes from sample to sample
    by_class = {k: [t for c, _, t in renders if c == k] for k in range(3)}
    for truths in by_class.values():
        assert np.ptp([t.iris_r for t in truths]) < 10 and np.ptp([t.pupil_r for t in truths]) > 1


def test_rendering_is_deterministic_for_a_seed():
    tex = iris_texture(8)
    a, ta = render_iris(tex, 5, iris_r=100.0)
    b, tb = render_iris(tex, np.random.default_rng(5), iris_r=100.0)
    c, tc = render_iris(tex, 6, iris_r=100.0)
    assert np.array_equal(a, b) and ta == tb
    assert not np.array_equal(a, c) and ta != tc


def test_samples_of_a_class_are_more_alike_than_samples_of_different_classes(renders):
    bands = [(k, unwrap(image, truth)) for k, image, truth in renders]
    genuine, impostor = [], []
    for i, (ki, a) in enumerate(bands):
        for kj, b in bands[i + 1:]:
            (genuine if ki == kj else impostor).append(similarity(a, b))
    assert len(genuine) == 9 and len(impostor) == 27
    assert np.mean(genuine) > np.mean(impostor) + 0.25
    assert np.mean(np.array(genuine)[:, None] > np.array(impostor)[None, :]) > 0.85  # AUC
    assert max(genuine) < 0.99  # but not identical: acquisitions vary


def test_dilation_warp_is_not_undone_by_a_linear_rubber_sheet():
    tex = iris_texture(12)

    def band(pupil: float, warp: float) -> np.ndarray:
        v = dataclasses.replace(CLEAN, pupil_radius=(pupil, pupil), dilation_warp=warp)
        image, truth = render_iris(tex, 0, variation=v, iris_r=100.0)
        return unwrap(image, truth, u=(0.1, 0.9), degrees=(0.0, 359.0), shape=(24, 360))

    linear = similarity(band(24.0, 0.0), band(44.0, 0.0), shifts=0)
    warped = similarity(band(24.0, 2.0), band(44.0, 2.0), shifts=0)
    assert linear > 0.85 and warped < linear - 0.1


def test_simulated_set_is_a_dataset_with_truth_and_keyed_streams(tmp_path):
    result = simulate_irises(tmp_path / "four", classes=4, samples=2, rng=7)
    assert result.n_images == 8 and result.subjects == ["001_L", "001_R", "002_L", "002_R"]
    assert result.to_dict()["seed"] == 7
    dataset = open_dataset(tmp_path / "four")
    assert [f.file for f in dataset] == [f"{s}_{i:02d}.png" for s in result.subjects for i in range(2)]
    assert [f.subject for f in dataset] == [s for s in result.subjects for _ in range(2)]
    assert all(f.device is None for f in dataset)
    with open(tmp_path / "four" / "manifest.csv", newline="") as handle:
        header = next(csv.reader(handle))
    assert header[:3] == ["file", "device", "subject"]
    with open(tmp_path / "four" / "truth.csv", newline="") as handle:
        truth_rows = list(csv.DictReader(handle))
    assert list(truth_rows[0]) == ["file", "subject", *(f.name for f in dataclasses.fields(IrisTruth))]
    assert [r["file"] for r in truth_rows] == [f.file for f in dataset]
    image = read_image(tmp_path / "four" / "002_R_01.png")
    assert image.dtype == np.uint8 and image.shape == (240, 320)

    two = simulate_irises(tmp_path / "two", classes=2, samples=2, rng=np.random.default_rng(7))
    assert two.subjects == ["001_L", "001_R"]
    for name in ("001_L_00.png", "001_L_01.png", "001_R_00.png", "001_R_01.png"):
        assert np.array_equal(read_image(tmp_path / "two" / name), read_image(tmp_path / "four" / name))
    assert not np.array_equal(read_image(tmp_path / "two" / "001_L_00.png"),
                              read_image(tmp_path / "two" / "001_L_01.png"))


def test_existing_output_is_refused_without_force_and_failures_leave_nothing(tmp_path):
    out = tmp_path / "set"
    out.mkdir()
    with pytest.raises(UsageError, match="already exists"):
        simulate_irises(out, classes=2, samples=2, rng=1)
    simulate_irises(out, classes=2, samples=2, rng=1, force=True)
    assert len(open_dataset(out)) == 4

    def interrupted(items, total=None, desc=None):
        yield next(iter(items))
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        simulate_irises(tmp_path / "broken", classes=3, samples=2, rng=1, progress=interrupted)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["set"]


@pytest.mark.parametrize("kwargs", [{"classes": 1}, {"samples": 1}, {"classes": 2.5}, {"size": (120, 160)}])
def test_bad_arguments_raise_usage_errors(tmp_path, kwargs):
    args = {"classes": 2, "samples": 2, **kwargs}
    with pytest.raises(UsageError) as info:
        simulate_irises(tmp_path / "out", rng=0, **args)
    assert "\n" not in str(info.value)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("kwargs", [{"pupil_radius": (40.0, 30.0)}, {"pupil_radius": (20.0, 90.0)},
                                    {"dilation_warp": 9.0}, {"noise_std": -1.0}, {"poor_probability": 2.0}])
def test_inconsistent_variations_are_refused(kwargs):
    with pytest.raises(UsageError):
        IrisVariation(**kwargs)
