"""ROS bags: scans and poses read with load_rosbag, scans and maps written into bags."""

import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")

from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.interfaces import QosDurability, QosHistory, QosReliability  # noqa: E402
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402
from sklearn.metrics import roc_auc_score  # noqa: E402

from skoccmap import OccupancyGrid  # noqa: E402
from skoccmap.cli import main  # noqa: E402
from skoccmap.datasets import load_carmen, load_rosbag, make_paper_scans, write_rosbag  # noqa: E402
from skoccmap.datasets._rosbag import is_rosbag  # noqa: E402
from skoccmap.observations import NO_RETURN, Scans  # noqa: E402

FORMATS = [(1, "sqlite3"), (2, "sqlite3"), (2, "mcap")]
FORMAT_IDS = ["ros1", "ros2-sqlite3", "ros2-mcap"]


# --------------------------------------------------------------------------------------------
# Bags written message by message with rosbags, independently of the package's writer
# --------------------------------------------------------------------------------------------


def _store(ros_version):
    if ros_version == 2:
        return get_typestore(Stores.ROS2_HUMBLE)
    store = get_typestore(Stores.ROS1_NOETIC)
    if "tf2_msgs/msg/TFMessage" not in store.fielddefs:
        store.register(
            get_types_from_msg(
                "geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"
            )
        )
    return store


