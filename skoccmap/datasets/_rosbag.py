"""ROS bags in and out, without ROS: laser scans and poses read, scans and maps written.

Everything here goes through the pure-Python ``rosbags`` package (``pip install
"skoccmap[ros]"``), which reads and writes ROS 1 bags (one ``.bag`` file) and ROS 2 bags (a
directory with ``metadata.yaml`` and sqlite3 ``.db3`` or ``.mcap`` storage files).

Frames follow tf2: a ``geometry_msgs/TransformStamped`` with ``header.frame_id`` *parent* and
``child_frame_id`` *child* is the pose of the child frame in the parent frame, so a point
``p`` in the child frame is ``R p + t`` in the parent frame. Frame names are compared without a
leading ``/`` (ROS 1 allowed ``/base_link``; tf2 strips it).
"""

import re
import shutil
import warnings
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._validation import caller_stacklevel, is_number

__all__ = ["load_rosbag", "write_rosbag"]

_INSTALL_HINT = (
    'reading and writing ROS bags needs the rosbags package: pip install "skoccmap[ros]"'
)

_LASER_SCAN = "sensor_msgs/msg/LaserScan"
_TF_MESSAGE = "tf2_msgs/msg/TFMessage"
_OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
_POSE_TYPES = (
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
)
# ROS 1 message definition of tf2_msgs/TFMessage; some rosbags releases lack it in their
# ROS 1 Noetic type store, and /tf cannot be written without it.
_TF_MESSAGE_DEF = "geometry_msgs/TransformStamped[] transforms\n"
_ROS2_STORAGES = (".db3", ".mcap")
_NS = 1_000_000_000


def _import_rosbags():
    try:
        import rosbags  # noqa: F401
    except ImportError as exc:
        raise ImportError(_INSTALL_HINT) from exc


# --------------------------------------------------------------------------------------------
# Bag paths and type stores
# --------------------------------------------------------------------------------------------


def is_rosbag(path):
    """Whether ``path`` looks like a ROS bag: a ``.bag`` file, a ROS 2 storage file
    (``.db3``, ``.mcap``) or a directory holding ``metadata.yaml`` or such files."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file() or any(
            p.suffix in _ROS2_STORAGES for p in path.iterdir()
        )
    return path.suffix in (".bag", *_ROS2_STORAGES)


def _bag_paths(path):
    """The path(s) to hand to ``AnyReader``: a ROS 2 directory without ``metadata.yaml`` is
    read through its single storage file (``rosbags`` reads bare ``.mcap``/``.db3`` files)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"No such file or directory: {str(path)!r}")
    if not is_rosbag(path):
        raise ValueError(
            f"{path} is not a ROS bag: expected a ROS 1 .bag file or a ROS 2 bag directory "
            "(metadata.yaml with .db3 or .mcap storage)."
        )
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        storages = sorted(p for p in path.iterdir() if p.suffix in _ROS2_STORAGES)
        if len(storages) != 1:
            raise ValueError(
                f"{path} has no metadata.yaml and {len(storages)} storage files; "
                "pass the path of one storage file."
            )
        return [storages[0]]
    return [path]


def _typestore(ros_version):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    if ros_version == 2:
        return get_typestore(Stores.ROS2_HUMBLE)
    store = get_typestore(Stores.ROS1_NOETIC)
    if _TF_MESSAGE not in store.fielddefs:
        store.register(get_types_from_msg(_TF_MESSAGE_DEF, _TF_MESSAGE))
    return store


def _check_ros_version(ros_version):
    if ros_version not in (1, 2):
        raise ValueError(f"ros_version must be 1 or 2, got {ros_version!r}.")


# --------------------------------------------------------------------------------------------
# Quaternions [w, x, y, z] and rigid transforms, vectorised over rows
# --------------------------------------------------------------------------------------------


def _qmul(a, b):
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def _qconj(q):
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def _qrotate(q, v):
    qv = np.concatenate([np.zeros(v.shape[:-1] + (1,)), v], axis=-1)
    return _qmul(_qmul(q, qv), _qconj(q))[..., 1:]


def _compose(a, b):
    """``a`` then ``b``: the pose ``b`` (in ``a``'s child frame) expressed in ``a``'s parent."""
    (ta, qa), (tb, qb) = a, b
    return ta + _qrotate(qa, tb), _qmul(qa, qb)


def _invert(transform):
    t, q = transform
    qi = _qconj(q)
    return -_qrotate(qi, t), qi


