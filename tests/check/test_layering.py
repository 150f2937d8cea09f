"""Imports flow one way: the sensor model never imports the checker; the checker draws nothing."""
from __future__ import annotations

import subprocess
import sys


def _modules_after(statement: str) -> set[str]:
    code = f"import sys; {statement}; print('\\n'.join(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    return set(out.split())


def test_sensor_does_not_import_check_and_check_does_not_import_plotting():
    assert not any(m.startswith("forensics.check") for m in _modules_after("import forensics.sensor"))
    # every module of the checker, loaded explicitly (the package's public names load lazily)
    loaded = _modules_after("import importlib, pkgutil, forensics.sensor, forensics.check as c; "
                            "[importlib.import_module('forensics.check.' + m.name) for m in pkgutil.iter_modules(c.__path__)]")
    assert {"forensics.check.pipeline", "forensics.check.select", "forensics.check.structure"} <= loaded
    assert not any(m.startswith(("matplotlib", "forensics.report")) for m in loaded)


def test_evidence_satisfies_the_protocol_effects_see():
    from forensics.check.evidence import Evidence
    from forensics.check.signatures import SignatureContext
    from forensics.sensor.evidence import Evidence as EvidenceProtocol
    from forensics.sensor.evidence import SignatureEvidence

    for cls, protocol in ((Evidence, EvidenceProtocol), (SignatureContext, SignatureEvidence)):
        wanted = {n for n in dir(protocol) if not n.startswith("_")}
        assert wanted <= {n for n in dir(cls) if not n.startswith("_")} | {"shape"}, wanted