class _Bag:
    """Messages given in seconds and plain numbers, written on close."""

    def __init__(self, ros_version):
        self.ros_version = ros_version
        self.store = _store(ros_version)
        self.messages = []  # (topic, msgtype, stamp, message)

    def _header(self, stamp, frame):
        sec, nanosec = divmod(int(round(stamp * 1e9)), 10**9)
        time = self.store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
        extra = {"seq": 0} if self.ros_version == 1 else {}
        return self.store.types["std_msgs/msg/Header"](stamp=time, frame_id=frame, **extra)

    def _pose_parts(self, xyz, yaw=0.0, roll=0.0):
        t = self.store.types
        # Roll about x, then yaw about z: q = q_yaw * q_roll.
        cy, sy, cr, sr = np.cos(yaw / 2), np.sin(yaw / 2), np.cos(roll / 2), np.sin(roll / 2)
        q = t["geometry_msgs/msg/Quaternion"](x=cy * sr, y=sy * sr, z=sy * cr, w=cy * cr)
        return [float(v) for v in xyz], q

    def tf(self, stamp, parent, child, xyz, yaw=0.0, roll=0.0, static=False):
        t = self.store.types
        (x, y, z), q = self._pose_parts(xyz, yaw, roll)
        transform = t["geometry_msgs/msg/TransformStamped"](
            header=self._header(stamp, parent),
            child_frame_id=child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=x, y=y, z=z), rotation=q
            ),
        )
        message = t["tf2_msgs/msg/TFMessage"](transforms=[transform])
        topic = "/tf_static" if static else "/tf"
        self.messages.append((topic, "tf2_msgs/msg/TFMessage", stamp, message))

    def scan(self, stamp, ranges, *, frame="laser", angle_min=-0.5, increment=0.5,
             range_min=0.1, range_max=5.0, topic="/scan"):  # fmt: skip
        ranges = np.asarray(ranges, dtype=np.float32)
        message = self.store.types["sensor_msgs/msg/LaserScan"](
            header=self._header(stamp, frame),
            angle_min=angle_min,
            angle_max=angle_min + increment * (ranges.size - 1),
            angle_increment=increment,
            time_increment=0.0,
            scan_time=0.0,
            range_min=range_min,
            range_max=range_max,
            ranges=ranges,
            intensities=np.zeros(0, dtype=np.float32),
        )
        self.messages.append((topic, "sensor_msgs/msg/LaserScan", stamp, message))

    def odometry(self, stamp, xyz, yaw, *, frame="odom", child="base_link", topic="/odom"):
        t = self.store.types
        (x, y, z), q = self._pose_parts(xyz, yaw)
        pose = t["geometry_msgs/msg/Pose"](position=t["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                                           orientation=q)  # fmt: skip
        twist = t["geometry_msgs/msg/Twist"](
            linear=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            angular=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        )
        message = t["nav_msgs/msg/Odometry"](
            header=self._header(stamp, frame),
            child_frame_id=child,
            pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
        )
        self.messages.append((topic, "nav_msgs/msg/Odometry", stamp, message))

    def pose_stamped(self, stamp, xyz, yaw, *, frame="map", topic="/pose"):
        t = self.store.types
        (x, y, z), q = self._pose_parts(xyz, yaw)
        pose = t["geometry_msgs/msg/Pose"](position=t["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                                           orientation=q)  # fmt: skip
        message = t["geometry_msgs/msg/PoseStamped"](header=self._header(stamp, frame), pose=pose)
        self.messages.append((topic, "geometry_msgs/msg/PoseStamped", stamp, message))

    def write(self, path):
        path = Path(path)
        writer = Writer1(path) if self.ros_version == 1 else Writer2(path, version=8)
        with writer:
            conns = {}
            for topic, msgtype, stamp, message in sorted(self.messages, key=lambda m: m[2]):
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, msgtype, typestore=self.store)
                serialize = (self.store.serialize_ros1 if self.ros_version == 1
                             else self.store.serialize_cdr)  # fmt: skip
                writer.write(conns[topic], int(round(stamp * 1e9)), serialize(message, msgtype))
        return path


def _bag_path(tmp_path, ros_version, name="run"):
    return tmp_path / (f"{name}.bag" if ros_version == 1 else name)


def _se2(x, y, yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def _pose_of(matrix):
    return np.array([matrix[0, 2], matrix[1, 2], np.arctan2(matrix[1, 0], matrix[0, 0])])


def _wrap(angle):
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


# --------------------------------------------------------------------------------------------
# Fixtures
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def paper_scans():
    """The paper's simulated scans (26 x 17 beams), stamped 0.5 s apart."""
    data = make_paper_scans(random_state=0)
    scans = data.scans
    stamped = Scans(scans.poses, scans.ranges, scans.angles, scans.max_range,
                    timestamps=100.0 + 0.5 * np.arange(len(scans)))  # fmt: skip
    return stamped, data


@pytest.fixture(scope="module")
def intel_scans(shared_data):
    """The Intel lab log, in time order (its stamps step back four times)."""
    scans = load_carmen(shared_data / "intel.gfs.log")
    return scans[np.argsort(scans.timestamps, kind="stable")]


def _assert_same_scans(back, scans):
    assert len(back) == len(scans) and back.n_beams == scans.n_beams
    np.testing.assert_allclose(back.poses[:, :2], scans.poses[:, :2], atol=1e-9)
    np.testing.assert_allclose(_wrap(back.poses[:, 2] - scans.poses[:, 2]), 0.0, atol=1e-9)
    np.testing.assert_array_equal(np.isinf(back.ranges), ~scans.returned())
    returned = scans.returned()
    expected = scans.ranges[returned].astype(np.float32).astype(np.float64)
    np.testing.assert_array_equal(back.ranges[returned], expected)
    np.testing.assert_allclose(back.angles, scans.angles, atol=1e-6)  # float32 angle fields
    np.testing.assert_allclose(back.timestamps, scans.timestamps, atol=1e-8)
    assert back.max_range == scans.max_range


# --------------------------------------------------------------------------------------------
# Scans through bags
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("ros_version, storage", FORMATS, ids=FORMAT_IDS)
def test_written_scans_read_back(paper_scans, tmp_path, ros_version, storage):
    scans, _ = paper_scans
    bag = write_rosbag(scans, _bag_path(tmp_path, ros_version), ros_version=ros_version,
                       storage=storage)  # fmt: skip
    assert is_rosbag(bag)
    _assert_same_scans(load_rosbag(bag), scans)


def test_zero_readings_stay_no_reading_through_a_bag(paper_scans, tmp_path):
    scans, _ = paper_scans
    ranges = scans.ranges[:3].copy()
    ranges[:, ::4] = 0.0
    scans = Scans(scans.poses[:3], ranges, scans.angles, scans.max_range,
                  timestamps=scans.timestamps[:3])  # fmt: skip
    back = load_rosbag(write_rosbag(scans, tmp_path / "zeros", ros_version=2))
    np.testing.assert_array_equal(back.unread(), scans.unread())
    X, y, kind = scans.to_observations()
    X_back, y_back, kind_back = back.to_observations()
    np.testing.assert_array_equal(kind_back, kind)
    np.testing.assert_allclose(X_back, X, atol=1e-5)  # float32 ranges in a LaserScan


def test_ros2_storage_without_metadata(paper_scans, tmp_path):
    scans, _ = paper_scans
    bag = write_rosbag(scans, tmp_path / "bag", storage="mcap")
    (bag / "metadata.yaml").unlink()  # a recorder killed before it wrote the metadata
    assert is_rosbag(bag)
    _assert_same_scans(load_rosbag(bag), scans)


@pytest.mark.parametrize("ros_version", [1, 2])
def test_intel_log_through_a_bag_reads_as_load_carmen(intel_scans, tmp_path, ros_version):
    bag = write_rosbag(intel_scans, _bag_path(tmp_path, ros_version, "intel"),
                       ros_version=ros_version)  # fmt: skip
    back = load_rosbag(bag)
    _assert_same_scans(back, intel_scans)
    assert back.max_range == 81.83  # the float32 range_max read as the driver's value
    X0, y0, kind0 = intel_scans.to_observations()
    X1, y1, kind1 = back.to_observations()
    np.testing.assert_array_equal(kind1, kind0)
    np.testing.assert_allclose(X1, X0, atol=1e-4)  # float32 ranges up to 81 m


def test_3d_scans_with_a_tilted_laser_read_back(tmp_path):
    q = [np.cos(0.15), np.sin(0.15), 0.0, 0.0]  # 0.3 rad roll
    scans = Scans(poses=[[1.0, 2.0, 0.5, *q], [1.5, 2.0, 0.5, *q]], ranges=[[1.0, 2.0, 3.0]] * 2,
                  angles=[[np.cos(a), np.sin(a), 0.0] for a in (-0.2, 0.0, 0.2)],
                  max_range=10.0, timestamps=[1.0, 2.0])  # fmt: skip
    back = load_rosbag(write_rosbag(scans, tmp_path / "tilted"))
    assert back.n_dims == 3
    np.testing.assert_allclose(back.poses, scans.poses, atol=1e-12)
    np.testing.assert_allclose(back.angles, scans.angles, atol=1e-6)
    # Forced to 2-D: the laser's yaw (zero here) and position in the plane.
    flat = load_rosbag(tmp_path / "tilted", level_tolerance=np.inf)
    np.testing.assert_allclose(flat.poses, [[1.0, 2.0, 0.0], [1.5, 2.0, 0.0]], atol=1e-12)


@pytest.mark.parametrize("first", [0.0, -np.pi, 2.5])
def test_3d_scans_over_the_whole_circle_read_back(tmp_path, first):
    # Eight beams a full turn round from `first`: their directions pass arctan2's cut at pi.
    q = [np.cos(0.15), np.sin(0.15), 0.0, 0.0]
    angles = first + np.arange(8) * np.pi / 4
    directions = np.column_stack([np.cos(angles), np.sin(angles), np.zeros(8)])
    scans = Scans(poses=[[0.0, 0.0, 0.5, *q]], ranges=[np.full(8, 2.0)], angles=directions,
                  max_range=5.0, timestamps=[1.0])  # fmt: skip
    back = load_rosbag(write_rosbag(scans, tmp_path / "round.bag", ros_version=1))
    np.testing.assert_allclose(back.angles, directions, atol=1e-6)
    np.testing.assert_allclose(back.hit_points(), scans.hit_points(), atol=1e-5)


# --------------------------------------------------------------------------------------------
# Poses from TF and from pose topics
# --------------------------------------------------------------------------------------------


def test_interpolation_between_two_transforms(tmp_path):
    bag = _Bag(2)
    bag.tf(1.0, "map", "laser", (0.0, 0.0, 0.0), yaw=0.0)
    bag.tf(3.0, "map", "laser", (2.0, 4.0, 0.0), yaw=np.pi / 2)
    bag.tf(5.0, "map", "laser", (2.0, 4.0, 0.0), yaw=3.0)
    bag.tf(7.0, "map", "laser", (2.0, 4.0, 0.0), yaw=-3.0)
    for stamp in (1.5, 3.0, 6.0):
        bag.scan(stamp, [1.0, 1.0, 1.0])
    scans = load_rosbag(bag.write(tmp_path / "b"))
    # A quarter of the way from t=1 to t=3: a quarter of the translation and of the turn.
    np.testing.assert_allclose(scans.poses[0], [0.5, 1.0, np.pi / 8], atol=1e-12)
    np.testing.assert_allclose(scans.poses[1], [2.0, 4.0, np.pi / 2], atol=1e-12)
    # Halfway from 3 rad to -3 rad turns the short way, through pi, not through 0.
    assert abs(_wrap(scans.poses[2, 2] - np.pi)) < 1e-9
    np.testing.assert_allclose(scans.timestamps, [1.5, 3.0, 6.0])


@pytest.mark.parametrize("ros_version", [1, 2])
def test_tf_chain_with_a_static_laser_offset(tmp_path, ros_version):
    # map -> odom drifts, odom -> base_link drives, base_link -> laser is fixed.
    slash = "/" if ros_version == 1 else ""  # ROS 1 frame ids may carry a leading slash
    bag = _Bag(ros_version)
    bag.tf(0.0, "base_link", f"{slash}laser", (0.2, -0.1, 0.3), yaw=np.pi / 2, static=True)
    for t in (0.0, 2.0, 4.0):
        bag.tf(t, f"{slash}map", "odom", (0.1 * t, -0.05 * t, 0.0), yaw=0.02 * t)
    for t in np.arange(0.0, 4.01, 0.5):
        bag.tf(t, "odom", f"{slash}base_link", (t, 0.5 * t**2, 0.0), yaw=0.3 * t)
    stamps = [0.25, 1.0, 2.7, 3.9, 4.5]  # the last one is after the transforms end
    for stamp in stamps:
        bag.scan(stamp, [1.0, 2.0, 3.0], frame=f"{slash}laser")
    path = bag.write(_bag_path(tmp_path, ros_version))
    # The static offset, sent once at 0 s, holds at every time: the poses span the dynamic
    # transforms' [0, 4] s.
    match = r"skipped 1 of 5 scans .*outside the time range of their poses \[0, 4\] s"
    with pytest.warns(UserWarning, match=match):
        scans = load_rosbag(path)
    expected = []
    for t in stamps[:-1]:
        # Each transform interpolated between its own samples, by hand.
        map_odom = _se2(0.1 * t, -0.05 * t, 0.02 * t)  # linear in t: interpolation is exact
        b0, b1 = np.floor(t / 0.5) * 0.5, np.floor(t / 0.5) * 0.5 + 0.5
        v = (t - b0) / 0.5
        x = (1 - v) * b0 + v * b1
        y = (1 - v) * 0.5 * b0**2 + v * 0.5 * b1**2
        odom_base = _se2(x, y, 0.3 * t)
        expected.append(_pose_of(map_odom @ odom_base @ _se2(0.2, -0.1, np.pi / 2)))
    np.testing.assert_allclose(scans.poses, expected, atol=1e-9)
    np.testing.assert_allclose(scans.timestamps, stamps[:-1])


def test_chain_against_the_direction_of_a_transform(tmp_path):
    bag = _Bag(2)
    bag.tf(0.0, "map", "odom", (1.0, 0.0, 0.0), yaw=np.pi / 2, static=True)
    bag.tf(0.0, "map", "laser", (2.0, 3.0, 0.0), yaw=0.3)
    bag.tf(1.0, "map", "laser", (2.0, 3.0, 0.0), yaw=0.3)
    bag.scan(0.5, [1.0, 2.0, 3.0])
    scans = load_rosbag(bag.write(tmp_path / "b"), map_frame="odom")  # odom -> map -> laser
    expected = _pose_of(np.linalg.inv(_se2(1.0, 0.0, np.pi / 2)) @ _se2(2.0, 3.0, 0.3))
    np.testing.assert_allclose(scans.poses, [expected], atol=1e-12)


def test_odometry_topic_with_the_laser_offset_from_tf_static(tmp_path):
    bag = _Bag(2)
    bag.tf(0.0, "base_link", "laser", (0.3, 0.0, 0.2), yaw=0.1, static=True)
    bag.odometry(0.0, (0.0, 0.0, 0.0), 0.0)
    bag.odometry(1.0, (1.0, 2.0, 0.0), 0.4)
    bag.scan(0.5, [1.0, 2.0, 3.0])
    scans = load_rosbag(bag.write(tmp_path / "b"), pose_topic="/odom")
    expected = _pose_of(_se2(0.5, 1.0, 0.2) @ _se2(0.3, 0.0, 0.1))
    np.testing.assert_allclose(scans.poses, [expected], atol=1e-12)


def test_pose_topic_without_a_laser_offset_needs_base_frame(tmp_path):
    bag = _Bag(1)
    bag.odometry(0.0, (0.0, 0.0, 0.0), 0.0)
    bag.odometry(1.0, (1.0, 0.0, 0.0), 0.0)
    bag.scan(0.5, [1.0, 2.0, 3.0])
    path = bag.write(tmp_path / "b.bag")
    with pytest.raises(ValueError, match=r"base_frame='laser'"):
        load_rosbag(path, pose_topic="/odom")
    scans = load_rosbag(path, pose_topic="/odom", base_frame="laser")
    np.testing.assert_allclose(scans.poses, [[0.5, 0.0, 0.0]], atol=1e-12)
    scans = load_rosbag(path, pose_topic="/odom", base_frame="/laser")  # ROS 1's slash
    np.testing.assert_allclose(scans.poses, [[0.5, 0.0, 0.0]], atol=1e-12)


def test_pose_stamped_topic_gives_the_laser_pose(tmp_path):
    bag = _Bag(2)
    bag.pose_stamped(10.0, (1.0, 1.0, 0.0), 1.0)
    bag.pose_stamped(12.0, (3.0, 1.0, 0.0), 2.0)
    bag.scan(11.5, [1.0, 2.0, 3.0])
    bag.scan(12.5, [1.0, 2.0, 3.0])
    with pytest.warns(UserWarning, match="skipped 1 of 2 scans"):
        scans = load_rosbag(bag.write(tmp_path / "b"), pose_topic="/pose")
    np.testing.assert_allclose(scans.poses, [[2.5, 1.0, 1.75]], atol=1e-12)


@pytest.mark.parametrize("message", ["pose_stamped", "odometry"])
def test_a_pose_topic_naming_no_frame_warns_when_the_laser_is_mounted(tmp_path, message):
    # amcl_pose and an Odometry with an empty child_frame_id give the robot's pose, not the
    # laser's: read as the laser's own pose they lose its offset, which a warning names.
    bag = _Bag(2)
    bag.tf(0.0, "base_link", "laser", (0.3, 0.0, 0.2), yaw=np.pi, static=True)
    for stamp, x in ((0.0, 0.0), (1.0, 1.0)):
        if message == "pose_stamped":
            bag.pose_stamped(stamp, (x, 0.0, 0.0), 0.0, topic="/odom")
        else:
            bag.odometry(stamp, (x, 0.0, 0.0), 0.0, child="")
    bag.scan(0.5, [1.0, 2.0, 3.0])
    path = bag.write(tmp_path / "b")
    with pytest.warns(UserWarning, match=r"mount 'laser' on 'base_link'.*base_frame='base_link'"):
        scans = load_rosbag(path, pose_topic="/odom")
    np.testing.assert_allclose(scans.poses, [[0.5, 0.0, 0.0]], atol=1e-12)
    scans = load_rosbag(path, pose_topic="/odom", base_frame="base_link")
    np.testing.assert_allclose(scans.poses[:, :2], [[0.8, 0.0]], atol=1e-12)
    np.testing.assert_allclose(_wrap(scans.poses[:, 2] - np.pi), 0.0, atol=1e-12)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scans = load_rosbag(path, pose_topic="/odom", base_frame="laser")
    np.testing.assert_allclose(scans.poses, [[0.5, 0.0, 0.0]], atol=1e-12)


def test_a_pose_topic_in_the_lasers_parent_frame_does_not_warn(tmp_path):
    # The transforms place the laser in the poses' own frame: no other frame to suggest.
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (0.3, 0.0, 0.0), static=True)
    bag.pose_stamped(0.0, (0.0, 0.0, 0.0), 0.0)
    bag.pose_stamped(1.0, (1.0, 0.0, 0.0), 0.0)
    bag.scan(0.5, [1.0, 2.0, 3.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scans = load_rosbag(bag.write(tmp_path / "b"), pose_topic="/pose")
    np.testing.assert_allclose(scans.poses, [[0.5, 0.0, 0.0]], atol=1e-12)


def test_cli_names_its_options_in_the_bag_reader_warnings(tmp_path, capsys):
    from skoccmap._cmd_map import load_scans
    from skoccmap.cli import build_parser

    bag = _Bag(2)
    bag.tf(0.0, "base_link", "laser", (0.3, 0.0, 0.2), static=True)
    bag.pose_stamped(0.0, (0.0, 0.0, 0.0), 0.0)
    bag.pose_stamped(1.0, (1.0, 0.0, 0.0), 0.0)
    bag.scan(0.5, [1.0, 2.0, 3.0])
    bag.scan(1.5, [1.0, 2.0, 3.0])
    path = bag.write(tmp_path / "b")
    load_scans(build_parser().parse_args(["map", str(path), "--pose-topic", "/pose"]))
    err = capsys.readouterr().err
    assert "skoccmap map: warning:" in err and "skipped 1 of 2 scans" in err
    assert "pass --base-frame its frame (e.g. --base-frame 'base_link')" in err
    assert "base_frame=" not in err


def test_cli_prints_the_bag_reader_warnings_when_it_then_fails(tmp_path, capsys):
    from skoccmap._cmd_map import load_scans
    from skoccmap.cli import build_parser

    bag = _Bag(2)
    bag.tf(0.0, "base_link", "laser", (0.3, 0.0, 0.2), static=True)
    bag.pose_stamped(0.0, (0.0, 0.0, 0.0), 0.0)
    bag.pose_stamped(1.0, (1.0, 0.0, 0.0), 0.0)
    bag.scan(1.5, [1.0, 2.0, 3.0])  # after the last pose: no scan has one
    path = bag.write(tmp_path / "b")
    args = build_parser().parse_args(["map", str(path), "--pose-topic", "/pose"])
    with pytest.raises(ValueError, match="no scan of '/scan' has a pose"):
        load_scans(args)
    err = capsys.readouterr().err
    assert "skoccmap map: warning:" in err and "--base-frame 'base_link'" in err


def _rolled_laser_bag(tmp_path, roll):
    """A ROS 2 bag of one scan by a laser 0.4 m up at yaw 0.5, rolled by ``roll``."""
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (1.0, 0.0, 0.4), yaw=0.5, roll=roll)
    bag.tf(1.0, "map", "laser", (1.0, 0.0, 0.4), yaw=0.5, roll=roll)
    bag.scan(0.5, [1.0, 2.0, 3.0])
    return bag.write(tmp_path / "b")


def test_level_tolerance_chooses_2d_or_3d_poses(tmp_path):
    path = _rolled_laser_bag(tmp_path, 0.005)
    level = load_rosbag(path)  # 0.005 rad of roll is level at the default 0.01 rad
    np.testing.assert_allclose(level.poses, [[1.0, 0.0, 0.5]], atol=1e-12)
    tilted = load_rosbag(path, level_tolerance=0.001)
    assert tilted.poses.shape == (1, 7) and tilted.angles.shape == (3, 3)
    # Yaw 0.5 after roll 0.005: (cy, 0, 0, sy) * (cr, sr, 0, 0), multiplied out by hand.
    cy, sy, cr, sr = np.cos(0.25), np.sin(0.25), np.cos(0.0025), np.sin(0.0025)
    q = [cy * cr, cy * sr, sy * sr, sy * cr]
    np.testing.assert_allclose(tilted.poses[0], [1.0, 0.0, 0.4, *q], atol=1e-12)
    # Both describe the same beams: hit points agree in the plane.
    np.testing.assert_allclose(tilted.hit_points()[:, :2], level.hit_points(), atol=0.02)


def test_level_tolerance_and_tf_topics_are_checked(tmp_path):
    path = _rolled_laser_bag(tmp_path, 0.2)
    for bad in ("0.3", None, True, -0.1, np.nan):
        with pytest.raises(ValueError, match="level_tolerance must be >= 0 radians"):
            load_rosbag(path, level_tolerance=bad)
    # 5 "degrees" read as radians: every laser level, the 0.2 rad roll flattened.
    with pytest.warns(UserWarning, match="Degrees\\? Pass radians"):
        assert load_rosbag(path, level_tolerance=5).poses.shape == (1, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_rosbag(path, level_tolerance=np.inf).poses.shape == (1, 3)
        assert load_rosbag(path, level_tolerance=np.pi / 2).poses.shape == (1, 3)
    for bad in (("/tf",), "/tf", ("/tf", "/tf_static", "/x"), ("/tf", 3), 5):
        with pytest.raises(ValueError, match="tf_topics must be a pair of topic names"):
            load_rosbag(path, tf_topics=bad)
    # The bag has no static topic: naming another one reads it as well.
    assert load_rosbag(path, tf_topics=["/tf", "/none"]).poses.shape == (1, 7)


@pytest.mark.parametrize("roll", [np.pi, np.pi - 0.005])
def test_a_laser_upside_down_scans_a_level_plane_mirrored(tmp_path, roll):
    # Rolled by pi the laser's z axis points down: the beam at angle a points at yaw - a.
    bag = _Bag(2)
    for stamp in (0.0, 1.0):
        bag.tf(stamp, "map", "laser", (1.0, 2.0, 0.4), yaw=0.5, roll=roll)
    bag.scan(0.5, [1.0, 2.0, 3.0])  # angles -0.5, 0, 0.5
    path = bag.write(tmp_path / "b")
    level = load_rosbag(path)
    assert level.poses.shape == (1, 3)
    np.testing.assert_allclose(level.poses, [[1.0, 2.0, 0.5]], atol=1e-12)
    heading = 0.5 - np.array([-0.5, 0.0, 0.5])
    expected = [1.0, 2.0] + np.array([1.0, 2.0, 3.0])[:, None] * np.column_stack(
        [np.cos(heading), np.sin(heading)]
    )
    np.testing.assert_allclose(level.hit_points(), expected, atol=0.02)
    if roll != np.pi:  # exactly upside down is level at any tolerance
        # The 3-D poses put the hits at the same places in the plane.
        tilted = load_rosbag(path, level_tolerance=0.001)
        assert tilted.n_dims == 3
        np.testing.assert_allclose(tilted.hit_points()[:, :2], level.hit_points(), atol=0.02)
    forced = load_rosbag(path, level_tolerance=np.inf)
    np.testing.assert_allclose(forced.hit_points(), level.hit_points(), atol=1e-12)


def test_base_frame_needs_poses_from_a_topic(tmp_path):
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (0.0, 0.0, 0.0))
    bag.tf(1.0, "map", "laser", (0.0, 0.0, 0.0))
    bag.scan(0.5, [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="base_frame= applies only to poses read from a topic"):
        load_rosbag(bag.write(tmp_path / "b"), base_frame="base_link")


# --------------------------------------------------------------------------------------------
# Readings: range limits and beam counts
# --------------------------------------------------------------------------------------------


def test_range_rules(tmp_path):
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (0.0, 0.0, 0.0))
    bag.tf(2.0, "map", "laser", (0.0, 0.0, 0.0))
    # range_min 0.1, range_max 5: NaN, +inf and 5.5 are no-return beams, 5.0 reaches the
    # maximum range (no return too); -inf, 0 and 0.05 are below range_min and dropped.
    readings = [np.nan, np.inf, -np.inf, 0.0, 0.05, 1.0, 5.5, 5.0]
    bag.scan(1.0, readings, angle_min=0.0, increment=0.1)
    bag.scan(1.5, [1.0] * 8, angle_min=0.0, increment=0.1)
    scans = load_rosbag(bag.write(tmp_path / "b"))
    assert scans.max_range == 5.0 and scans.n_beams == 8
    usable = np.array([0, 1, 5, 6, 7])
    # Five usable beams fill eight slots by repeating them in beam order: 0 0 1 1 5 5 6 7.
    index = np.sort(np.resize(usable, 8))
    np.testing.assert_allclose(scans.angles[0], 0.1 * index, atol=1e-6)
    expected = np.array([np.inf, np.inf, 1.0, 5.5, 5.0])[np.searchsorted(usable, index)]
    expected[expected >= 5.0] = np.inf
    np.testing.assert_array_equal(scans.ranges[0], expected)
    np.testing.assert_allclose(scans.angles[1], 0.1 * np.arange(8), atol=1e-6)
    # No hit at or near the sensor, no free beam along a dropped reading's direction.
    assert np.all(np.linalg.norm(scans[0].hit_points(), axis=1) > 0.1)
    X, _, kind, scan = scans.to_observations(return_scan_index=True)
    free_ends = X[(kind == NO_RETURN) & (scan == 0), 2:]
    directions = np.round(np.arctan2(free_ends[:, 1], free_ends[:, 0]), 4)
    assert set(directions) == {0.0, 0.1, 0.6, 0.7}


def test_a_topic_name_without_its_leading_slash_is_found(tmp_path):
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (0.0, 0.0, 0.0), static=True)
    bag.scan(0.5, [1.0, 2.0, 3.0])
    path = bag.write(tmp_path / "b")
    np.testing.assert_array_equal(load_rosbag(path, "scan").ranges, [[1.0, 2.0, 3.0]])
    with pytest.raises(ValueError, match="has no scan topic 'scans'; its topics: "):
        load_rosbag(path, "scans")


def test_two_names_of_one_scan_topic_read_it_once(tmp_path):
    # "scan" and "/scan" (--scan-topic scan --scan-topic /scan) are one topic: read twice,
    # every scan came out twice.
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (0.0, 0.0, 0.0), static=True)
    bag.scan(0.5, [1.0, 2.0, 3.0])
    path = bag.write(tmp_path / "b")
    for topics in (["scan", "/scan"], ["/scan", "scan"]):
        np.testing.assert_array_equal(load_rosbag(path, topics).ranges, [[1.0, 2.0, 3.0]])


def test_transform_topic_names_without_their_leading_slash_are_found(tmp_path):
    # As the scan and pose topics are: ("tf", "tf_static") found no transform topic.
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (1.0, 0.0, 0.0), static=True)
    bag.scan(0.5, [1.0, 2.0, 3.0])
    path = bag.write(tmp_path / "b")
    scans = load_rosbag(path, "scan", tf_topics=("tf", "tf_static"))
    np.testing.assert_allclose(scans.poses, [[1.0, 0.0, 0.0]], atol=1e-12)


def test_cli_tf_topics_of_a_namespaced_robot(tmp_path):
    from skoccmap._cmd_map import load_scans
    from skoccmap.cli import build_parser

    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (1.0, 0.0, 0.0))
    bag.tf(1.0, "map", "laser", (1.0, 0.0, 0.0))
    bag.messages = [("/robot1" + m[0], *m[1:]) for m in bag.messages]
    bag.scan(0.5, [1.0, 2.0, 3.0])
    path = str(bag.write(tmp_path / "b"))
    parser = build_parser()
    with pytest.raises(ValueError, match="has no transform topic"):
        load_scans(parser.parse_args(["map", path]))
    args = parser.parse_args(["map", path, "--tf-topics", "/robot1/tf", "/robot1/tf_static"])
    np.testing.assert_allclose(load_scans(args).poses, [[1.0, 0.0, 0.0]], atol=1e-12)


