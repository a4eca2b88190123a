import os
from pathlib import Path

import pytest

# Timing-independent tests: keep BLAS to one thread so two test processes don't oversubscribe.
for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(var, "1")

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data():
    """Directory of the real laser logs (``../shared/data``); skips when it is absent."""
    path = Path(os.environ.get("SKOCCMAP_SHARED_DATA", SHARED_DATA))
    if not path.is_dir():
        pytest.skip(f"shared data directory {path} not found")
    return path
