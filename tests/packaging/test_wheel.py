"""The built wheel installs one top-level import name, `intercap`, and carries every module of
the repository's package folders (intercap/, body_models/ -> intercap.body_models, calib/ -> intercap.calib)."""
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def wheel_names(tmp_path_factory) -> set[str]:
    out = tmp_path_factory.mktemp("wheel")
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(out), str(ROOT)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0 and "No module named" in done.stderr:
        pytest.skip(f"cannot build a wheel here: {done.stderr.strip().splitlines()[-1]}")
    assert done.returncode == 0, done.stderr
    (wheel,) = out.glob("intercap-*.whl")
    return set(zipfile.ZipFile(wheel).namelist())


def test_only_top_level_import_name_is_intercap(wheel_names):
    top = {name.split("/")[0] for name in wheel_names if not name.split("/")[0].endswith((".dist-info", ".data"))}
    assert top == {"intercap"}
    assert not any(name.startswith(("tools/", "calib/", "body_models/", "tests/")) for name in wheel_names)


def test_every_module_and_shipped_file_is_in_the_wheel(wheel_names):
    expected = set()
    for folder, target in (("intercap", "intercap"), ("body_models", "intercap/body_models"), ("calib", "intercap/calib")):
        for path in (ROOT / folder).rglob("*.py"):
            expected.add(f"{target}/{path.relative_to(ROOT / folder).as_posix()}")
    expected |= {f"intercap/data/{p.name}" for p in (ROOT / "intercap" / "data").glob("*.npz")}
    expected |= {f"intercap/calib/rigs/{p.name}" for p in (ROOT / "calib" / "rigs").glob("*.json")}
    missing = sorted(expected - wheel_names)
    assert not missing, f"setup.cfg does not package: {missing[:10]}"
