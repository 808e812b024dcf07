"""The test run's devices are chosen once (tests/conftest.py pytest_configure, with
clrf.testing.impls.choose) and handed to every pytest-xdist worker (impls.fix), so that all
workers collect the same tests even where two implementations measure alike."""
import json
import subprocess
import sys

from clrf.testing import impls


def test_this_run_uses_the_run_s_choice(request):
    chosen = request.config.clrf_devices
    assert ":" in chosen["default"]
    d = impls.default_device()
    assert f"{d.platform_index}:{d.device_index}" == chosen["default"]


def test_a_fixed_choice_is_taken_as_given(request):
    """A process given a choice (fix) takes its devices from it and measures nothing: an
    implementation that is not here, and its slow verdict, come back as given."""
    default = request.config.clrf_devices["default"]
    given = {"default": default, "present": {"pocl": default, "nothere": default},
             "slow": {"nothere": True, "pocl": False}}
    code = ("import json, sys; from clrf.testing import impls; "
            "impls.fix(json.loads(sys.argv[1])); d = impls.default_device(); "
            "print(json.dumps([impls.present(), impls.is_slow('nothere'), impls.is_slow('pocl'), "
            "f'{d.platform_index}:{d.device_index}', impls.choose()]))")
    out = subprocess.run([sys.executable, "-c", code, json.dumps(given)], capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    present, slow, fast, spec, again = json.loads(out.stdout.strip().splitlines()[-1])
    assert present == given["present"] and slow is True and fast is False
    assert spec == default and again == given