def test_nan_readings_invalid_drops_them(tmp_path):
    # A scan made from a depth camera: NaN where a pixel has no depth is no free space.
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (0.0, 0.0, 0.0), static=True)
    bag.scan(0.5, [1.0, np.nan, np.inf, 2.0], angle_min=0.0, increment=0.1)
    path = bag.write(tmp_path / "b")
    as_no_return = load_rosbag(path)
    np.testing.assert_array_equal(as_no_return.ranges, [[1.0, np.inf, np.inf, 2.0]])
    dropped = load_rosbag(path, nan_readings="invalid")
    np.testing.assert_allclose(dropped.angles, [0.0, 0.2, 0.3], atol=1e-6)
    np.testing.assert_array_equal(dropped.ranges, [[1.0, np.inf, 2.0]])
    with pytest.raises(ValueError, match="nan_readings must be 'no_return' or 'invalid'"):
        load_rosbag(path, nan_readings="drop")


def test_cli_nan_readings_and_a_max_range_beyond_the_lasers(tmp_path, capsys):
    from skoccmap._cmd_map import load_scans
    from skoccmap.cli import build_parser

    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (0.0, 0.0, 0.0), static=True)
    bag.scan(0.5, [1.0, np.nan, 2.0], angle_min=0.0, increment=0.1, range_max=5.0)
    bag.scan(1.0, [1.0, 1.5, 2.0], angle_min=0.0, increment=0.1, range_max=5.0)
    path = str(bag.write(tmp_path / "b"))
    parser = build_parser()
    scans = load_scans(parser.parse_args(["map", path, "--nan-readings", "invalid"]))
    assert np.isfinite(scans.ranges).all()
    load_scans(parser.parse_args(["map", path, "--max-range", "8"]))
    err = capsys.readouterr().err
    assert "--max-range 8 is beyond the range_max 5 m the scans state" in err
    assert "Pass --max-range 5 or less" in err