def _slerp(q0, q1, u):
    """Spherical interpolation between unit quaternions, the short way round."""
    dot = np.sum(q0 * q1, axis=-1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    dot = np.abs(dot)
    angle = np.arccos(np.clip(dot, -1.0, 1.0))
    sin = np.sin(angle)
    # Nearly equal rotations: linear interpolation is exact to rounding and avoids 0 / 0.
    near = sin < 1e-9
    safe = np.where(near, 1.0, sin)
    w0 = np.where(near, 1.0 - u, np.sin((1.0 - u) * angle) / safe)
    w1 = np.where(near, u, np.sin(u * angle) / safe)
    q = w0[:, None] * q0 + w1[:, None] * q1
    return q / np.linalg.norm(q, axis=1, keepdims=True)


# --------------------------------------------------------------------------------------------
# Time-stamped transforms
# --------------------------------------------------------------------------------------------


@dataclass
class _Track:
    """Samples of one transform (a TF edge or a pose topic) over time."""

    stamps: np.ndarray  # int64 nanoseconds, increasing
    translations: np.ndarray  # (n, 3)
    rotations: np.ndarray  # (n, 4) unit quaternions [w, x, y, z]
    static: bool = False

    @classmethod
    def from_samples(cls, stamps, translations, rotations, static=False):
        stamps = np.asarray(stamps, dtype=np.int64)
        order = np.argsort(stamps, kind="stable")
        # A stamp sent twice keeps its last sample, as tf2's buffer does.
        last = np.r_[stamps[order][1:] != stamps[order][:-1], True]
        keep = order[last]
        rotations = np.asarray(rotations, dtype=np.float64)[keep]
        rotations = rotations / np.linalg.norm(rotations, axis=1, keepdims=True)
        translations = np.asarray(translations, dtype=np.float64)[keep]
        return cls(stamps[keep], translations, rotations, static)

    @property
    def span(self):
        return int(self.stamps[0]), int(self.stamps[-1])

    def at(self, stamps):
        """Translations, rotations and a validity mask at ``stamps`` (ns): linear in
        translation, slerp in rotation; no extrapolation outside the sampled time range."""
        n = len(stamps)
        if self.static:
            t = np.broadcast_to(self.translations[-1], (n, 3))
            q = np.broadcast_to(self.rotations[-1], (n, 4))
            return t, q, np.ones(n, dtype=bool)
        valid = (stamps >= self.stamps[0]) & (stamps <= self.stamps[-1])
        if len(self.stamps) == 1:
            t = np.broadcast_to(self.translations[0], (n, 3))
            q = np.broadcast_to(self.rotations[0], (n, 4))
            return t, q, valid
        i = np.clip(
            np.searchsorted(self.stamps, stamps, side="right") - 1, 0, len(self.stamps) - 2
        )
        # Nanosecond differences are exact in int64; only their ratio is rounded.
        u = (stamps - self.stamps[i]) / (self.stamps[i + 1] - self.stamps[i])
        u = np.clip(u, 0.0, 1.0)
        t = (1.0 - u)[:, None] * self.translations[i] + u[:, None] * self.translations[i + 1]
        q = _slerp(self.rotations[i], self.rotations[i + 1], u)
        return t, q, valid


class _TransformTree:
    """The transforms of ``/tf`` and ``/tf_static``: edges between frames, looked up along
    the chain that joins two frames (either direction along each edge)."""

    def __init__(self, samples):
        # samples: {(parent, child): (stamps, translations, rotations, static)}
        self.edges = {
            edge: _Track.from_samples(*values) for edge, values in samples.items() if values[0]
        }
        self.neighbours = {}
        for parent, child in self.edges:
            self.neighbours.setdefault(parent, set()).add(child)
            self.neighbours.setdefault(child, set()).add(parent)

    @property
    def frames(self):
        return sorted(self.neighbours)

    def chain(self, source, target):
        """Frames from ``source`` to ``target`` (breadth first), or None."""
        previous = {source: None}
        queue = deque([source])
        while queue:
            frame = queue.popleft()
            if frame == target:
                path = [frame]
                while previous[path[-1]] is not None:
                    path.append(previous[path[-1]])
                return path[::-1]
            for nxt in sorted(self.neighbours.get(frame, ())):
                if nxt not in previous:
                    previous[nxt] = frame
                    queue.append(nxt)
        return None

    def lookup(self, target, source, stamps):
        """Pose of frame ``source`` in frame ``target`` at ``stamps`` (ns): translations
        (n, 3), rotations (n, 4), the mask of stamps inside every edge's time range, and the
        time span ``(start, end)`` in which all edges of the chain have samples."""
        n = len(stamps)
        t, q = np.zeros((n, 3)), np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
        valid, span = np.ones(n, dtype=bool), (-np.inf, np.inf)
        if target == source:
            return t, q, valid, span
        path = self.chain(target, source)
        if path is None:
            raise KeyError((target, source))
        for parent, child in zip(path[:-1], path[1:], strict=True):
            track = self.edges.get((parent, child))
            inverse = track is None
            track = self.edges[(child, parent)] if inverse else track
            te, qe, ok = track.at(stamps)
            step = _invert((te, qe)) if inverse else (te, qe)
            t, q = _compose((t, q), step)
            valid &= ok
            if not track.static:
                span = (max(span[0], track.span[0]), min(span[1], track.span[1]))
        return t, q, valid, span


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


def _frame(name):
    return str(name).lstrip("/")


def _stamp_ns(header):
    return int(header.stamp.sec) * _NS + int(header.stamp.nanosec)


def _describe_topics(reader):
    topics = reader.topics
    if not topics:
        return "it has no topics"
    return "its topics: " + ", ".join(f"{name} ({info.msgtype})" for name, info in topics.items())


def _resolved_topic(reader, topic):
    """``topic`` as the bag names it: a relative name (``"scan"``) the bag lacks resolves
    in the global namespace (``"/scan"``), as a node started without one would resolve it."""
    names = {c.topic for c in reader.connections}
    if topic not in names and not topic.startswith("/") and "/" + topic in names:
        return "/" + topic
    return topic


def _connections(reader, path, topic, msgtypes, what):
    resolved = _resolved_topic(reader, topic)
    conns = [c for c in reader.connections if c.topic == resolved]
    if not conns:
        raise ValueError(f"{path} has no {what} topic {topic!r}; {_describe_topics(reader)}.")
    wrong = sorted({c.msgtype for c in conns} - set(msgtypes))
    if wrong:
        raise ValueError(
            f"{path}: topic {topic!r} carries {', '.join(wrong)}; the {what} topic must carry "
            f"{' or '.join(msgtypes)}."
        )
    return conns


def _read(reader, conns):
    for conn, _, raw in reader.messages(connections=conns):
        yield conn, reader.deserialize(raw, conn.msgtype)


@dataclass
class _LaserMessage:
    """A scan as read: its ranges as the message holds them (float32), its beam angles as
    ``angle_min`` and ``angle_increment`` (a bag of many scans is held in memory until the
    rows are built: per-scan float64 copies of both would take four times as much)."""

    stamp: int
    frame: str
    ranges: np.ndarray
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float

    @property
    def angles(self):
        return self.angle_min + self.angle_increment * np.arange(self.ranges.size)


def _check_scan_topics(scan_topic):
    """``scan_topic`` as a tuple of distinct topic names, or a ValueError."""
    topics = (scan_topic,) if isinstance(scan_topic, str) else scan_topic
    try:
        topics = tuple(dict.fromkeys(topics))
    except TypeError:  # not a sequence, or unhashable names
        topics = ()
    if not topics or not all(isinstance(topic, str) for topic in topics):
        raise ValueError(
            "scan_topic must be a topic name or a sequence of them (one per laser), got "
            f"{scan_topic!r}."
        )
    return topics


def _read_scans(reader, path, topics):
    """The scans of every topic in ``topics``, in header stamp order."""
    scans = []
    # Resolved first: "scan" and "/scan" name one topic, whose scans are read once.
    for topic in dict.fromkeys(_resolved_topic(reader, topic) for topic in topics):
        scans += _read_topic_scans(reader, path, topic)
    scans.sort(key=lambda s: s.stamp)  # header stamps, whatever order they were recorded in
    return scans


def _read_topic_scans(reader, path, topic):
    scans = []
    for _, msg in _read(reader, _connections(reader, path, topic, [_LASER_SCAN], "scan")):
        ranges = np.array(msg.ranges, dtype=np.float32)
        start, step = float(msg.angle_min), float(msg.angle_increment)
        if not (np.isfinite(start) and np.isfinite(step) and (step != 0 or ranges.size < 2)):
            raise ValueError(
                f"{path}: a LaserScan on {topic!r} at {_stamp_ns(msg.header) * 1e-9:.9f} s has "
                f"angle_min {start} and angle_increment {step}: its beams have no directions."
            )
        range_min, range_max = float(msg.range_min), float(msg.range_max)
        # Both limits in use (see _usable_ranges) and crossed: every reading is dropped
        # (below range_min) or read as a beam without a return (above range_max), so the
        # scan's returns would become free space up to the maximum range, without a word.
        if 0 < range_max < range_min < np.inf:
            raise ValueError(
                f"{path}: a LaserScan on {topic!r} at {_stamp_ns(msg.header) * 1e-9:.9f} s has "
                f"range_min {range_min:g} above range_max {range_max:g}: no reading lies "
                "between them, and each would be dropped or read as a beam without a return. "
                "The driver's range limits are wrong (swapped?)."
            )
        scans.append(
            _LaserMessage(
                _stamp_ns(msg.header),
                _frame(msg.header.frame_id),
                ranges,
                start,
                step,
                range_min,
                range_max,
            )
        )
    if not scans:
        raise ValueError(f"{path}: topic {topic!r} holds no message.")
    return scans


def _vector(v):
    return (float(v.x), float(v.y), float(v.z))


def _quaternion(q):
    return (float(q.w), float(q.x), float(q.y), float(q.z))


def _places_frame(translation, rotation):
    """Whether a transform sample places a frame: finite, with a non-zero quaternion (ROS 1's
    default Quaternion is all zeros)."""
    finite = np.all(np.isfinite(translation)) and np.all(np.isfinite(rotation))
    return bool(finite and any(rotation))


def _warn_left_out(path, left_out):
    """One warning for the transform samples that place nothing, naming the first; called
    by the reader of /tf or of the pose topic, from ``_poses``, from ``load_rosbag``."""
    if left_out:
        what, stamp = left_out[0]
        warnings.warn(
            f"{path}: left out {len(left_out)} transform sample(s) with a non-finite "
            f"translation or a zero or non-finite rotation, as tf2 would (the first: {what} "
            f"at {stamp * 1e-9:.9f} s).",
            UserWarning,
            stacklevel=caller_stacklevel(),
        )


def _kept(track, stamp, translation, rotation, what, left_out):
    """Append a pose sample to ``track``'s (stamps, translations, rotations) lists, or note
    it in ``left_out`` when it places no frame; whether it was kept."""
    if not _places_frame(translation, rotation):
        left_out.append((what, stamp))
        return False
    for column, value in zip(track, (stamp, translation, rotation), strict=True):
        column.append(value)
    return True


def _check_tf_topics(tf_topics):
    """``tf_topics`` as a pair of topic names, or a ValueError."""
    try:
        topics = (tf_topics,) if isinstance(tf_topics, str) else tuple(tf_topics)
    except TypeError:  # not a sequence
        topics = (tf_topics,)
    if len(topics) != 2 or not all(isinstance(topic, str) for topic in topics):
        raise ValueError(
            "tf_topics must be a pair of topic names, the dynamic and the static transforms "
            f"(default ('/tf', '/tf_static')), got {tf_topics!r}. A bag without the static "
            "topic is read as well."
        )
    return topics


def _read_tf(reader, tf_topics, path):
    samples, left_out = {}, []
    static_topic = tf_topics[1]
    for conn, msg in _read(reader, [c for c in reader.connections if c.topic in tf_topics]):
        static = conn.topic == static_topic
        for tf in msg.transforms:
            edge = (_frame(tf.header.frame_id), _frame(tf.child_frame_id))
            if static and not samples.get(edge, (0, 0, 0, True))[3]:
                del samples[edge]  # a transform on /tf_static is fixed, whatever /tf said
            *track, was_static = samples.setdefault(edge, ([], [], [], static))
            if was_static and not static:
                continue
            t, r = _vector(tf.transform.translation), _quaternion(tf.transform.rotation)
            what = f"the transform {edge[0]} -> {edge[1]}"
            _kept(track, _stamp_ns(tf.header), t, r, what, left_out)
    _warn_left_out(path, left_out)
    return _TransformTree(samples)


def _read_pose_topic(reader, path, topic):
    track, frames, children, left_out = ([], [], []), set(), set(), []
    for conn, msg in _read(reader, _connections(reader, path, topic, _POSE_TYPES, "pose")):
        pose = msg.pose.pose if conn.msgtype != "geometry_msgs/msg/PoseStamped" else msg.pose
        t, r = _vector(pose.position), _quaternion(pose.orientation)
        if not _kept(track, _stamp_ns(msg.header), t, r, f"the pose on {topic!r}", left_out):
            continue
        frames.add(_frame(msg.header.frame_id))
        children.add(_frame(getattr(msg, "child_frame_id", "")))
    _warn_left_out(path, left_out)
    if not track[0]:
        raise ValueError(f"{path}: pose topic {topic!r} holds no message that places a frame.")
    if len(frames) > 1 or len(children) > 1:
        raise ValueError(
            f"{path}: pose topic {topic!r} changes frames (header.frame_id {sorted(frames)}, "
            f"child_frame_id {sorted(children)})."
        )
    return _Track.from_samples(*track), frames.pop(), children.pop()


def _laser_in_map(tree, map_frame, laser_frame, stamps, path):
    try:
        return tree.lookup(map_frame, laser_frame, stamps)
    except KeyError:
        missing = [f for f in (map_frame, laser_frame) if f not in tree.neighbours]
        why = f"frame(s) {missing} are not in them" if missing else "no chain joins them"
        raise ValueError(
            f"{path}: cannot transform the scans' frame {laser_frame!r} into {map_frame!r} "
            f"with /tf and /tf_static: {why}; frames present: {tree.frames}. Pass map_frame= "
            "or read poses from a topic with pose_topic=."
        ) from None


def _laser_from_pose_topic(track, tree, base_frame, laser_frame, stamps, path):
    tb, qb, valid = track.at(stamps)
    span = track.span
    if base_frame == laser_frame:
        return tb, qb, valid, span
    try:
        to, qo, ok, offset_span = tree.lookup(base_frame, laser_frame, stamps)
    except KeyError:
        raise ValueError(
            f"{path}: the pose topic gives the pose of frame {base_frame!r} but the scans are "
            f"in frame {laser_frame!r}, and /tf_static and /tf hold no chain between them "
            f"(frames present: {tree.frames}). Pass base_frame={laser_frame!r} if the pose "
            "topic gives the laser's own pose."
        ) from None
    span = (max(span[0], offset_span[0]), min(span[1], offset_span[1]))
    t, q = _compose((tb, qb), (to, qo))
    return t, q, valid & ok, span


def _warn_laser_has_parents(tree, laser_frame, pose_frame, pose_topic, path):
    """Warn when pose messages that name no child frame (``PoseStamped``,
    ``PoseWithCovarianceStamped``, an ``Odometry`` with an empty ``child_frame_id``) are taken
    as the laser's own pose although the transforms mount the laser on another frame: such
    poses are most often the robot's (``amcl_pose``, a SLAM node's pose), and using them for
    the laser would leave out its mounting offset and rotation without a word. The poses'
    own frame (``header.frame_id``), where the transforms place the laser directly in it,
    is no frame to suggest."""
    parents = {parent for parent, child in tree.edges if child == laser_frame}
    parents = sorted(parents - {pose_frame})
    if parents:
        warnings.warn(
            f"{path}: the poses on {pose_topic!r} name no child frame, so they are taken as "
            f"the pose of the scans' frame {laser_frame!r} itself; but the transforms mount "
            f"{laser_frame!r} on {', '.join(map(repr, parents))}. If the poses are the "
            f"robot's, pass base_frame= its frame (e.g. base_frame={parents[0]!r}); "
            f"base_frame={laser_frame!r} keeps them as the laser's pose without this warning.",
            UserWarning,
            stacklevel=caller_stacklevel(),
        )


def _poses(scans, reader, path, pose, map_frame, pose_topic, base_frame, tf_topics):
    """Laser poses (translation, rotation, valid) of every scan at its stamp."""
    stamps = np.array([s.stamp for s in scans], dtype=np.int64)
    tf_topics = tuple(_resolved_topic(reader, topic) for topic in tf_topics)
    have_tf = any(c.topic in tf_topics for c in reader.connections)
    if pose == "tf" and not have_tf:
        raise ValueError(
            f"{path} has no transform topic ({' or '.join(tf_topics)}); "
            f"{_describe_topics(reader)}. Read poses from a topic with pose_topic=."
        )
    tree = _read_tf(reader, tf_topics, path) if have_tf else _TransformTree({})
    t = np.empty((len(scans), 3))
    q = np.empty((len(scans), 4))
    valid = np.empty(len(scans), dtype=bool)
    spans = []
    if pose == "topic":
        track, pose_frame, child = _read_pose_topic(reader, path, pose_topic)
    # Scans from several lasers (frames) on one topic each get their own chain.
    frames = np.array([s.frame for s in scans])
    for frame in dict.fromkeys(s.frame for s in scans):
        rows = frames == frame
        if pose == "tf":
            out = _laser_in_map(tree, map_frame, frame, stamps[rows], path)
        else:
            if base_frame is None and not child:
                _warn_laser_has_parents(tree, frame, pose_frame, pose_topic, path)
            base = base_frame if base_frame is not None else (child or frame)
            out = _laser_from_pose_topic(track, tree, _frame(base), frame, stamps[rows], path)
        t[rows], q[rows], valid[rows] = out[:3]
        spans.append(out[3])
    span = (max(s[0] for s in spans), min(s[1] for s in spans))
    return t, q, valid, span


def _usable_ranges(scan, nan_invalid=False):
    """Ranges with no-return beams as ``inf`` and the mask of beams that carry information.

    NaN (unless ``nan_invalid``: then dropped) and readings above ``range_max`` (``+inf``
    included) are beams without a return.
    Readings below ``range_min`` (``-inf`` included, REP 117's "too close") say nothing about
    where the nearest obstacle is -- a return the sensor could not measure, or an error code
    -- so they are dropped: a free beam to the maximum range would invent free space through
    whatever was in front of the sensor.
    """
    ranges = scan.ranges.astype(np.float64)
    limit = scan.range_max if np.isfinite(scan.range_max) and scan.range_max > 0 else np.inf
    range_min = scan.range_min if np.isfinite(scan.range_min) else 0.0
    with np.errstate(invalid="ignore"):
        nan = np.isnan(ranges)
        ranges[nan | (ranges > limit)] = np.inf
        usable = ~(ranges < max(range_min, 0.0))
    if nan_invalid:
        usable &= ~nan
    return ranges, usable


def _rectangular(scans, max_range, nan_invalid=False):
    """Ranges (n_scans, n_beams) and angles of the usable beams of every scan.

    A scan with fewer usable beams than the widest fills its row by repeating its own
    usable beams, in beam order: a repeated beam counts twice, no beam is invented.
    Returns the rows, the angles -- one row (n_beams,) when every scan with a usable beam
    has all its beams usable at the same angles, per scan (n_scans, n_beams) otherwise --
    and the mask of scans that have at least one usable beam. Each scan's ranges are
    cleaned twice (counted, then copied) rather than held cleaned: the rows are the only
    float64 copy of the bag's ranges. ``nan_invalid``: see :func:`_usable_ranges`.
    """
    counts = np.array([int(_usable_ranges(s, nan_invalid)[1].sum()) for s in scans])
    has_beams = counts > 0
    width = int(counts.max()) if has_beams.any() else 0
    with_beams = [s for s, has in zip(scans, has_beams, strict=True) if has]
    shared = bool(with_beams) and all(
        s.ranges.size == width
        and s.angle_min == with_beams[0].angle_min
        and s.angle_increment == with_beams[0].angle_increment
        for s in with_beams
    )
    shared &= bool(np.all(counts[has_beams] == width))
    ranges = np.empty((len(scans), width))
    angles = with_beams[0].angles if shared else np.empty((len(scans), width))
    for row, scan in enumerate(scans):
        if not has_beams[row]:
            continue
        r, usable = _usable_ranges(scan, nan_invalid)
        if shared:
            ranges[row] = r
            continue
        index = np.flatnonzero(usable)
        if index.size < width:
            index = np.sort(np.resize(index, width))
        ranges[row], angles[row] = r[index], scan.angles[index]
    ranges[ranges >= max_range] = np.inf
    return ranges, angles, has_beams


def _scan_max_range(scans, max_range, path):
    stated = [s.range_max for s in scans if np.isfinite(s.range_max) and s.range_max > 0]
    # range_max is a float32 field: its shortest decimal is the value the driver was given
    # (81.83, not 81.83000183).
    laser = float(str(np.float32(min(stated)))) if stated else None
    if max_range is not None:  # checked by load_rosbag before the bag is read
        if laser is not None and max_range > min(stated) * (1 + 1e-6):
            warnings.warn(
                f"{path}: max_range={max_range:g} is beyond the range_max {laser:g} m the "
                f"scans state: their beams without a return become free up to {max_range:g} "
                f"m, further than the laser measures. Pass max_range={laser:g} or less "
                "(or None, the scans' own).",
                UserWarning,
                stacklevel=caller_stacklevel(),
            )
        return max_range
    if laser is None:
        raise ValueError(f"{path}: the scans state no positive finite range_max; pass max_range=.")
    return laser


def _to_scans(t, q, ranges, angles, stamps, max_range, level_tolerance):
    """Scans from the laser poses and the rows of :func:`_rectangular`: ``angles`` of shape
    (n_beams,) shared by all scans, or (n_scans, n_beams)."""
    from ..observations import Scans, _quaternion_to_matrix

    rot = _quaternion_to_matrix(q)
    tilt = np.arccos(np.clip(rot[:, 2, 2], -1.0, 1.0))
    # A laser mounted upside down (z axis down) scans a level plane too.
    if np.all(np.minimum(tilt, np.pi - tilt) <= level_tolerance):
        theta = np.arctan2(rot[:, 1, 0], rot[:, 0, 0])
        poses = np.column_stack([t[:, :2], theta])
        # Upside down, the map's x-y block of the rotation is a reflection: the beam at
        # angle a points at theta - a.
        upside_down = rot[:, 2, 2] < 0.0
        if angles.ndim == 1 and upside_down.all():
            beams = -angles
        elif angles.ndim == 1 and not upside_down.any():
            beams = angles
        else:
            beams = np.where(upside_down[:, None], -angles, angles)
        per_scan = beams.ndim == 2
    else:
        poses = np.column_stack([t, q])
        beams = np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], axis=-1)
        per_scan = beams.ndim == 3
    if per_scan and np.all(beams == beams[0]):
        beams = beams[0].copy()
    return Scans(
        poses=poses, ranges=ranges, angles=beams, max_range=max_range, timestamps=stamps / _NS
    )


