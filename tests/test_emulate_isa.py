"""tools/emulate_isa.py: a tool run under it sees the older ISA's float width, and on PoCL a
device compiled for that ISA's LLVM CPU."""
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_usage_names_the_isas():
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "emulate_isa.py"), "avx9", "x.py"],
                       capture_output=True, text=True)
    assert r.returncode != 0 and "avx2" in r.stderr


def test_avx2_device(tmp_path, device):
    if "pocl" not in device.caps.platform_version.lower():
        pytest.skip("the ISA is chosen through PoCL's environment")
    script = tmp_path / "show.py"
    script.write_text("import clrf\nd = clrf.Device()\n"
                      "print(d.caps.native_float_width, d.caps.name)\n")
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "emulate_isa.py"), "avx2",
                        str(script)], capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert r.returncode == 0, r.stderr
    width, name = r.stdout.split(maxsplit=1)
    assert width == "8"
    assert "haswell" in name