@pytest.mark.parametrize("roll", [0.0, np.pi])
def test_scans_with_the_same_beams_share_one_row_of_angles(tmp_path, roll):
    # Upright or upside down, scans alike share one row of angles, also with a scan
    # without a usable reading among them (skipped).
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (0.0, 0.0, 0.0), roll=roll)
    bag.tf(2.0, "map", "laser", (0.0, 0.0, 0.0), roll=roll)
    bag.scan(0.5, [1.0, 2.0, 3.0])
    bag.scan(1.0, [0.0, 0.0, 0.0])  # below range_min
    bag.scan(1.5, [3.0, 2.0, 1.0])
    with pytest.warns(UserWarning, match="skipped 1 scans without a reading"):
        scans = load_rosbag(bag.write(tmp_path / "b"))
    expected = [-0.5, 0.0, 0.5] if roll == 0.0 else [0.5, 0.0, -0.5]
    assert scans.angles.shape == (3,)
    np.testing.assert_allclose(scans.angles, expected, atol=1e-6)
    np.testing.assert_array_equal(scans.ranges, [[1.0, 2.0, 3.0], [3.0, 2.0, 1.0]])


def test_scans_alike_hold_one_row_of_angles_not_one_per_scan():
    # The memory of a long bag: one (n_beams,) row of angles, not (n_scans, n_beams).
    from skoccmap.datasets._rosbag import _LaserMessage, _rectangular

    def message(ranges, start=-0.5):
        return _LaserMessage(0, "laser", np.float32(ranges), start, 0.5, 0.1, 5.0)

    ranges, angles, has_beams = _rectangular([message([1, 2, 3]), message([3, 2, 1])], 5.0)
    assert angles.shape == (3,) and ranges.shape == (2, 3) and has_beams.all()
    np.testing.assert_allclose(angles, [-0.5, 0.0, 0.5])
    # Another start, or a dropped reading: per-scan rows.
    for other in (message([3, 2, 1], start=-0.4), message([3, 0.0, 1])):
        _, angles, _ = _rectangular([message([1, 2, 3]), other], 5.0)
        assert angles.shape == (2, 3)


def test_an_upright_and_an_upside_down_laser_mirror_only_the_second(tmp_path):
    bag = _Bag(2)
    bag.tf(0.0, "map", "up", (0.0, 0.0, 0.0), static=True)
    bag.tf(0.0, "map", "down", (0.0, 0.0, 0.0), roll=np.pi, static=True)
    bag.scan(0.5, [1.0, 2.0, 3.0], frame="up")
    bag.scan(1.0, [1.0, 2.0, 3.0], frame="down")
    scans = load_rosbag(bag.write(tmp_path / "b"))
    np.testing.assert_allclose(scans.angles, [[-0.5, 0.0, 0.5], [0.5, 0.0, -0.5]], atol=1e-6)


@pytest.mark.parametrize("ros_version", [1, 2])
def test_two_laser_topics_read_into_one_set_of_scans(tmp_path, ros_version, capsys):
    # A front laser (3 beams) and a rear one (2 beams, mounted backwards) on their own
    # topics: one time-ordered set of scans, each placed by its own frame.
    bag = _Bag(ros_version)
    bag.tf(0.0, "base_link", "front", (0.3, 0.0, 0.2), static=True)
    bag.tf(0.0, "base_link", "rear", (-0.3, 0.0, 0.2), yaw=np.pi, static=True)
    bag.tf(0.0, "map", "base_link", (0.0, 0.0, 0.0))
    bag.tf(1.0, "map", "base_link", (1.0, 0.0, 0.0))
    bag.scan(0.25, [1.0, 2.0, 3.0], frame="front", topic="/front_scan")
    bag.scan(0.5, [1.5, 2.5], frame="rear", topic="/rear_scan", range_max=4.0)
    bag.scan(0.75, [1.0, 2.0, 3.0], frame="front", topic="/front_scan")
    path = bag.write(_bag_path(tmp_path, ros_version))
    scans = load_rosbag(path, ["/front_scan", "/rear_scan"])
    np.testing.assert_allclose(scans.timestamps, [0.25, 0.5, 0.75])
    np.testing.assert_allclose(scans.poses[:, :2], [[0.55, 0.0], [0.2, 0.0], [1.05, 0.0]],
                               atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(_wrap(scans.poses[:, 2] - [0.0, np.pi, 0.0]), 0.0, atol=1e-12)
    assert scans.max_range == 4.0  # the rear laser's range_max
    np.testing.assert_array_equal(scans.ranges[1], [1.5, 1.5, 2.5])  # 2 beams fill 3 slots
    np.testing.assert_array_equal(scans.ranges[[0, 2]], [[1.0, 2.0, 3.0]] * 2)
    with pytest.raises(ValueError, match="no scan topic '/side_scan'"):
        load_rosbag(path, ["/front_scan", "/side_scan"])
    for bad in ([], [None], 3):
        with pytest.raises(ValueError, match="scan_topic must be a topic name or a sequence"):
            load_rosbag(path, bad)
    # The command line takes --scan-topic once per topic.
    from skoccmap._cmd_map import load_scans
    from skoccmap.cli import build_parser

    argv = ["map", str(path), "--scan-topic", "/front_scan", "--scan-topic", "/rear_scan"]
    assert len(load_scans(build_parser().parse_args(argv))) == 3
    assert load_scans(build_parser().parse_args(argv[:4])).n_beams == 3
    assert f"{path}: 2 scans x 3 beams" in capsys.readouterr().out


def test_scans_with_different_beam_counts(tmp_path):
    bag = _Bag(1)
    bag.tf(0.0, "map", "laser", (0.0, 0.0, 0.0))
    bag.tf(2.0, "map", "laser", (0.0, 0.0, 0.0))
    bag.scan(0.5, [1.0, 2.0, 3.0, 4.0], angle_min=-0.3, increment=0.2)
    bag.scan(1.0, [1.5, 2.5], angle_min=-1.0, increment=2.0)
    scans = load_rosbag(bag.write(tmp_path / "b.bag"))
    assert scans.ranges.shape == (2, 4) and scans.angles.shape == (2, 4)
    np.testing.assert_allclose(scans.angles[0], [-0.3, -0.1, 0.1, 0.3], atol=1e-6)
    np.testing.assert_allclose(scans.angles[1], [-1.0, -1.0, 1.0, 1.0], atol=1e-6)
    np.testing.assert_array_equal(scans.ranges[1], [1.5, 1.5, 2.5, 2.5])


# --------------------------------------------------------------------------------------------
# Errors name what the bag has
# --------------------------------------------------------------------------------------------


@pytest.fixture
def small_bag(tmp_path):
    bag = _Bag(2)
    bag.tf(0.0, "map", "odom", (0.0, 0.0, 0.0), static=True)
    bag.tf(0.0, "odom", "laser", (0.0, 0.0, 0.0))
    bag.tf(1.0, "odom", "laser", (1.0, 0.0, 0.0))
    bag.scan(0.5, [1.0, 2.0, 3.0], topic="/front_scan")
    bag.odometry(0.5, (0.0, 0.0, 0.0), 0.0)
    return bag.write(tmp_path / "small")


def test_missing_scan_topic_names_the_topics(small_bag):
    with pytest.raises(ValueError, match=r"no scan topic '/scan'.*/front_scan \(sensor_msgs"):
        load_rosbag(small_bag)
    assert len(load_rosbag(small_bag, "/front_scan")) == 1


def test_missing_frame_names_the_frames(small_bag):
    with pytest.raises(ValueError, match=r"\['world'\] are not in them.*'laser', 'map', 'odom'"):
        load_rosbag(small_bag, "/front_scan", map_frame="world")
    odom = load_rosbag(small_bag, "/front_scan", map_frame="odom")
    np.testing.assert_allclose(odom.poses, [[0.5, 0.0, 0.0]])


def test_wrong_types_and_missing_pose_topic(small_bag):
    with pytest.raises(ValueError, match=r"'/odom' carries nav_msgs/msg/Odometry"):
        load_rosbag(small_bag, "/odom")
    with pytest.raises(ValueError, match=r"no pose topic '/pose'.*/odom \(nav_msgs"):
        load_rosbag(small_bag, "/front_scan", pose_topic="/pose")
    with pytest.raises(ValueError, match="pose='topic' needs pose_topic"):
        load_rosbag(small_bag, "/front_scan", pose="topic")


def test_laser_frame_overrides_the_scans_frame(tmp_path):
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (1.0, 2.0, 0.0), yaw=0.5, static=True)
    bag.scan(0.5, [1.0, 2.0, 3.0], frame="")
    path = bag.write(tmp_path / "b")
    with pytest.raises(ValueError, match=r"scans' frame ''.*frames present: \['laser', 'map'\]"):
        load_rosbag(path)
    np.testing.assert_allclose(load_rosbag(path, laser_frame="laser").poses, [[1.0, 2.0, 0.5]])
    # Frame arguments with ROS 1's leading slash name the same frames.
    scans = load_rosbag(path, laser_frame="/laser", map_frame="/map")
    np.testing.assert_allclose(scans.poses, [[1.0, 2.0, 0.5]])


@pytest.mark.parametrize("angle_min, increment", [(-0.5, 0.0), (-0.5, np.nan), (np.inf, 0.1)])
def test_scans_without_beam_directions_are_refused(tmp_path, angle_min, increment):
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (0.0, 0.0, 0.0), static=True)
    bag.scan(0.5, [1.0, 2.0, 3.0], angle_min=angle_min, increment=increment)
    with pytest.raises(ValueError, match=r"LaserScan on '/scan' at 0.5.* no directions"):
        load_rosbag(bag.write(tmp_path / "b"))


@pytest.mark.parametrize("max_range", [None, 4.0])
def test_a_scan_whose_range_min_exceeds_its_range_max_is_refused(tmp_path, max_range):
    # range_min 3 > range_max 1: the returns at 1.5 and 2.5 m lie above range_max (no
    # return) and the one at 0.5 m below range_min (dropped): the scan would be read as
    # free space through the walls it hit.
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (0.0, 0.0, 0.0), static=True)
    bag.scan(0.5, [1.0, 2.0, 3.0], range_min=0.1, range_max=5.0)
    bag.scan(0.7, [1.5, 2.5, 0.5], range_min=3.0, range_max=1.0)
    with pytest.raises(ValueError, match=r"at 0.700000000 s has range_min 3 above range_max 1"):
        load_rosbag(bag.write(tmp_path / "b"), max_range=max_range)