def _warn_skipped(path, topic, n_total, outside, span, no_beams):
    notes = []
    if outside:
        start, end = (f"{v / _NS:.9g}" for v in span)
        notes.append(
            f"{outside} of {n_total} scans whose stamps lie outside the time range of their "
            f"poses [{start}, {end}] s (poses are interpolated, never extrapolated)"
        )
        if span[0] == span[1]:
            notes[-1] += (
                "; a range of one instant is that of a transform sampled once on the dynamic "
                "transform topic: a static transform belongs on the static one (/tf_static)"
            )
    if no_beams:
        notes.append(f"{no_beams} scans without a reading within [range_min, range_max]")
    if notes:
        message = f"{path}, {topic}: skipped " + "; ".join(notes) + "."
        warnings.warn(message, UserWarning, stacklevel=caller_stacklevel())


def load_rosbag(
    path,
    scan_topic="/scan",
    *,
    pose="tf",
    map_frame="map",
    pose_topic=None,
    base_frame=None,
    laser_frame=None,
    max_range=None,
    level_tolerance=0.01,
    tf_topics=("/tf", "/tf_static"),
    nan_readings="no_return",
):
    """Load the laser scans of a ROS bag, with the laser's pose at every scan.

    Reads ROS 1 bags (a ``.bag`` file) and ROS 2 bags (a directory with ``metadata.yaml`` and
    sqlite3 or mcap storage, or a bare ``.db3`` / ``.mcap`` file) with the pure-Python
    ``rosbags`` package: no ROS installation is needed.

    Parameters
    ----------
    path : str or path-like
        The bag: ``.bag`` file (ROS 1), ROS 2 bag directory or bare ``.db3`` / ``.mcap``
        file.
    scan_topic : str or sequence of str, default="/scan"
        Topic of ``sensor_msgs/LaserScan`` messages, or several (a robot's front and rear
        lasers, e.g. ``["/front_scan", "/rear_scan"]``), read into one time-ordered set of
        scans, each placed by its own frame's transforms. Beam ``i`` of a scan points at
        ``angle_min + i * angle_increment`` in the scan's ``header.frame_id``. A topic name
        without its leading slash (``"scan"``) is looked up as the global name
        (``"/scan"``) when the bag has no topic of that name (so are ``pose_topic`` and
        ``tf_topics``), and two names of one topic read it once.
    pose : {"tf", "topic"}, default="tf"
        Where the laser poses come from. ``"tf"``: the chain of transforms from ``map_frame``
        to each scan's frame in ``/tf`` and ``/tf_static`` (for example map -> odom ->
        base_link -> laser). ``"topic"``: the messages of ``pose_topic``, composed with the
        transform from their frame to the laser's frame in ``/tf_static`` (or ``/tf``).
        Giving ``pose_topic`` implies ``"topic"``.
    map_frame : str, default="map"
        Frame the poses are expressed in, with ``pose="tf"``. (With a pose topic the poses
        are in the messages' ``header.frame_id``.) Use ``"odom"`` for a bag without
        localisation, to map with odometry alone.
    pose_topic : str or None, default=None
        Topic of ``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped`` or
        ``geometry_msgs/PoseWithCovarianceStamped`` messages.
    base_frame : str or None, default=None
        Frame whose pose the ``pose_topic`` messages give. ``None``: the ``child_frame_id``
        of Odometry messages, the laser's own frame for the pose messages, which name none
        (and for Odometry messages with an empty ``child_frame_id``), with a warning when
        the transforms mount the laser on another frame: ``amcl_pose`` and most pose topics
        give the robot's base, not the laser. Pass the laser's frame to use the message
        poses as laser poses unchanged. Only with ``pose_topic`` (a ValueError otherwise:
        the transforms give the laser's pose itself).
    laser_frame : str or None, default=None
        Frame of the scans; ``None``: each scan's ``header.frame_id``. For bags whose scans
        name no frame, or the wrong one.
    max_range : float or None, default=None
        Readings at or above it are beams without a return (free up to ``max_range``).
        ``None``: the smallest ``range_max`` the scans state.
    level_tolerance : float, default=0.01
        Radians. When every scan's plane is within this angle of the map's horizontal plane
        (the laser's z axis within it of the map's z axis), poses are 2-D ``[x, y, theta]``
        (the laser's height is dropped); otherwise they are 3-D ``[x, y, z, qw, qx, qy, qz]``
        with beam directions ``(cos a, sin a, 0)`` in the laser frame. A laser mounted upside
        down (its z axis within this angle of the map's -z) is level too: its beam angles are
        mirrored (the beam at angle ``a`` points at ``theta - a``). ``np.inf`` forces 2-D
        poses (the yaw of a tilted laser, mirrored where its z axis points down).
    tf_topics : (str, str), default=("/tf", "/tf_static")
        The dynamic and the static transform topics.
    nan_readings : {"no_return", "invalid"}, default="no_return"
        What a ``NaN`` reading is. ``"no_return"``: a beam without a return, free up to
        ``max_range``, as most laser drivers mean it. ``"invalid"``: dropped, as readings
        below ``range_min`` are -- REP 117's "erroneous measurement"; use it for scans
        made from a depth camera (``depthimage_to_laserscan`` writes ``NaN`` where a pixel
        has no depth, which says nothing about free space).

    Returns
    -------
    scans : skoccmap.observations.Scans
        In time order of the scans' header stamps; ``timestamps`` are those stamps in
        seconds. ``angles`` are shared by all scans when they agree, per scan otherwise.

    Raises
    ------
    ValueError
        If the scan topic, the pose topic, the transform topics or a frame is missing (the
        message names what the bag has), no scan has a pose, or a scan has no beam
        directions or a ``range_min`` above its ``range_max``.
    ImportError
        If ``rosbags`` is not installed.

    Warns
    -----
    UserWarning
        With the number of scans skipped because their stamp lies outside the time range of
        their transforms (poses are interpolated -- linearly in translation, by slerp in
        rotation -- never extrapolated) or because they have no usable reading.
    UserWarning
        When ``pose_topic`` messages name no child frame, ``base_frame`` is not given, and
        the transforms mount the scans' frame on another frame (see ``base_frame``).

    Notes
    -----
    Readings follow skoccmap's no-return rule: ``NaN``, ``+inf`` and readings above the
    message's ``range_max`` or at or above ``max_range`` are beams without a return, free up to
    ``max_range``, as :func:`load_carmen` and :class:`~skoccmap.observations.Scans` treat them.
    (REP 117 reserves ``NaN`` for erroneous readings; laser drivers use it for no return
    too. ``nan_readings="invalid"`` drops them.) A ``max_range`` beyond the scans'
    ``range_max`` is kept, with a warning: beams without a return then become free further
    than the laser measures.

    Readings below ``range_min`` (zeros, ``-inf``, drivers' error codes) are dropped: ROS calls
    them invalid, and they do not tell where the nearest obstacle is -- something may have been
    right in front of the sensor -- so turning them into free beams to the maximum range would
    invent free space, and into hits would invent obstacles.

    Every row of ``ranges`` has as many beams as the widest scan after that: a scan with fewer
    usable beams (readings dropped, or a laser with fewer beams on the same topic) repeats its
    own usable beams, in beam order, to fill its row, with per-scan ``angles``. A repeated
    beam counts twice in training; no beam is invented. A bag whose scans all have every
    beam usable gives rows exactly as recorded.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> from skoccmap.datasets import load_rosbag, write_rosbag
    >>> from skoccmap.observations import Scans
    >>> scans = Scans(poses=[[0.0, 0.0, 0.0], [1.0, 0.0, np.pi / 2]],
    ...               ranges=[[1.0, 2.0, np.inf], [0.5, 1.5, 3.0]],
    ...               angles=[-0.5, 0.0, 0.5], max_range=4.0, timestamps=[10.0, 10.1])
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     bag = write_rosbag(scans, os.path.join(tmp, "scans"), ros_version=2)
    ...     back = load_rosbag(bag)
    >>> back.poses.round(6).tolist(), back.max_range
    ([[0.0, 0.0, 0.0], [1.0, 0.0, 1.570796]], 4.0)
    >>> back.ranges
    array([[1. , 2. , inf],
           [0.5, 1.5, 3. ]])
    """
    _import_rosbags()
    from rosbags.highlevel import AnyReader, AnyReaderError

    if pose_topic is not None:
        pose = "topic"
    if pose not in ("tf", "topic"):
        raise ValueError(f"pose must be 'tf' or 'topic', got {pose!r}.")
    if pose == "topic" and pose_topic is None:
        raise ValueError("pose='topic' needs pose_topic, the topic to read poses from.")
    if nan_readings not in ("no_return", "invalid"):
        raise ValueError(f"nan_readings must be 'no_return' or 'invalid', got {nan_readings!r}.")
    if not (is_number(level_tolerance) and level_tolerance >= 0):
        raise ValueError(f"level_tolerance must be >= 0 radians, got {level_tolerance!r}.")
    if np.pi / 2 < level_tolerance < np.inf:
        warnings.warn(
            f"level_tolerance={level_tolerance!r} radians takes every laser for level, as "
            "np.inf does (no scan plane is more than pi / 2 from the horizontal). Degrees? "
            "Pass radians: np.deg2rad(...).",
            UserWarning,
            stacklevel=caller_stacklevel(),
        )
    tf_topics = _check_tf_topics(tf_topics)
    scan_topics = _check_scan_topics(scan_topic)
    topic_names = ", ".join(map(repr, scan_topics))
    if max_range is not None:
        from ..observations import _check_max_range

        max_range = _check_max_range(max_range)
    if base_frame is not None and pose != "topic":
        raise ValueError(
            "base_frame= applies only to poses read from a topic, given by pose_topic=. "
            "The transforms give the laser's own pose."
        )
    paths = _bag_paths(path)
    reader = AnyReader(paths, default_typestore=_typestore(2))
    try:
        reader.open()
    except AnyReaderError as exc:
        raise ValueError(f"{path} cannot be read as a ROS bag: {exc}") from None
    try:
        messages = _read_scans(reader, path, scan_topics)
        if laser_frame is not None:
            for message in messages:
                message.frame = _frame(laser_frame)
        t, q, valid, span = _poses(
            messages, reader, path, pose, _frame(map_frame), pose_topic, base_frame, tf_topics
        )
    finally:
        reader.close()
    max_range = _scan_max_range(messages, max_range, path)
    ranges, angles, has_beams = _rectangular(messages, max_range, nan_readings == "invalid")
    keep = valid & has_beams
    _warn_skipped(
        path,
        ", ".join(scan_topics),
        len(messages),
        int((~valid).sum()),
        span,
        int((valid & ~has_beams).sum()),
    )
    if not keep.any():
        stamps = [messages[0].stamp / _NS, messages[-1].stamp / _NS]
        raise ValueError(
            f"{path}: no scan of {topic_names} has a pose and a usable reading; the scans "
            f"span [{stamps[0]:.9g}, {stamps[1]:.9g}] s."
        )
    stamps = np.array([s.stamp for s in messages], dtype=np.int64)[keep]
    del messages  # the rows hold the ranges now
    if not keep.all():
        ranges = ranges[keep]
        angles = angles if angles.ndim == 1 else angles[keep]
    return _to_scans(t[keep], q[keep], ranges, angles, stamps, max_range, level_tolerance)


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def _time(store, stamp_ns):
    sec, nanosec = divmod(int(stamp_ns), _NS)
    return store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)


