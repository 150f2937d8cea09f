"""The physical sensor model: defect catalogue, effects, presets A–H, scenes and the ageing simulation.

One model serves both simulation and fitting.  A :class:`SensorModel` is an image size, a bit depth and a
list of :class:`Effect` objects applied in physical order (:class:`Stage`); :meth:`SensorModel.realize`
draws one :class:`Device` (one defect history, its fixed patterns), whose :meth:`Device.expose` forms
frames.  Importing this package registers the built-in effects, so :func:`make_effect` knows them.
"""
import lazy_loader as _lazy

# Public names load their module on first use (as in scikit-image), so that importing one module of
# this package does not import the whole domain.
__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    submod_attrs={
        "catalogue": ["KIND_CODES", "KIND_NAMES", "PARTIAL", "STUCK", "DefectCatalogue"],
        "model": [
            "EFFECTS", "Device", "Effect", "FrameContext", "Pattern", "SensorModel", "Stage", "load_model",
            "make_effect", "param", "register_effect",
        ],
        "effects": [
            "AcceleratingGrowth", "Clusters", "DarkCurrent", "Dsnu", "Gain", "Growth", "Nonlinearity", "Offset",
            "Prnu", "ReadNoise", "ShotNoise", "Stuck", "describe_effects",
        ],
        "presets": ["PRESETS", "preset"],
        "scenes": ["pink_texture", "scene", "scene_image"],
        "simulate": [
            "AgeingResult", "age_dataset", "aged_exposures", "check_ageing_request", "expected_arrivals", "make_scenes",
            "parse_years", "read_catalogue", "write_catalogue",
        ],
    },
)

from forensics.sensor import effects as _effects  # noqa: E402,F401  (registers the built-in effects)