@pytest.mark.parametrize("xyz, yaw", [((np.nan, 0.0, 0.0), 0.0), ((0.0, 0.0, 0.0), np.nan)])
def test_transform_samples_that_place_nothing_are_left_out(tmp_path, xyz, yaw):
    # One bad sample on the laser's own chain, one on a frame no scan uses: the scan between
    # two good samples is placed as without them, as tf2 leaves such samples out.
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", xyz, yaw=yaw)
    bag.tf(0.1, "base_link", "camera", xyz, yaw=yaw)
    bag.tf(10.0, "map", "laser", (0.0, 0.0, 0.0))
    bag.tf(10.2, "map", "laser", (2.0, 0.0, 0.0))
    bag.scan(10.1, [1.0, 2.0, 3.0])
    with pytest.warns(UserWarning, match=r"left out 2 transform sample.*map -> laser at 0.0") as w:
        scans = load_rosbag(bag.write(tmp_path / "b"))
    assert [warning.filename for warning in w] == [__file__]  # the caller's line
    np.testing.assert_allclose(scans.poses, [[1.0, 0.0, 0.0]], atol=1e-9)


def test_bag_without_transforms_asks_for_a_pose_topic(tmp_path):
    bag = _Bag(2)
    bag.scan(0.5, [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match=r"no transform topic.*pose_topic="):
        load_rosbag(bag.write(tmp_path / "b"))


def test_not_a_bag(tmp_path):
    log = tmp_path / "run.log"
    log.write_text("FLASER 2 1 1 0 0 0 0 0 0 0 h 0\n")
    assert not is_rosbag(log)
    with pytest.raises(ValueError, match="is not a ROS bag"):
        load_rosbag(log)
    with pytest.raises(FileNotFoundError):
        load_rosbag(tmp_path / "missing.bag")
    # A log renamed .bag (or a damaged bag) used to raise rosbags' own AnyReaderError.
    for name in ("fake.bag", "fake.mcap"):
        fake = tmp_path / name
        fake.write_text("FLASER 2 1 1 0 0 0 0 0 0 0 h 0\n")
        with pytest.raises(ValueError, match="cannot be read as a ROS bag"):
            load_rosbag(fake)


def test_missing_rosbags_says_how_to_install(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "rosbags", None)
    with pytest.raises(ImportError, match=r'pip install "skoccmap\[ros\]"'):
        load_rosbag(tmp_path / "x.bag")
    grid = OccupancyGrid([[0.5]], origin=(0.0, 0.0), resolution=1.0)
    with pytest.raises(ImportError, match=r'pip install "skoccmap\[ros\]"'):
        grid.to_ros_message()


# --------------------------------------------------------------------------------------------
# Maps out
# --------------------------------------------------------------------------------------------


@pytest.fixture
def grid():
    probability = np.array([[0.0, 0.1, 0.3], [0.6, 0.9, 1.0]])
    unknown = np.array([[False, False, False], [False, False, True]])
    return OccupancyGrid(probability, origin=(-2.0, 3.5), resolution=0.25, unknown=unknown)


@pytest.mark.parametrize("ros_version, storage", FORMATS, ids=FORMAT_IDS)
@pytest.mark.parametrize("trinary", [False, True])
def test_map_round_trip_on_a_latched_topic(grid, tmp_path, ros_version, storage, trinary):
    path = grid.write_rosbag(_bag_path(tmp_path, ros_version, "map"), frame_id="world",
                             trinary=trinary, stamp=12.5, ros_version=ros_version,
                             storage=storage)  # fmt: skip
    with AnyReader([path]) as reader:
        (conn,) = reader.connections
        ((_, stamp, raw),) = list(reader.messages())
        msg = reader.deserialize(raw, conn.msgtype)
    assert conn.topic == "/map" and conn.msgtype == "nav_msgs/msg/OccupancyGrid"
    if ros_version == 1:
        assert conn.ext.latching == 1
    else:
        (qos,) = conn.ext.offered_qos_profiles
        assert qos.durability == QosDurability.TRANSIENT_LOCAL
        assert qos.reliability == QosReliability.RELIABLE
        assert (qos.history, qos.depth) == (QosHistory.KEEP_LAST, 1)
    assert stamp == 12_500_000_000
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (
        12, 500_000_000, "world")  # fmt: skip
    assert (msg.info.width, msg.info.height, msg.info.resolution) == (3, 2, 0.25)
    origin = msg.info.origin
    assert (origin.position.x, origin.position.y, origin.orientation.w) == (-2.0, 3.5, 1.0)
    expected = [0, 0, -1, -1, 100, -1] if trinary else [0, 10, 30, 60, 90, -1]
    np.testing.assert_array_equal(msg.data, expected)


def test_map_bag_takes_the_trinary_thresholds(grid, tmp_path):
    path = grid.write_rosbag(tmp_path / "map", trinary=True, stamp=1.0, free_threshold=0.35,
                             occupied_threshold=0.95)  # fmt: skip
    with AnyReader([path]) as reader:
        ((conn, _, raw),) = list(reader.messages())
        msg = reader.deserialize(raw, conn.msgtype)
    np.testing.assert_array_equal(msg.data, [0, 0, 0, -1, -1, -1])
    message = grid.to_ros_message(trinary=True, stamp=1.0, free_threshold=0.35,
                                  occupied_threshold=0.95)  # fmt: skip
    np.testing.assert_array_equal(message.data, msg.data)


@pytest.mark.parametrize("ros_version", [1, 2])
def test_a_map_bag_is_written_into_folders_made_for_it(grid, tmp_path, ros_version):
    path = grid.write_rosbag(_bag_path(tmp_path / "new" / "maps", ros_version, "map"),
                             stamp=1.0, ros_version=ros_version)  # fmt: skip
    with AnyReader([path]) as reader:
        ((conn, _, raw),) = list(reader.messages())
        assert reader.deserialize(raw, conn.msgtype).info.width == 3


def test_to_ros_message_matches_the_fields(grid):
    for ros_version in (1, 2):
        msg = grid.to_ros_message(stamp=1.0, ros_version=ros_version)
        fields = grid.to_ros_occupancy_grid()
        np.testing.assert_array_equal(msg.data, fields["data"])
        assert msg.data.dtype == np.int8 and msg.info.map_load_time.sec == 1
    with pytest.raises(ValueError, match="3-D"):
        OccupancyGrid(np.zeros((2, 2, 2)), origin=(0, 0, 0), resolution=1.0).to_ros_message()


def test_writers_refuse_bad_arguments(grid, paper_scans, tmp_path):
    scans, _ = paper_scans
    path = grid.write_rosbag(tmp_path / "map", stamp=0.0)
    with pytest.raises(FileExistsError):
        grid.write_rosbag(path, stamp=0.0)
    with pytest.raises(ValueError, match="ros_version must be 1 or 2"):
        grid.write_rosbag(tmp_path / "other", ros_version=3)
    with pytest.raises(ValueError, match=r"\.bag file"):
        write_rosbag(scans, tmp_path / "scans", ros_version=1)
    for topic in ("map with space", "", "/map/", "//map", "/2d_map", 5):
        with pytest.raises(ValueError, match="must be a ROS topic name"):
            grid.write_rosbag(tmp_path / "named", topic=topic)
        with pytest.raises(ValueError, match="scan_topic must be a ROS topic name"):
            write_rosbag(scans, tmp_path / "named", scan_topic=topic)
        assert not (tmp_path / "named").exists()
    for name in ("scans.bag", "scans.db3", "scans.mcap"):
        # A ROS 2 bag is a directory: so named, it would not read back.
        with pytest.raises(ValueError, match="a ROS 2 bag is a directory"):
            write_rosbag(scans, tmp_path / name, ros_version=2)
        assert not (tmp_path / name).exists()
    uneven_angles = scans.angles * np.abs(scans.angles) / np.pi  # within the same turn
    uneven = Scans(scans.poses, scans.ranges, uneven_angles, scans.max_range)
    with pytest.raises(ValueError, match="evenly spaced"):
        write_rosbag(uneven, tmp_path / "uneven")


# --------------------------------------------------------------------------------------------
# The command line
# --------------------------------------------------------------------------------------------


def test_cli_maps_a_bag(paper_scans, tmp_path, capsys):
    scans, data = paper_scans
    bag = write_rosbag(scans, tmp_path / "paper_bag", storage="mcap")
    out = tmp_path / "out"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc = main(["map", str(bag), "--scan-topic", "/scan", "--resolution", "0.5",
                   "--out", str(out), "--quiet"])  # fmt: skip
    assert rc == 0
    assert not [w for w in caught if "skipped" in str(w.message)]  # every scan has a pose
    assert f"{bag}: 26 scans x 17 beams, max range 8 m" in capsys.readouterr().out
    grid = OccupancyGrid.load(out / "paper_bag.npz")
    assert (out / "paper_bag.yaml").is_file()
    truth = data.environment.ground_truth_grid(0.5, extent=grid.extent, scans=data.scans)
    observed = truth.observed
    auc = roc_auc_score(truth.occupied[observed], grid.probability.ravel()[observed])
    assert auc > 0.85


def test_cli_bag_options_reach_the_reader(small_bag, capsys):
    assert main(["map", str(small_bag), "--quiet"]) == 2
    assert "no scan topic '/scan'" in capsys.readouterr().err
    argv = ["map", str(small_bag), "--scan-topic", "/front_scan", "--pose-topic", "/pose"]
    assert main(argv) == 2
    assert "no pose topic '/pose'" in capsys.readouterr().err
    # A CARMEN log's option, given with a bag, was ignored.
    assert main(["map", str(small_bag), "--skip-bad-lines", "--quiet"]) == 2
    assert "--skip-bad-lines applies only to CARMEN logs" in capsys.readouterr().err
    argv = ["map", str(small_bag), "--scan-topic", "/front_scan", "--map-frame", "world"]
    assert main(argv) == 2
    assert "['world'] are not in them" in capsys.readouterr().err


def test_cli_base_and_laser_frames_reach_the_reader(tmp_path, capsys):
    # Odometry of the laser itself, and scans whose header names a frame nothing knows.
    bag = _Bag(2)
    bag.odometry(0.0, (0.0, 0.0, 0.0), 0.0)
    bag.odometry(10.0, (2.0, 0.0, 0.0), 0.0)
    for t in range(1, 10):
        bag.scan(float(t), [1.0, 2.0, 3.0, 2.5, 1.5], frame="unnamed")
    path = bag.write(tmp_path / "b")
    out = tmp_path / "out"
    argv = ["map", str(path), "--pose-topic", "/odom", "--resolution", "0.5", "--out", str(out),
            "--quiet"]  # fmt: skip
    assert main(argv) == 2
    assert "Pass --base-frame 'unnamed' if the pose topic" in capsys.readouterr().err
    assert main([*argv, "--laser-frame", "laser"]) == 2
    assert "Pass --base-frame 'laser' if the pose topic" in capsys.readouterr().err
    assert main([*argv, "--laser-frame", "laser", "--base-frame", "laser"]) == 0
    assert f"{path}: 9 scans x 5 beams" in capsys.readouterr().out
    assert (out / "b.npz").is_file()


def test_cli_level_tolerance_maps_a_tilted_laser(tmp_path, capsys):
    # A laser rolled by 0.05 rad: 3-D poses at the default tolerance, which the command
    # refuses with the way out; --level-tolerance projects its scans onto the plane.
    bag = _Bag(2)
    for stamp in (0.0, 10.0):
        bag.tf(stamp, "map", "laser", (stamp / 5.0, 0.0, 0.4), roll=0.05)
    for t in range(1, 10):
        bag.scan(float(t), [1.0, 2.0, 3.0, 2.5, 1.5])
    path = bag.write(tmp_path / "b")
    argv = ["map", str(path), "--resolution", "0.5", "--out", str(tmp_path / "out"), "--quiet"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "not level (3-D poses) within --level-tolerance 0.01 rad" in err
    assert "A larger --level-tolerance projects the scans" in err
    assert main([*argv, "--level-tolerance", "0.1"]) == 0
    assert f"{path}: 9 scans x 5 beams" in capsys.readouterr().out
    # The transforms give the laser's own pose: a base frame would be ignored.
    assert main([*argv, "--base-frame", "base_link"]) == 2
    assert "--base-frame applies only to poses read from a topic" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("ros_version", "timestamps"),
    [
        (1, [-2.0, -1.0]),
        (1, [1.7e12, 1.7e12 + 0.1]),
        (2, [1.7e12, 1.7e12 + 0.1]),
        (2, [-2.0, -1.0]),
    ],
)
def test_write_rosbag_refuses_times_a_bag_cannot_hold(tmp_path, ros_version, timestamps):
    # ROS 1 stamps are unsigned 32-bit seconds, ROS 2 signed: milliseconds by mistake or
    # negative times failed inside rosbags and left a half-written bag behind.
    scans = Scans(poses=[[0.0, 0.0, 0.0], [5.0, 5.0, 1.0]], ranges=[[1.0, 2.0, 3.0]] * 2,
                  angles=[-0.1, 0.0, 0.1], max_range=4.0, timestamps=timestamps)  # fmt: skip
    path = _bag_path(tmp_path, ros_version)
    with pytest.raises(ValueError, match=f"for a ROS {ros_version} bag.*not milliseconds"):
        write_rosbag(scans, path, ros_version=ros_version)
    assert not path.exists()


def test_write_rosbag_refuses_two_poses_at_one_stamp(tmp_path):
    # One transform per stamp: scan 0 read back in scan 1's pose.
    scans = Scans(poses=[[0.0, 0.0, 0.0], [5.0, 5.0, 1.0], [10.0, 0.0, 2.0]],
                  ranges=[[1.0, 2.0, 3.0]] * 3, angles=[-0.1, 0.0, 0.1], max_range=4.0,
                  timestamps=[1.0, 1.0, 2.0])  # fmt: skip
    with pytest.raises(ValueError, match="scans 0 and 1 share the timestamp 1 s"):
        write_rosbag(scans, tmp_path / "dup")
    assert not (tmp_path / "dup").exists()
    # The same pose twice is one transform: fine.
    still = Scans(poses=[[0.0, 0.0, 0.0]] * 2, ranges=[[1.0, 2.0, 3.0]] * 2,
                  angles=[-0.1, 0.0, 0.1], max_range=4.0, timestamps=[1.0, 1.0])  # fmt: skip
    back = load_rosbag(write_rosbag(still, tmp_path / "still"))
    np.testing.assert_allclose(back.poses, still.poses)


def test_a_failed_write_leaves_no_bag(tmp_path, monkeypatch):
    import skoccmap.datasets._rosbag as rosbag_module

    def fail(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(rosbag_module, "_transform_stamped", fail)
    scans = Scans(poses=[[0.0, 0.0, 0.0]], ranges=[[1.0, 2.0, 3.0]], angles=[-0.1, 0.0, 0.1],
                  max_range=4.0)  # fmt: skip
    for ros_version in (1, 2):
        path = _bag_path(tmp_path, ros_version)
        with pytest.raises(RuntimeError, match="disk full"):
            write_rosbag(scans, path, ros_version=ros_version)
        assert not path.exists()


def test_a_grid_at_a_negative_stamp_is_refused_and_leaves_no_bag(tmp_path):
    # mcap keeps unsigned times: rosbags failed inside its writer, and the failed close
    # left the half-written bag behind.
    grid = OccupancyGrid([[0.1, 0.9]], origin=(0.0, 0.0), resolution=1.0)
    for storage in ("sqlite3", "mcap"):
        path = tmp_path / storage
        with pytest.raises(ValueError, match="stamp must lie in"):
            grid.write_rosbag(path, stamp=-1.0, storage=storage)
        assert not path.exists()


def test_a_stamp_that_is_no_number_is_named(tmp_path):
    # Before: numpy's "ufunc 'isfinite' not supported" for a string.
    grid = OccupancyGrid([[0.1, 0.9]], origin=(0.0, 0.0), resolution=1.0)
    for stamp in ("1", True, [1.0]):
        with pytest.raises(TypeError, match="stamp must be a time in seconds"):
            grid.to_ros_message(stamp=stamp)
        with pytest.raises(TypeError, match="stamp must be a time in seconds"):
            grid.write_rosbag(tmp_path / "b", stamp=stamp)
        assert not (tmp_path / "b").exists()


def test_a_write_whose_close_fails_leaves_no_bag(tmp_path, monkeypatch):
    from rosbags.rosbag2 import Writer

    def fail(self):
        raise OSError("close failed")

    monkeypatch.setattr(Writer, "close", fail)
    grid = OccupancyGrid([[0.1, 0.9]], origin=(0.0, 0.0), resolution=1.0)
    with pytest.raises(OSError, match="close failed"):
        grid.write_rosbag(tmp_path / "m", stamp=1.0)
    assert not (tmp_path / "m").exists()


# --------------------------------------------------------------------------------------------
# Transforms: composition in 3-D, repeated stamps, static and dynamic samples of one edge
# --------------------------------------------------------------------------------------------


def _rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_tf_chain_composes_rotations_about_different_axes(tmp_path):
    # A turned robot carrying a rolled laser: the laser's orientation is R_z(yaw) R_x(roll),
    # not R_x(roll) R_z(yaw) (rotations about z alone would not tell the two apart).
    bag = _Bag(2)
    bag.tf(0.0, "base_link", "laser", (0.2, 0.1, 0.3), roll=0.3, static=True)
    for stamp in (0.0, 1.0):
        bag.tf(stamp, "map", "base_link", (1.0, 2.0, 0.0), yaw=0.5)
    bag.scan(0.5, [1.0, 2.0, 3.0])  # angles -0.5, 0, 0.5
    scans = load_rosbag(bag.write(tmp_path / "b"))
    assert scans.n_dims == 3
    rotation = _rot_z(0.5) @ _rot_x(0.3)
    position = np.array([1.0, 2.0, 0.0]) + _rot_z(0.5) @ np.array([0.2, 0.1, 0.3])
    angles = np.array([-0.5, 0.0, 0.5])
    beams = np.column_stack([np.cos(angles), np.sin(angles), np.zeros(3)])
    expected = position + np.array([1.0, 2.0, 3.0])[:, None] * (beams @ rotation.T)
    np.testing.assert_allclose(scans.hit_points(), expected, atol=1e-6)


def test_tf_chain_composes_two_tilted_rotations(tmp_path):
    # A rolled base carrying a laser that is turned and rolled too: both rotations of the
    # chain have x and y components, and the laser's orientation is R_x(0.4) R_z(0.7) R_x(0.3).
    bag = _Bag(2)
    bag.tf(0.0, "base_link", "laser", (0.2, 0.1, 0.3), yaw=0.7, roll=0.3, static=True)
    for stamp in (0.0, 1.0):
        bag.tf(stamp, "map", "base_link", (1.0, 2.0, 0.5), roll=0.4)
    bag.scan(0.5, [1.0, 2.0, 3.0])  # angles -0.5, 0, 0.5
    scans = load_rosbag(bag.write(tmp_path / "b"))
    assert scans.n_dims == 3
    rotation = _rot_x(0.4) @ _rot_z(0.7) @ _rot_x(0.3)
    position = np.array([1.0, 2.0, 0.5]) + _rot_x(0.4) @ np.array([0.2, 0.1, 0.3])
    angles = np.array([-0.5, 0.0, 0.5])
    beams = np.column_stack([np.cos(angles), np.sin(angles), np.zeros(3)])
    expected = position + np.array([1.0, 2.0, 3.0])[:, None] * (beams @ rotation.T)
    np.testing.assert_allclose(scans.hit_points(), expected, atol=1e-6)


def test_a_stamp_sent_twice_keeps_its_last_sample(tmp_path):
    # The transform at t=1 is sent again (recorded later) with a corrected translation; tf2
    # keeps the last one sent.
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (0.0, 0.0, 0.0))
    bag.tf(1.0, "map", "laser", (5.0, 0.0, 0.0))
    bag.tf(1.0, "map", "laser", (1.0, 0.0, 0.0))
    topic, msgtype, _, message = bag.messages[-1]
    bag.messages[-1] = (topic, msgtype, 1.5, message)  # recorded at 1.5, stamped 1.0
    bag.scan(0.5, [1.0, 2.0, 3.0])
    scans = load_rosbag(bag.write(tmp_path / "b"))
    np.testing.assert_allclose(scans.poses, [[0.5, 0.0, 0.0]], atol=1e-12)


def test_a_republished_static_transform_replaces_the_first(tmp_path):
    bag = _Bag(2)
    bag.tf(0.0, "base_link", "laser", (0.1, 0.0, 0.0), static=True)
    bag.tf(0.2, "base_link", "laser", (0.3, 0.0, 0.0), static=True)  # the corrected offset
    for stamp in (0.0, 2.0):
        bag.tf(stamp, "map", "base_link", (1.0, 0.0, 0.0))
    bag.scan(1.0, [1.0, 2.0, 3.0])
    scans = load_rosbag(bag.write(tmp_path / "b"))
    np.testing.assert_allclose(scans.poses, [[1.3, 0.0, 0.0]], atol=1e-12)


def test_tf_static_fixes_an_edge_whatever_tf_says(tmp_path):
    # On /tf_static before /tf: the /tf samples are left out. On /tf before /tf_static:
    # the static transform replaces them, at every time.
    for first_static in (True, False):
        bag = _Bag(2)
        if first_static:
            bag.tf(0.0, "map", "laser", (1.0, 2.0, 0.0), yaw=0.5, static=True)
        bag.tf(0.1, "map", "laser", (5.0, 0.0, 0.0))
        bag.tf(1.0, "map", "laser", (6.0, 0.0, 0.0))
        if not first_static:
            bag.tf(1.5, "map", "laser", (1.0, 2.0, 0.0), yaw=0.5, static=True)
        bag.scan(0.5, [1.0, 2.0, 3.0])
        bag.scan(3.0, [1.0, 2.0, 3.0])  # after the /tf samples
        scans = load_rosbag(bag.write(tmp_path / f"b{first_static}"))
        np.testing.assert_allclose(scans.poses, [[1.0, 2.0, 0.5]] * 2, atol=1e-12)


def test_a_dynamic_laser_offset_limits_the_scans_of_a_pose_topic(tmp_path):
    # The pose topic covers both scans; the base_link -> laser offset on /tf only the first:
    # the second is skipped, not placed with an extrapolated offset.
    bag = _Bag(2)
    bag.odometry(0.0, (0.0, 0.0, 0.0), 0.0)
    bag.odometry(10.0, (10.0, 0.0, 0.0), 0.0)
    bag.tf(0.0, "base_link", "laser", (0.5, 0.0, 0.0))
    bag.tf(1.0, "base_link", "laser", (0.5, 0.0, 0.0))
    bag.scan(0.5, [1.0, 2.0, 3.0])
    bag.scan(5.0, [1.0, 2.0, 3.0])
    match = r"skipped 1 of 2 scans .*outside the time range of their poses \[0, 1\] s"
    with pytest.warns(UserWarning, match=match):
        scans = load_rosbag(bag.write(tmp_path / "b"), pose_topic="/odom")
    np.testing.assert_allclose(scans.poses, [[1.0, 0.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(scans.timestamps, [0.5])


def test_a_zero_quaternion_places_nothing(tmp_path):
    # ROS 1's default Quaternion is all zeros: such a sample is left out, not interpolated.
    bag = _Bag(2)
    bag.tf(10.0, "map", "laser", (0.0, 0.0, 0.0))
    bag.tf(10.1, "map", "laser", (7.0, 0.0, 0.0))
    bag.tf(10.2, "map", "laser", (2.0, 0.0, 0.0))
    zero = bag.store.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=0.0)
    bag.messages[1][3].transforms[0].transform.rotation = zero
    bag.scan(10.05, [1.0, 2.0, 3.0])
    with pytest.warns(UserWarning, match=r"left out 1 transform sample.*map -> laser at 10.1"):
        scans = load_rosbag(bag.write(tmp_path / "b"))
    np.testing.assert_allclose(scans.poses, [[0.5, 0.0, 0.0]], atol=1e-9)


def test_scans_come_back_in_header_stamp_order(tmp_path):
    # Recorded in the other order (a driver's buffer): the header stamps decide.
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (0.0, 0.0, 0.0))
    bag.tf(4.0, "map", "laser", (4.0, 0.0, 0.0))
    bag.scan(3.0, [3.0, 3.0, 3.0])
    bag.scan(1.0, [1.0, 1.0, 1.0])
    topic, msgtype, _, message = bag.messages[-2]
    bag.messages[-2] = (topic, msgtype, 0.5, message)  # stamped 3.0, recorded first
    scans = load_rosbag(bag.write(tmp_path / "b"))
    np.testing.assert_allclose(scans.timestamps, [1.0, 3.0])
    np.testing.assert_allclose(scans.poses, [[1.0, 0.0, 0.0], [3.0, 0.0, 0.0]], atol=1e-12)
    np.testing.assert_array_equal(scans.ranges, [[1.0] * 3, [3.0] * 3])


# --------------------------------------------------------------------------------------------
# Readings: the limits themselves
# --------------------------------------------------------------------------------------------


def test_readings_at_range_min_and_range_max_are_hits(tmp_path):
    # REP 117: range_min <= r <= range_max is a valid measurement; with a max_range above
    # the laser's range_max, a reading of range_max is a hit like any other.
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (0.0, 0.0, 0.0), static=True)
    bag.scan(0.5, [0.1, 1.0, 5.0], range_min=0.1, range_max=5.0)  # float32 0.1 both times
    with pytest.warns(UserWarning, match="max_range=6 is beyond the range_max"):
        scans = load_rosbag(bag.write(tmp_path / "b"), max_range=6.0)
    np.testing.assert_allclose(scans.angles, [-0.5, 0.0, 0.5], atol=1e-6)
    np.testing.assert_allclose(scans.ranges, [[0.1, 1.0, 5.0]], atol=1e-6)


def test_equal_range_limits_keep_the_reading_between_them(tmp_path):
    # range_min == range_max is not a swapped pair: a reading at that value is a hit, one
    # below is dropped, one above is a beam without a return.
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (0.0, 0.0, 0.0), static=True)
    bag.scan(0.5, [2.0, 1.0, 3.0], range_min=2.0, range_max=2.0)
    with pytest.warns(UserWarning, match="max_range=6 is beyond the range_max"):
        scans = load_rosbag(bag.write(tmp_path / "b"), max_range=6.0)
    np.testing.assert_allclose(scans.angles, [-0.5, 0.5], atol=1e-6)
    np.testing.assert_array_equal(scans.ranges, [[2.0, np.inf]])