def _header(store, stamp_ns, frame_id):
    fields = {"stamp": _time(store, stamp_ns), "frame_id": frame_id}
    if "seq" in dict(store.fielddefs["std_msgs/msg/Header"][1]):
        fields["seq"] = 0  # ROS 1 headers carry a sequence number
    return store.types["std_msgs/msg/Header"](**fields)


def _transform_stamped(store, stamp_ns, parent, child, translation, rotation):
    types = store.types
    w, x, y, z = (float(v) for v in rotation)
    tx, ty, tz = (float(v) for v in translation)
    return types["geometry_msgs/msg/TransformStamped"](
        header=_header(store, stamp_ns, parent),
        child_frame_id=child,
        transform=types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](x=tx, y=ty, z=tz),
            rotation=types["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
        ),
    )


class _BagWriter:
    """One ``rosbags`` writer for either ROS version: connections and serialisation."""

    def __init__(self, path, ros_version, storage):
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        _check_ros_version(ros_version)
        path = Path(path)
        if path.exists():
            raise FileExistsError(f"{path} exists already; bags are never overwritten.")
        self.ros_version = ros_version
        self.store = _typestore(ros_version)
        if ros_version == 1:
            if path.suffix != ".bag":
                raise ValueError(f"a ROS 1 bag is a .bag file, got {path}.")
            # Its folders are made as a ROS 2 bag's are (the ROS 2 writer makes them).
            path.parent.mkdir(parents=True, exist_ok=True)
            self.writer = Writer1(path)
        else:
            plugins = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}
            if path.suffix in (".bag", *_ROS2_STORAGES):
                # A directory so named would be read back as a ROS 1 bag or a bare storage
                # file, and fail.
                raise ValueError(
                    f"a ROS 2 bag is a directory, not a {path.suffix} file; name it without "
                    f"the suffix (e.g. {path.with_suffix('')}), or pass ros_version=1."
                )
            if storage not in plugins:
                raise ValueError(f"storage must be 'sqlite3' or 'mcap', got {storage!r}.")
            self.writer = Writer2(path, version=8, storage_plugin=plugins[storage])
        self.path = path

    def __enter__(self):
        self.writer.open()
        return self

    def __exit__(self, exc_type, *exc):
        # A half-written bag would block the next try ("exists already"): removed when a
        # write failed, or the close (which may fail after a failed write too).
        try:
            self.writer.close()
        except BaseException:
            self._remove()
            raise
        if exc_type is not None:
            self._remove()
        return False

    def _remove(self):
        if self.path.is_dir():
            shutil.rmtree(self.path, ignore_errors=True)
        else:
            self.path.unlink(missing_ok=True)

    def connection(self, topic, msgtype, *, latched=False):
        """A connection; latched ones are ROS 1 ``latching=1`` or ROS 2 ``transient_local``
        with a history of one (what map_server and the static transform broadcaster offer)."""
        if self.ros_version == 1:
            latching = 1 if latched else None
            return self.writer.add_connection(
                topic, msgtype, typestore=self.store, latching=latching
            )
        qos = [_latched_qos()] if latched else []
        return self.writer.add_connection(
            topic, msgtype, typestore=self.store, offered_qos_profiles=qos
        )

    def write(self, connection, stamp_ns, message):
        if self.ros_version == 1:
            raw = self.store.serialize_ros1(message, connection.msgtype)
        else:
            raw = self.store.serialize_cdr(message, connection.msgtype)
        self.writer.write(connection, int(stamp_ns), raw)


