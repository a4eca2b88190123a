"""
=========================================
ROS bags in, a map for map_server out
=========================================

Most laser data recorded today sits in ROS bags. :func:`~skoccmap.datasets.load_rosbag`
reads the ``sensor_msgs/LaserScan`` messages of a bag, ROS 1 (a ``.bag`` file) or ROS 2
(a directory with sqlite3 or mcap storage), and the pose of the laser at every scan, from
the transforms on ``/tf`` and ``/tf_static`` (map -> odom -> base_link -> laser,
interpolated to each scan's stamp) or from an odometry topic. It needs the pure-Python
``rosbags`` package (``pip install "skoccmap[ros]"``), not a ROS installation.

A fitted map goes back into a bag with :meth:`skoccmap.OccupancyGrid.write_rosbag`: one
``nav_msgs/OccupancyGrid`` on a latched ``/map`` topic, as map_server publishes it.

This example has no recording to hand, so it makes one: the simulated office of
:func:`~skoccmap.datasets.make_office_scans`, written as a ROS 2 bag by
:func:`~skoccmap.datasets.write_rosbag` (LaserScan on ``/scan``, the laser's pose on
``/tf``). From the command line the same map is ``skoccmap map office_bag``.
"""

# %%
# A bag of laser scans
# --------------------
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from skoccmap import MixtureGPOccupancyMap, OccupancyGrid
from skoccmap.datasets import load_rosbag, make_office_scans, write_rosbag
from skoccmap.plotting import OccupancyMapDisplay

tmp = Path(tempfile.mkdtemp())
office = make_office_scans(noise_std=0.02, random_state=0)
# Without rosbags installed, write_rosbag stops here with the command that installs it.
bag = write_rosbag(office.scans, tmp / "office_bag", ros_version=2)

from rosbags.highlevel import AnyReader  # noqa: E402 (installed with skoccmap[ros])

with AnyReader([bag]) as reader:
    for topic, info in reader.topics.items():
        print(f"{topic:6s} {info.msgtype:28s} {info.msgcount} messages")

# %%
# Scans and poses back
# --------------------
# The poses come from ``/tf``, the beams from each message's ``angle_min`` and
# ``angle_increment``; readings are float32 in a LaserScan.
scans = load_rosbag(bag, "/scan", map_frame="map")
print(f"{len(scans)} scans x {scans.n_beams} beams, max range {scans.max_range:g} m")
print("largest pose error:", np.abs(scans.poses - office.scans.poses).max())

# %%
# The map
# -------
X, y, _ = scans.to_observations()
model = MixtureGPOccupancyMap(random_state=0).fit(X, y)
grid = OccupancyGrid.from_estimator(model, scans.hit_points(), 0.1, observed_by=scans)
OccupancyMapDisplay.from_grid(grid, kind="both")
plt.show()

# %%
# The map into a bag
# ------------------
# ``ros2 bag play office_map`` offers ``/map`` with transient-local durability, so RViz or
# nav2 receive it whenever they subscribe (``ros_version=1`` writes a latched ROS 1 topic).
# ``data`` holds ``round(100 * P(occupied))`` and -1 for unknown cells, or 0 / 100 / -1 at
# map_server's thresholds with ``trinary=True``. ``grid.save_map_server(stem)`` writes the
# PGM + YAML pair that map_server loads from disk.
map_bag = grid.write_rosbag(tmp / "office_map", topic="/map", frame_id="map", stamp=0.0)
with AnyReader([map_bag]) as reader:
    (connection,) = reader.connections
    (qos,) = connection.ext.offered_qos_profiles
    _, _, raw = next(reader.messages())
    message = reader.deserialize(raw, connection.msgtype)
info = message.info
print(f"{connection.topic}: {connection.msgtype}, durability {qos.durability.name}")
print(f"{info.width} x {info.height} cells of {info.resolution:g} m, origin "
      f"({info.origin.position.x:g}, {info.origin.position.y:g})")  # fmt: skip
values, counts = np.unique(message.data, return_counts=True)
print("unknown cells:", counts[values == -1].sum(), "of", message.data.size)
