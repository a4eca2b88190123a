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


@pytest.fixture(scope="session")
def paper_log(tmp_path_factory):
    """The paper's simulated scans written as a CARMEN FLASER log (8 m sentinel), and the data."""
    # Imported here: numpy must load after the BLAS thread settings above.
    import numpy as np

    from skoccmap.datasets import flaser_angles, make_paper_scans

    data = make_paper_scans(random_state=0)
    scans = data.scans
    np.testing.assert_allclose(scans.angles, flaser_angles(scans.n_beams))
    path = tmp_path_factory.mktemp("log") / "paper.log"
    lines = ["# simulated FLASER log\n"]
    for t, (pose, ranges) in enumerate(zip(scans.poses, scans.ranges, strict=True)):
        readings = np.where(np.isfinite(ranges), ranges, scans.max_range)
        fields = ["FLASER", str(scans.n_beams), *(f"{r:.6f}" for r in readings)]
        fields += [f"{v:.9f}" for v in pose] * 2 + [str(t), "sim", str(t)]
        lines.append(" ".join(fields) + "\n")
    path.write_text("".join(lines))
    return path, data