def _latched_qos():
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    default = QosTime(0, 0)  # RMW_DURATION_UNSPECIFIED: the middleware default
    return Qos(
        QosHistory.KEEP_LAST,
        1,
        QosReliability.RELIABLE,
        QosDurability.TRANSIENT_LOCAL,
        default,
        default,
        QosLiveliness.AUTOMATIC,
        default,
        False,
    )


def _scan_geometry(scans):
    """Per scan: ``angle_min``, ``angle_increment`` of evenly spaced in-plane beams."""
    if scans.n_dims == 2:
        angles = np.broadcast_to(scans.angles, scans.ranges.shape)
    else:
        beams = np.broadcast_to(scans.angles, scans.ranges.shape + (3,))
        if np.any(np.abs(beams[..., 2]) > 1e-6):
            raise ValueError("LaserScan beams lie in the laser's xy-plane; these scans' do not.")
        # Unwrapped along the scan: a scan over all of the circle crosses arctan2's cut.
        angles = np.unwrap(np.arctan2(beams[..., 1], beams[..., 0]), axis=1)
    n = scans.n_beams
    increment = (angles[:, -1] - angles[:, 0]) / max(n - 1, 1)
    even = angles[:, :1] + increment[:, None] * np.arange(n)
    if not np.allclose(angles, even, rtol=0.0, atol=1e-6):
        raise ValueError(
            "LaserScan beams are evenly spaced (angle_min + i * angle_increment); these "
            "scans' beam angles are not."
        )
    return angles[:, 0], increment


