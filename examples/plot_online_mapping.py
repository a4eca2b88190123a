"""
===========================================
Online mapping: the map grows as scans come
===========================================

A robot builds its map while it drives. :meth:`~skoccmap.MixtureGPOccupancyMap.partial_fit`
adds a batch of scans to a fitted map: new hits join the clusters they belong to (or open
a new one when the robot enters a new room), and only the experts that received rows
change: they take the new rows by EP on those rows' sites alone, and are refitted
(warm-started from their EP state) once enough rows have been added. The other experts stay
as they were.

This example replays the simulated office of
:func:`~skoccmap.datasets.make_office_scans` (a path through the corridor and seven rooms)
in batches of scans, prints the update time and the experts touched per batch, and shows
snapshots of the growing map. ``skoccmap map LOG --online --batch-scans N`` does the same
for a CARMEN log or a ROS bag.
"""

# %%
# Replay the scans in batches
# ---------------------------
import time

import matplotlib.pyplot as plt

from skoccmap import MixtureGPOccupancyMap, OccupancyGrid
from skoccmap.datasets import make_office_scans
from skoccmap.plotting import OccupancyMapDisplay

data = make_office_scans(n_poses=60, n_beams=90, noise_std=0.02, random_state=0)
scans = data.scans
batch = 6
model = MixtureGPOccupancyMap(n_jobs=2, random_state=0)
snapshots = {}
print(f"{'scans':>6s} {'update s':>9s} {'touched':>8s} {'experts':>8s} {'clusters':>9s}")
for first in range(0, len(scans), batch):
    X, y, _ = scans[first : first + batch].to_observations()
    tic = time.perf_counter()
    model.partial_fit(X, y, classes=[0, 1])
    seen = min(first + batch, len(scans))
    print(
        f"{seen:6d} {time.perf_counter() - tic:9.2f} {model.touched_experts_.size:8d} "
        f"{model.n_experts_:8d} {model.n_clusters_:9d}"
    )
    if seen in (18, 36, len(scans)):
        grid = OccupancyGrid.from_estimator(
            model, extent=data.environment.extent, resolution=0.2, observed_by=scans[:seen]
        )
        snapshots[seen] = grid

# %%
# The first update is a fit; later ones change the experts near the new scans only (most
# take their new rows without a refit), so an update costs about the same however large the
# map has grown.
#
# Snapshots of the growing map
# ----------------------------
# Cells no beam has crossed yet are unknown.
fig, axes = plt.subplots(1, len(snapshots), figsize=(5 * len(snapshots), 4.5))
for ax, (seen, grid) in zip(axes, snapshots.items(), strict=True):
    OccupancyMapDisplay.from_grid(grid, kind="probability", ax=ax)
    path = scans.poses[:seen, :2]
    ax.plot(path[:, 0], path[:, 1], "r-", lw=1)
    ax.set_title(f"after {seen} of {len(scans)} scans")
plt.show()