def test_max_range_is_the_smallest_range_max_stated(tmp_path):
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (0.0, 0.0, 0.0), static=True)
    bag.scan(0.5, [1.0, 6.0, 2.0], range_max=8.0)
    bag.scan(1.0, [1.0, 4.0, 2.0], range_max=5.0)
    scans = load_rosbag(bag.write(tmp_path / "b"))
    assert scans.max_range == 5.0
    # The 6 m reading of the 8 m laser reaches the map's maximum range: no return.
    np.testing.assert_array_equal(scans.ranges, [[1.0, np.inf, 2.0], [1.0, 4.0, 2.0]])


# --------------------------------------------------------------------------------------------
# Writing scans: the fields a ROS tool reads
# --------------------------------------------------------------------------------------------


def test_written_laser_scans_state_their_last_beam_and_exact_stamps(tmp_path):
    angles = np.linspace(-0.6, 0.6, 5)
    scans = Scans(poses=[[0.0, 0.0, 0.0], [1.0, 0.0, 0.5]], ranges=[[1.0] * 5] * 2,
                  angles=angles, max_range=4.0, timestamps=[1.001, 2.001])  # fmt: skip
    path = write_rosbag(scans, tmp_path / "b")
    with AnyReader([path]) as reader:
        (conn,) = [c for c in reader.connections if c.topic == "/scan"]
        messages = [reader.deserialize(raw, conn.msgtype)
                    for _, _, raw in reader.messages(connections=[conn])]  # fmt: skip
    assert len(messages) == 2
    for msg, sec in zip(messages, (1, 2), strict=True):
        # angle_max is the angle of the last beam (sensor_msgs/LaserScan).
        np.testing.assert_allclose(msg.angle_min, -0.6, atol=1e-6)
        np.testing.assert_allclose(msg.angle_max, 0.6, atol=1e-6)
        np.testing.assert_allclose(msg.angle_increment, 0.3, atol=1e-6)
        # 1.001 s is 1 s and 1 000 000 ns (1.001 * 1e9 is 1000999999.9999999 in floats).
        assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (sec, 1_000_000)