def _laser_transforms(scans):
    """Translations (n, 3) and rotations (n, 4) of the laser in the map frame."""
    if scans.n_dims == 3:
        return scans.poses[:, :3], scans.poses[:, 3:]
    half = scans.poses[:, 2] / 2.0
    zeros = np.zeros(len(scans))
    translations = np.column_stack([scans.poses[:, :2], zeros])
    return translations, np.column_stack([np.cos(half), zeros, zeros, np.sin(half)])


# A ROS graph resource name (ROS 1 and ROS 2 alike): tokens of letters, digits and
# underscores, not starting with a digit, separated by single slashes, optionally absolute.
_TOPIC = re.compile(r"/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*")


def _check_topic(topic, name):
    if not (isinstance(topic, str) and _TOPIC.fullmatch(topic)):
        raise ValueError(
            f"{name} must be a ROS topic name (letters, digits and underscores between single "
            f"slashes, not starting with a digit, e.g. '/map'), got {topic!r}."
        )


def write_rosbag(
    scans,
    path,
    *,
    scan_topic="/scan",
    laser_frame="laser",
    map_frame="map",
    ros_version=2,
    storage="sqlite3",
):
    """Write scans into a new ROS bag: ``sensor_msgs/LaserScan`` and their poses on ``/tf``.

    Turns a CARMEN log or simulated scans into the recording a ROS tool expects; read it back
    with :func:`load_rosbag`.

    Parameters
    ----------
    scans : skoccmap.observations.Scans
        Scans with evenly spaced beams in the laser's plane (2-D scans, or 3-D scans whose
        beam directions have no z component).
    path : str or path-like
        The new bag: a ``.bag`` file for ROS 1, a directory for ROS 2. It must not exist.
    scan_topic : str, default="/scan"
        Topic of the scans.
    laser_frame, map_frame : str, default="laser", "map"
        ``header.frame_id`` of the scans; the laser pose of every scan is the transform
        ``map_frame`` -> ``laser_frame`` on ``/tf``, stamped like its scan.
    ros_version : {1, 2}, default=2
        Bag format.
    storage : {"sqlite3", "mcap"}, default="sqlite3"
        ROS 2 storage plugin.

    Returns
    -------
    path : pathlib.Path
        The bag written.

    Notes
    -----
    Each scan is stamped with its timestamp (``0, 1, 2, ..`` seconds when ``scans`` has
    none), which must lie in ``[0, 2**31)`` s (ROS 2 stamps are signed 32-bit seconds, and
    the ``rosbags`` writer packs ROS 1 seconds as signed 32-bit too); a ValueError
    otherwise, and for two scans at one stamp in different poses, since the bag holds one
    laser pose per time). Ranges are stored as float32 (as
    LaserScan defines them); no-return beams as ``+inf``, ``range_min`` 0 and ``range_max``
    the scans' ``max_range``.

    Examples
    --------
    >>> import os, tempfile
    >>> from rosbags.highlevel import AnyReader
    >>> from skoccmap.datasets import make_paper_scans, write_rosbag
    >>> scans = make_paper_scans(random_state=0).scans[:3]
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     bag = write_rosbag(scans, os.path.join(tmp, "paper.bag"), ros_version=1)
    ...     with AnyReader([bag]) as reader:
    ...         topics = {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
    >>> topics["/scan"]
    ('sensor_msgs/msg/LaserScan', 3)
    >>> topics["/tf"][0]
    'tf2_msgs/msg/TFMessage'
    """
    from ..observations import Scans

    _import_rosbags()
    if not isinstance(scans, Scans):
        raise ValueError(f"scans must be a skoccmap.observations.Scans, got {type(scans)}.")
    _check_topic(scan_topic, "scan_topic")
    angle_min, increment = _scan_geometry(scans)
    _check_ros_version(ros_version)
    timestamps = scans.timestamps
    if timestamps is None:
        timestamps = np.arange(len(scans), dtype=np.float64)
    timestamps = np.asarray(timestamps, dtype=np.float64)
    _check_stamps(timestamps, ros_version, "the scans' timestamps")
    stamps = np.rint(timestamps * _NS).astype(np.int64)
    translations, rotations = _laser_transforms(scans)
    _check_one_pose_per_stamp(stamps, translations, rotations)
    # Readings of 0 (no measurement) stay 0, and read back as 0.
    kept = scans.returned() | scans.unread()
    ranges = np.where(kept, scans.ranges, np.inf).astype(np.float32)
    with _BagWriter(path, ros_version, storage) as bag:
        store = bag.store
        scan_conn = bag.connection(scan_topic, _LASER_SCAN)
        tf_conn = bag.connection("/tf", _TF_MESSAGE)
        for i in np.argsort(stamps, kind="stable"):
            tf = _transform_stamped(
                store, stamps[i], map_frame, laser_frame, translations[i], rotations[i]
            )
            bag.write(tf_conn, stamps[i], store.types[_TF_MESSAGE](transforms=[tf]))
            scan = store.types[_LASER_SCAN](
                header=_header(store, stamps[i], laser_frame),
                angle_min=float(angle_min[i]),
                angle_max=float(angle_min[i] + increment[i] * (scans.n_beams - 1)),
                angle_increment=float(increment[i]),
                time_increment=0.0,
                scan_time=0.0,
                range_min=0.0,
                range_max=float(scans.max_range),
                ranges=ranges[i],
                intensities=np.zeros(0, dtype=np.float32),
            )
            bag.write(scan_conn, stamps[i], scan)
    return Path(path)


