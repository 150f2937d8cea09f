"""forensics: what an image sensor leaves in its images.

One subpackage per domain; each lists its public names in ``__all__``:

``forensics.io``        images, datasets (folder + manifest.csv), streaming stack statistics
``forensics.sensor``    the physical model: defect catalogue, effects, presets A–H, scenes, ageing simulation
``forensics.prnu``      residuals, fingerprints, NCC/PCE matching, same-device protocol, fingerprint ageing
``forensics.defects``   defect detection, onsets, growth rates, dating
``forensics.stats``     score statistics (ROC, EER, bootstrap), count statistics, spatial statistics
``forensics.check``     the sensor model against measurements: fit, goodness of fit, missing effects
``forensics.validate``  estimators against simulated truth
``forensics.report``    the HTML report writer and one module of figures per domain
``forensics.demo``      ``forensics demo``
``forensics.cli``       the ``forensics`` command (source in ``cli/``)
``forensics.fixtures``  generators of synthetic test data (source in ``fixtures/``)

Subpackages are imported on demand (``import forensics.prnu``); importing ``forensics`` alone is cheap.
"""
__version__ = "0.1.0"
__all__ = ["__version__"]