def test_write_rosbag_refuses_ros2_times_past_2_to_the_31(tmp_path):
    # ROS 2 stamps are signed 32-bit seconds.
    scans = Scans(poses=[[0.0, 0.0, 0.0], [5.0, 5.0, 1.0]], ranges=[[1.0, 2.0, 3.0]] * 2,
                  angles=[-0.1, 0.0, 0.1], max_range=4.0, timestamps=[3e9, 3e9 + 1])  # fmt: skip
    with pytest.raises(ValueError, match="for a ROS 2 bag.*got 3e"):
        write_rosbag(scans, tmp_path / "late", ros_version=2)
    assert not (tmp_path / "late").exists()


@pytest.mark.parametrize("seconds", [2.0**31, 3e9])
def test_ros1_bags_refuse_times_from_2_to_the_31_with_a_value_error(tmp_path, seconds):
    # ROS 1 times are unsigned, but the rosbags writer packs their seconds as a signed
    # 32-bit integer: past 2**31 s it failed with a struct.error inside rosbags.
    scans = Scans(poses=[[0.0, 0.0, 0.0]], ranges=[[1.0, 2.0, 3.0]], angles=[-0.1, 0.0, 0.1],
                  max_range=4.0, timestamps=[seconds])  # fmt: skip
    with pytest.raises(ValueError, match=r"\[0, 2147483648\) seconds for a ROS 1 bag"):
        write_rosbag(scans, tmp_path / "late.bag", ros_version=1)
    assert not (tmp_path / "late.bag").exists()
    grid = OccupancyGrid([[0.1, 0.9]], origin=(0.0, 0.0), resolution=1.0)
    with pytest.raises(ValueError, match="stamp must lie in"):
        grid.write_rosbag(tmp_path / "map.bag", stamp=seconds, ros_version=1)
    # The last second that fits is written and read back.
    last = Scans(poses=[[0.0, 0.0, 0.0]], ranges=[[1.0, 2.0, 3.0]], angles=[-0.1, 0.0, 0.1],
                 max_range=4.0, timestamps=[2.0**31 - 1])  # fmt: skip
    back = load_rosbag(write_rosbag(last, tmp_path / "last.bag", ros_version=1))
    assert back.timestamps.tolist() == [2.0**31 - 1]


def test_write_rosbag_refuses_two_headings_at_one_stamp(tmp_path):
    # Same place, different heading: still two poses at one time.
    scans = Scans(poses=[[1.0, 2.0, 0.0], [1.0, 2.0, 1.0]], ranges=[[1.0, 2.0, 3.0]] * 2,
                  angles=[-0.1, 0.0, 0.1], max_range=4.0, timestamps=[1.0, 1.0])  # fmt: skip
    with pytest.raises(ValueError, match="scans 0 and 1 share the timestamp 1 s"):
        write_rosbag(scans, tmp_path / "dup")
    assert not (tmp_path / "dup").exists()


def test_cli_max_range_reaches_the_bag_reader(tmp_path, capsys):
    from skoccmap._cmd_map import load_scans
    from skoccmap.cli import build_parser

    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (0.0, 0.0, 0.0), static=True)
    bag.scan(0.5, [1.0, 3.0, 2.0], range_max=5.0)
    path = bag.write(tmp_path / "b")
    args = build_parser().parse_args(["map", str(path), "--max-range", "2.5"])
    scans = load_scans(args)
    assert f"{path}: 1 scans x 3 beams, max range 2.5 m" in capsys.readouterr().out
    assert scans.max_range == 2.5
    np.testing.assert_array_equal(scans.ranges, [[1.0, np.inf, 2.0]])


# --------------------------------------------------------------------------------------------
# Mutation audit: behaviour the tests above left open
# --------------------------------------------------------------------------------------------


def test_a_folder_of_two_storage_files_is_refused(paper_scans, tmp_path):
    # Without metadata.yaml there is no telling which storage file is the bag.
    scans, _ = paper_scans
    folder = tmp_path / "two"
    folder.mkdir()
    for name in ("a", "b"):
        bag = write_rosbag(scans[:2], tmp_path / name, storage="mcap")
        (storage,) = bag.glob("*.mcap")
        storage.rename(folder / f"{name}.mcap")
    with pytest.raises(ValueError, match="no metadata.yaml and 2 storage files"):
        load_rosbag(folder)