def _check_one_pose_per_stamp(stamps, translations, rotations):
    """ValueError for two scans at one stamp in different poses: the bag keeps one
    transform per stamp, and one of them would read back in the other's pose."""
    order = np.argsort(stamps, kind="stable")
    same = np.flatnonzero(np.diff(stamps[order]) == 0)
    if same.size == 0:
        return
    a, b = order[same], order[same + 1]
    differ = ~(
        np.all(translations[a] == translations[b], axis=1)
        & np.all(rotations[a] == rotations[b], axis=1)
    )
    if np.any(differ):
        i, j = sorted((int(a[differ][0]), int(b[differ][0])))
        raise ValueError(
            f"scans {i} and {j} share the timestamp {stamps[i] / _NS:.9g} s in different "
            "poses: a bag holds one laser pose per time, so one of them would read back in "
            "the other's pose. Give every scan its own timestamp."
        )


def _occupancy_grid_message(store, fields, stamp_ns):
    """A ``nav_msgs/OccupancyGrid`` of ``store`` from the dict of
    :meth:`skoccmap.OccupancyGrid.to_ros_occupancy_grid`."""
    types = store.types
    info, origin = fields["info"], fields["info"]["origin"]
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](**origin["position"]),
        orientation=types["geometry_msgs/msg/Quaternion"](**origin["orientation"]),
    )
    meta = types["nav_msgs/msg/MapMetaData"](
        map_load_time=_time(store, stamp_ns),
        resolution=float(info["resolution"]),
        width=int(info["width"]),
        height=int(info["height"]),
        origin=pose,
    )
    return types[_OCCUPANCY_GRID](
        header=_header(store, stamp_ns, fields["header"]["frame_id"]),
        info=meta,
        data=np.ascontiguousarray(fields["data"], dtype=np.int8),
    )


