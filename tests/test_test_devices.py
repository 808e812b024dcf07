"""The test run's devices are chosen once (clrf/testing/impls.py pin, from tests/conftest.py's
pytest_configure in the controller) and every process of the run reads that choice, so
pytest-xdist's workers collect the same tests even where two implementations measure alike."""
import json
import os
import subprocess
import sys

from clrf.testing import impls


def test_this_run_is_pinned():
    pinned = json.loads(os.environ[impls.PINNED_VAR])
    assert ":" in pinned["default"]
    d = impls.default_device()
    assert f"{d.platform_index}:{d.device_index}" == pinned["default"]


def test_a_child_reads_the_pinned_choice():
    """A process started with the variable set takes its devices from it and measures nothing:
    an implementation that is not here, and its slow verdict, come back as pinned."""
    default = json.loads(os.environ[impls.PINNED_VAR])["default"]
    pinned = {"default": default, "present": {"pocl": default, "nothere": default},
              "slow": {"nothere": True, "pocl": False}}
    code = ("import json; from clrf.testing import impls; d = impls.default_device(); "
            "print(json.dumps([impls.present(), impls.is_slow('nothere'), impls.is_slow('pocl'), "
            "f'{d.platform_index}:{d.device_index}', impls.pin()]))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env={**os.environ, impls.PINNED_VAR: json.dumps(pinned)})
    assert out.returncode == 0, out.stderr
    present, slow, fast, spec, again = json.loads(out.stdout.strip().splitlines()[-1])
    assert present == pinned["present"] and slow is True and fast is False
    assert spec == default and again == pinned
