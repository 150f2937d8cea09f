"""Importing one module of a domain does not import the whole domain (public names load lazily)."""
import subprocess
import sys


def test_fingerprint_does_not_load_the_same_device_statistics():
    code = ("import sys, forensics.prnu.fingerprint, forensics.prnu as p; "
            "assert 'forensics.prnu.samedevice' not in sys.modules, 'eager'; "
            "assert 'scipy.stats' not in sys.modules, 'scipy.stats'; "
            "p.same_device; assert 'forensics.prnu.samedevice' in sys.modules")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-1500:]


# Every package's listing is checked by tests/packaging/test_public_listing.py (all packages, discovered).
