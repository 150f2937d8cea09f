"""Model against measurement: fit the sensor model, show where it fails, name the missing effect.

:func:`check` takes a dataset (images + ``manifest.csv``) and a model (the base model — ``growth``,
``offset``, ``stuck``, ``read_noise`` and saturation at the bit depth — plus any added effects), and returns
a :class:`CheckResult`: the fitted parameters, the held-out error, goodness-of-fit p-values, a table of
checks, and the candidate effects ranked by how much adding each would improve the fit.

The stages, one module each, data flowing one way:

``measurements``  frames → per-condition stack statistics (:class:`Measurements`); ``scene`` the
                  leave-one-out quadratic scene estimate
``detection``     stuck and partially stuck pixels per epoch (onsets: :mod:`forensics.defects.onsets`)
``evidence``      what models are fitted to (:class:`Evidence`): ``arrivals`` (counts, sites, the arrival
                  model's predictions), ``pixels`` (pixel classes, scene estimates, noise floor, variance
                  bins), ``singles`` (single dark frames: their noise law, cosmic-ray hits, misfits),
                  ``reduced`` (light frames dark-subtracted before the check, named),
                  ``prediction`` (forward models), ``streams`` (Monte-Carlo streams)
``fit``           :func:`fit_model` → :class:`FittedModel` (``pixelfit``; the solvers ``local_solve`` and
                  ``joint_solve``; ``identifiability``; ``params``: new effects, never mutated ones)
``gof``           held-out error per pixel class and each channel's goodness of fit
``diagnosis``     ``signatures`` and ``scoretests`` of the candidates, ranking and flags;
                  ``frame_advice``: which frames would show what the data cannot
``structure``     residual structure no fitted effect explains: row, column and radial profiles and
                  covariate trends of the residual, each tested against noise; the strongest named
                  (:func:`residual_structure` → :class:`StructureResult`)
``result``        the result dataclasses (``to_dict()`` for ``--json``); ``darkfigures`` a dark series' fitted
                  law in ADU, ADU/s and e⁻/ADU with intervals (:func:`dark_figures`)
``pipeline``      :func:`check`, :func:`run_check`, :func:`base_model`, :func:`candidate_names`
``tiles``         the whole frame in tiles of bounded memory, combined by their information
                  (:func:`check_tiles` → :class:`TiledCheck`)
``select``        forward selection of several effects: :func:`check_auto`, :func:`forward_select` →
                  :class:`SelectionResult` (the path base → +A → +B …)

The measurements are reduced to four *channels* of statistics — pixel, variance, growth, spatial — and
every effect acts on one or more of them according to its :class:`~forensics.sensor.model.Stage`, so
nothing here depends on an effect's name.  The report is :func:`forensics.report.check.check_report`.
"""
import lazy_loader as _lazy

# Public names load their module on first use (as in scikit-image), so that importing one module of
# this package does not import the whole domain.
__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    submod_attrs={
        "classes": ["CHANNELS", "CLASSES"],
        "darkfigures": ["dark_figures"],
        "diagnosis": ["FLAG_DBIC", "FLAG_P", "diagnose"],
        "evidence": ["Evidence"],
        "fit": ["FittedModel", "fit_model"],
        "measurements": ["Group", "Measurements", "load_measurements"],
        "result": [
            "Candidate", "ChannelTest", "CheckResult", "CheckRow", "ParamEstimate", "PatternEstimate", "PlotData",
            "StructureResult", "StructureTest",
        ],
        "pipeline": ["base_model", "candidate_names", "check", "resolve_effects", "run_check"],
        "scene": ["KERNEL", "KERNEL_VAR", "loo_quadratic_kernel", "scene_estimate"],
        "select": ["Attempt", "SelectionResult", "Step", "check_auto", "forward_select"],
        "structure": ["residual_structure"],
        "tiles": ["TiledCheck", "TiledParam", "UncombinedParam", "check_tiles", "combine", "tile_grid"],
        "signatures": ["Signature"],
        "singles": ["SingleFrames", "single_frames"],
    },
)