def _stamp_to_ns(stamp, ros_version):
    import time

    stamp = time.time() if stamp is None else stamp
    if not is_number(stamp):
        raise TypeError(f"stamp must be a time in seconds (a number) or None, got {stamp!r}.")
    if not np.isfinite(stamp):
        raise ValueError(f"stamp must be a finite time in seconds, got {stamp!r}.")
    _check_stamps(np.array([float(stamp)]), ros_version, "stamp")
    return int(round(float(stamp) * _NS))


def _check_stamps(seconds, ros_version, what):
    """ValueError for times a bag of ``ros_version`` cannot hold: ROS 2 stamps are signed
    32-bit seconds (its bags' own mcap times are unsigned). ROS 1 defines unsigned 32-bit
    seconds, but the ``rosbags`` writer packs them as signed: from 2**31 s (2038) it would
    fail with a ``struct.error`` half-way through the bag."""
    lo, hi = 0.0, 2.0**31
    bad = ~((seconds >= lo) & (seconds < hi))
    if np.any(bad):
        raise ValueError(
            f"{what} must lie in [{lo:.0f}, {hi:.0f}) seconds for a ROS {ros_version} bag, got "
            f"{float(seconds[bad][0]):.9g}; times are seconds (since the epoch, or relative), not "
            "milliseconds."
        )


def occupancy_grid_message(fields, *, stamp=None, ros_version=2):
    """A ``rosbags`` ``nav_msgs/OccupancyGrid`` message built from a fields dict."""
    _import_rosbags()
    _check_ros_version(ros_version)
    return _occupancy_grid_message(
        _typestore(ros_version), fields, _stamp_to_ns(stamp, ros_version)
    )


def write_occupancy_grid(fields, path, *, topic, stamp, ros_version, storage):
    """Write one ``nav_msgs/OccupancyGrid`` on a latched topic into a new bag."""
    _import_rosbags()
    _check_topic(topic, "topic")
    _check_ros_version(ros_version)
    stamp_ns = _stamp_to_ns(stamp, ros_version)
    with _BagWriter(path, ros_version, storage) as bag:
        message = _occupancy_grid_message(bag.store, fields, stamp_ns)
        bag.write(bag.connection(topic, _OCCUPANCY_GRID, latched=True), stamp_ns, message)
    return Path(path)
