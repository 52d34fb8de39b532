import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)


import subprocess  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def solver() -> Path:
    """thermoDemFoam, installed (OpenFOAM + headers) and built (cached) on first use."""
    from coupling import foam_case as fc
    r = subprocess.run(["bash", os.path.join(ROOT, "scripts", "install_openfoam.sh")],
                       capture_output=True, text=True)
    assert r.returncode == 0, f"install_openfoam.sh failed:\n{r.stderr[-3000:]}"
    exe = fc.build_solver()
    assert exe.is_file() and os.access(exe, os.X_OK)
    return exe
