"""Shared set-up of the Python API tests (run by .ci/run in a fresh venv with the wheel).

KFMC_BIN names the command built by cargo (the reference the API is compared with); by
default target/release/kfmc of this checkout, or $CARGO_TARGET_DIR/release/kfmc.
"""

import os
import pathlib
import shutil

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]


def _kfmc_bin() -> str:
    if os.environ.get("KFMC_BIN"):
        return os.environ["KFMC_BIN"]
    target = os.environ.get("CARGO_TARGET_DIR", str(ROOT / "target"))
    return str(pathlib.Path(target) / "release" / "kfmc")


@pytest.fixture(scope="session")
def kfmc_bin() -> str:
    path = _kfmc_bin()
    if not os.path.isfile(path):
        pytest.fail(f"{path}: the cargo-built kfmc is needed as the reference (set KFMC_BIN)")
    return path


@pytest.fixture(scope="session")
def root() -> pathlib.Path:
    return ROOT


@pytest.fixture(scope="session")
def script_kfmc() -> str:
    """The wheel's console script `kfmc` (beside this Python)."""
    import sys

    path = pathlib.Path(sys.executable).parent / "kfmc"
    if not path.exists():
        found = shutil.which("kfmc")
        if found is None:
            pytest.fail("the wheel's `kfmc` script is not installed beside this Python")
        return found
    return str(path)
