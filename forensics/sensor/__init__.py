"""The physical sensor model: defect catalogue, effects, presets A–H, scenes and the ageing simulation.

One model serves both simulation and fitting.  A :class:`SensorModel` is an image size, a bit depth and a
list of :class:`Effect` objects applied in physical order (:class:`Stage`); :meth:`SensorModel.realize`
draws one :class:`Device` (one defect history, its fixed patterns), whose :meth:`Device.expose` forms
frames.  Importing this package registers the built-in effects, so :func:`make_effect` knows them.
"""
from forensics.sensor.catalogue import KIND_CODES, KIND_NAMES, PARTIAL, STUCK, DefectCatalogue
from forensics.sensor.model import (
    EFFECTS,
    Device,
    Effect,
    FrameContext,
    Pattern,
    SensorModel,
    Stage,
    load_model,
    make_effect,
    param,
    register_effect,
)
from forensics.sensor.effects import (  # noqa: E402  (registers the built-in effects)
    AcceleratingGrowth,
    Clusters,
    DarkCurrent,
    Dsnu,
    Gain,
    Growth,
    Nonlinearity,
    Offset,
    Prnu,
    ReadNoise,
    ShotNoise,
    Stuck,
    describe_effects,
)
from forensics.sensor.presets import PRESETS, preset
from forensics.sensor.scenes import pink_texture, scene, scene_image
from forensics.sensor.simulate import AgeingResult, age_dataset, make_scenes, parse_years, read_catalogue, write_catalogue

__all__ = [
    "PARTIAL", "STUCK", "KIND_NAMES", "KIND_CODES", "DefectCatalogue",
    "Stage", "Effect", "Pattern", "FrameContext", "param", "EFFECTS", "register_effect", "make_effect",
    "SensorModel", "Device", "load_model",
    "Growth", "Offset", "Stuck", "ReadNoise", "Prnu", "Dsnu", "DarkCurrent", "Gain", "Nonlinearity", "ShotNoise",
    "Clusters", "AcceleratingGrowth", "describe_effects",
    "PRESETS", "preset",
    "scene", "scene_image", "pink_texture",
    "age_dataset", "AgeingResult", "parse_years", "make_scenes", "read_catalogue", "write_catalogue",
]