def test_a_quaternion_written_to_four_decimals_is_normalised(tmp_path):
    # A hand-written transform facing +y, (w, z) = (0.7071, 0.7071), is 0.99999 long: read
    # as a unit quaternion it turns the laser offset without shrinking it.
    bag = _Bag(2)
    bag.tf(0.0, "map", "base_link", (1.0, 2.0, 0.0), static=True)
    bag.tf(0.0, "base_link", "laser", (0.5, 0.0, 0.0), static=True)
    rounded = bag.store.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.7071, w=0.7071)
    bag.messages[0][3].transforms[0].transform.rotation = rounded
    bag.scan(0.5, [1.0, 2.0, 3.0])
    scans = load_rosbag(bag.write(tmp_path / "b"))
    # The laser 0.5 m ahead of a robot at (1, 2) facing +y: at (1, 2.5), facing +y.
    np.testing.assert_allclose(scans.poses, [[1.0, 2.5, np.pi / 2]], atol=1e-12)


def test_a_stamp_sent_twice_keeps_its_last_sample_among_many(tmp_path):
    # 40 samples whose header stamps arrive out of order (a buffered publisher), the one at
    # 0.6 s sent again, corrected, after all the others: the correction is kept.
    bag = _Bag(2)
    order = np.random.default_rng(0).permutation(40)
    for k, index in enumerate(order):
        bag.tf(0.1 * index, "map", "laser", (0.0 if index != 6 else 5.0, 0.0, 0.0))
        topic, msgtype, _, message = bag.messages[-1]
        bag.messages[-1] = (topic, msgtype, 10.0 + 0.01 * k, message)  # recorded in this order
    bag.tf(0.6, "map", "laser", (0.0, 0.0, 0.0))
    topic, msgtype, _, message = bag.messages[-1]
    bag.messages[-1] = (topic, msgtype, 11.0, message)
    bag.scan(0.6, [1.0, 2.0, 3.0])
    scans = load_rosbag(bag.write(tmp_path / "b"))
    np.testing.assert_allclose(scans.poses, [[0.0, 0.0, 0.0]], atol=1e-12)


def test_a_single_transform_sample_is_not_extrapolated(tmp_path):
    # A dynamic transform seen once places a scan at its stamp, no other.
    bag = _Bag(2)
    bag.tf(1.0, "map", "laser", (1.0, 2.0, 0.0), yaw=0.5)
    bag.scan(1.0, [1.0, 2.0, 3.0])
    bag.scan(2.0, [1.0, 2.0, 3.0])
    match = r"skipped 1 of 2 scans .*poses \[1, 1\] s.*sampled once.*belongs on .*/tf_static"
    with pytest.warns(UserWarning, match=match):
        scans = load_rosbag(bag.write(tmp_path / "b"))
    np.testing.assert_allclose(scans.poses, [[1.0, 2.0, 0.5]], atol=1e-12)
    np.testing.assert_allclose(scans.timestamps, [1.0])


def test_a_single_beam_scan_needs_no_angle_increment(tmp_path):
    # One beam has a direction without an increment: angle_increment 0 is fine.
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (1.0, 0.0, 0.0), yaw=0.5, static=True)
    bag.scan(0.5, [2.0], angle_min=0.25, increment=0.0)
    scans = load_rosbag(bag.write(tmp_path / "b"))
    np.testing.assert_allclose(scans.angles, [0.25], atol=1e-6)
    np.testing.assert_allclose(
        scans.hit_points(), [[1.0 + 2.0 * np.cos(0.75), 2.0 * np.sin(0.75)]], atol=1e-6
    )


def test_a_pose_topic_that_changes_frames_is_refused(tmp_path):
    bag = _Bag(2)
    bag.tf(0.0, "base_link", "laser", (0.0, 0.0, 0.0), static=True)
    bag.odometry(0.0, (0.0, 0.0, 0.0), 0.0, frame="odom")
    bag.odometry(1.0, (1.0, 0.0, 0.0), 0.0, frame="map")  # localised half-way
    bag.scan(0.5, [1.0, 2.0, 3.0])
    path = bag.write(tmp_path / "b")
    with pytest.raises(
        ValueError, match=r"'/odom' changes frames \(header.frame_id \['map', 'odom'\]"
    ):
        load_rosbag(path, pose_topic="/odom")


def test_a_pose_topic_that_places_nothing_is_refused(tmp_path):
    # Odometry left at ROS 1's default, all-zero quaternion: no pose to interpolate.
    bag = _Bag(2)
    zero = bag.store.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=0.0)
    for stamp in (0.0, 1.0):
        bag.odometry(stamp, (stamp, 0.0, 0.0), 0.0, child="laser")
        bag.messages[-1][3].pose.pose.orientation = zero
    bag.scan(0.5, [1.0, 2.0, 3.0])
    path = bag.write(tmp_path / "b")
    with pytest.warns(UserWarning, match=r"left out 2 transform sample") as caught:
        with pytest.raises(ValueError, match="'/odom' holds no message that places a frame"):
            load_rosbag(path, pose_topic="/odom")
    assert [w.filename for w in caught] == [__file__]  # the caller's line, not the reader's


@pytest.mark.parametrize("range_min, range_max", [(0.1, 0.0), (np.nan, np.nan), (-1.0, 0.0)])
def test_a_scan_without_range_limits_reads_with_max_range(tmp_path, range_min, range_max):
    # Drivers that leave range_max at 0 or NaN, or range_min at NaN, state no limits: every
    # reading counts, except the negative ones, which a negative range_min does not admit.
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (0.0, 0.0, 0.0), static=True)
    bag.scan(0.5, [-1.0, 1.0, 2.0, 3.0], angle_min=0.0, increment=0.1,
             range_min=range_min, range_max=range_max)  # fmt: skip
    path = bag.write(tmp_path / "b")
    with pytest.raises(ValueError, match="state no positive finite range_max; pass max_range="):
        load_rosbag(path)
    scans = load_rosbag(path, max_range=10.0)
    # The negative reading dropped: three beams, from the second.
    np.testing.assert_array_equal(scans.ranges, [[1.0, 2.0, 3.0]])
    np.testing.assert_allclose(scans.angles, [0.1, 0.2, 0.3], atol=1e-6)


def test_level_tolerance_zero_keeps_a_level_laser_2d(tmp_path):
    bag = _Bag(2)
    for stamp in (0.0, 1.0):
        bag.tf(stamp, "map", "laser", (1.0, 2.0, 0.3), yaw=0.5)
    bag.scan(0.5, [1.0, 2.0, 3.0])
    scans = load_rosbag(bag.write(tmp_path / "b"), level_tolerance=0.0)
    np.testing.assert_allclose(scans.poses, [[1.0, 2.0, 0.5]], atol=1e-12)


def test_scans_without_a_usable_reading_are_skipped_and_counted(tmp_path):
    bag = _Bag(2)
    bag.tf(0.0, "map", "laser", (0.0, 0.0, 0.0))
    bag.tf(2.0, "map", "laser", (2.0, 0.0, 0.0))
    bag.scan(0.5, [1.0, 2.0, 3.0])
    bag.scan(1.0, [0.0, -np.inf, 0.05])  # every reading below range_min 0.1
    bag.scan(3.0, [1.0, 2.0, 3.0])  # after the transforms
    path = bag.write(tmp_path / "b")
    match = (
        r"skipped 1 of 3 scans whose stamps lie outside the time range of their poses "
        r"\[0, 2\] s .*; 1 scans without a reading within \[range_min, range_max\]\."
    )
    with pytest.warns(UserWarning, match=match) as caught:
        scans = load_rosbag(path)
    assert [w.filename for w in caught] == [__file__]  # the caller's line, not the reader's
    np.testing.assert_allclose(scans.timestamps, [0.5])
    np.testing.assert_array_equal(scans.ranges, [[1.0, 2.0, 3.0]])
    # No scan left: the error says when the scans were.
    bag.messages = [m for m in bag.messages if m[2] >= 1.0]
    with pytest.warns(UserWarning, match="skipped"):
        with pytest.raises(ValueError, match=r"no scan of '/scan' has a pose and a usable "
                           r"reading; the scans span \[1, 3\] s"):  # fmt: skip
            load_rosbag(bag.write(tmp_path / "c"))


def test_write_rosbag_refuses_beams_out_of_the_laser_plane(tmp_path):
    up = np.array([[np.cos(a), 0.0, np.sin(a)] for a in (-0.2, 0.0, 0.2)])  # a vertical fan
    scans = Scans(poses=[[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]], ranges=[[1.0, 2.0, 3.0]],
                  angles=up, max_range=10.0)  # fmt: skip
    with pytest.raises(ValueError, match="LaserScan beams lie in the laser's xy-plane"):
        write_rosbag(scans, tmp_path / "b")
    assert not (tmp_path / "b").exists()


def test_scans_without_timestamps_are_stamped_one_second_apart_from_zero(tmp_path):
    scans = Scans(
        poses=[[0.0, 0.0, 0.0], [1.0, 0.0, 0.5], [2.0, 0.0, 1.0]],
        ranges=[[1.0, 2.0, 3.0]] * 3,
        angles=[-0.1, 0.0, 0.1],
        max_range=4.0,
    )
    back = load_rosbag(write_rosbag(scans, tmp_path / "b"))
    np.testing.assert_array_equal(back.timestamps, [0.0, 1.0, 2.0])
    np.testing.assert_allclose(back.poses, scans.poses, atol=1e-12)


def test_write_rosbag_refuses_two_poses_at_one_stamp_out_of_order(tmp_path):
    # Scans 0 and 2 share a stamp with scan 1 between them (timestamps not sorted).
    scans = Scans(poses=[[0.0, 0.0, 0.0], [5.0, 5.0, 1.0], [10.0, 0.0, 2.0]],
                  ranges=[[1.0, 2.0, 3.0]] * 3, angles=[-0.1, 0.0, 0.1], max_range=4.0,
                  timestamps=[1.0, 2.0, 1.0])  # fmt: skip
    with pytest.raises(ValueError, match="scans 0 and 2 share the timestamp 1 s"):
        write_rosbag(scans, tmp_path / "dup")
    assert not (tmp_path / "dup").exists()


def test_a_map_stamp_is_rounded_to_the_nanosecond(grid, tmp_path):
    # 1.001 s is 1 s and 1 000 000 ns (1.001 * 1e9 is 1000999999.9999999 in floats).
    path = grid.write_rosbag(tmp_path / "map", stamp=1.001)
    with AnyReader([path]) as reader:
        ((conn, stamp, raw),) = list(reader.messages())
        msg = reader.deserialize(raw, conn.msgtype)
    assert stamp == 1_001_000_000
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1, 1_000_000)
    assert (msg.info.map_load_time.sec, msg.info.map_load_time.nanosec) == (1, 1_000_000)


@pytest.mark.parametrize("bad", [-1.0, 0.0, np.inf, np.nan, True, "far"])
def test_a_bad_max_range_is_refused_before_the_bag_is_read(tmp_path, bad):
    # The path does not exist: the argument is judged first, as load_carmen does, not after
    # every message was read (or behind the bag's own errors).
    with pytest.raises(ValueError, match="max_range must be a positive"):
        load_rosbag(tmp_path / "missing.bag", max_range=bad)
