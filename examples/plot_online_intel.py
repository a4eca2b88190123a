"""
=============================================
Online mapping of a real log: the Intel lab
=============================================

:meth:`~skoccmap.MixtureGPOccupancyMap.partial_fit` on a real robot's log, in the order
the robot recorded it. The log is the Intel Research Lab's (CARMEN format, SLAM-corrected
poses, 180 beams per scan), which is not shipped with skoccmap: this example reads it from
the path in the ``SKOCCMAP_INTEL_LOG`` environment variable, or from
``shared/data/intel.gfs.log`` next to a checkout of the repository, and replays the
simulated office of :func:`~skoccmap.datasets.make_office_scans` when neither is there.

Every 2nd of the first 300 scans is added in batches of 10 scans. Each update prints its
time, the experts it updated and the experts of the map; three snapshots show the map
growing as the robot drives down the lab's corridors. ``skoccmap map intel.gfs.log
--online --every-nth-scan 2 --batch-scans 10`` replays the whole log the same way from the
command line (every 2nd of all 910 scans, not of the first 300).
"""

# %%
# Load the scans
# --------------
import os
import time
from pathlib import Path

import matplotlib.pyplot as plt

from skoccmap import MixtureGPOccupancyMap, OccupancyGrid
from skoccmap.datasets import load_carmen, make_office_scans
from skoccmap.plotting import OccupancyMapDisplay

# Run from examples/ (as the gallery runs it) or from the repository's root.
near = [Path(up, "shared/data/intel.gfs.log") for up in ("../..", "..")]
log = Path(os.environ.get("SKOCCMAP_INTEL_LOG", next((p for p in near if p.is_file()), near[0])))
if log.is_file():
    scans = load_carmen(log)[:300:2]
    print(f"{log.name}: {len(scans)} scans")
else:
    scans = make_office_scans(n_poses=60, n_beams=90, noise_std=0.02, random_state=0).scans
    print(f"{log} not found: replaying the simulated office ({len(scans)} scans)")

# %%
# Replay them in batches
# ----------------------
# The first call fits the map; each later one clusters the new hits, routes the beams to
# the experts of their hits; those experts take the new rows by EP on their sites alone,
# and are refitted once the rows added so are due (``refit_fraction``).
batch = 10
model = MixtureGPOccupancyMap(n_jobs=2, random_state=0)
hits = scans.hit_points()  # the snapshots cover the final map's extent
snapshots = {}
print(f"{'scans':>6s} {'update s':>9s} {'updated':>9s} {'experts':>8s}")
for first in range(0, len(scans), batch):
    X, y, _ = scans[first : first + batch].to_observations()
    tic = time.perf_counter()
    model.partial_fit(X, y, classes=[0, 1])
    seen = min(first + batch, len(scans))
    print(
        f"{seen:6d} {time.perf_counter() - tic:9.2f} {model.touched_experts_.size:9d} "
        f"{model.n_experts_:8d}"
    )
    if seen in (len(scans) // 3, 2 * len(scans) // 3, len(scans)):
        snapshots[seen] = OccupancyGrid.from_estimator(
            model, extent=hits, resolution=0.2, observed_by=scans[:seen]
        )

# %%
# Snapshots of the growing map
# ----------------------------
# Cells no beam has crossed yet are unknown; the red line is the path driven so far.
fig, axes = plt.subplots(1, len(snapshots), figsize=(6 * len(snapshots), 5), layout="constrained")
for ax, (seen, grid) in zip(axes, snapshots.items(), strict=True):
    OccupancyMapDisplay.from_grid(grid, kind="probability", ax=ax)
    path = scans.poses[:seen, :2]
    ax.plot(path[:, 0], path[:, 1], "r-", lw=1)
    ax.set_title(f"after {seen} of {len(scans)} scans")
plt.show()
