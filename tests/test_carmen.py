import gzip
import warnings

import numpy as np
import pytest

from skoccmap.datasets._carmen import flaser_angles, load_carmen
from skoccmap.observations import Scans


def _flaser(ranges, pose, timestamp=1.0, odometry=None):
    """A FLASER line: the laser's pose, then the odometry (the laser's pose by default)."""
    odometry = pose if odometry is None else odometry
    fields = ["FLASER", str(len(ranges)), *map(str, ranges), *map(str, pose), *map(str, odometry)]
    return " ".join(fields + [str(timestamp), "host", str(timestamp)]) + "\n"


def _robotlaser(
    ranges, pose, *, start, resolution, max_range, remissions=(), timestamp=2.0, robot_pose=None
):
    """A ROBOTLASER1 line: the laser's pose, then the robot's (the laser's by default)."""
    robot_pose = pose if robot_pose is None else robot_pose
    fields = ["ROBOTLASER1", "0", str(start), str(resolution * len(ranges)), str(resolution)]
    fields += [str(max_range), "0.01", "0", str(len(ranges)), *map(str, ranges)]
    fields += [str(len(remissions)), *map(str, remissions), *map(str, pose)]
    fields += [*map(str, robot_pose)]
    fields += ["0", "0", "0.5", "0.5", "0", str(timestamp), "host", str(timestamp)]
    return " ".join(fields) + "\n"


# Two readings and two remissions: 9 fields up to the beam count, 2 readings, the remission
# count, 2 remissions, then 12 fields up to ipc_timestamp, hostname and logger_timestamp: 28.
_ROBOT_FIELDS = _robotlaser(
    [1.0, 2.0], [0, 0, 0], start=-0.5, resolution=0.25, max_range=30.0, remissions=(7, 8)
).split()
assert len(_ROBOT_FIELDS) == 28


def _robot_line(fields):
    return " ".join(fields) + "\n"


@pytest.fixture
def tiny_log(tmp_path):
    """Three FLASER scans of 4 beams with an 80 m sentinel, plus lines the reader must ignore."""
    lines = [
        "# message formats defined: FLASER ODOM\n",
        "PARAM robot_front_laser_max 80\n",
        _flaser([1.0, 2.0, 80.0, 1.5], [0.0, 0.0, 0.0], 10.0),
        "ODOM 0 0 0 0 0 0 10.1 host 10.1\n",
        "\n",
        # Its odometry differs from its laser pose, which places the scan.
        _flaser([3.0, 80.0, 80.0, 0.5], [1.0, 2.0, np.pi / 2], 11.0, [0.9, 1.7, 1.5]),
        _flaser([2.5, 2.5, 2.5, 2.5], [-1.0, 0.5, -np.pi], 12.0),
    ]
    path = tmp_path / "tiny.log"
    path.write_text("".join(lines))
    return path


def test_flaser_angles_conventions():
    # 180 beams: 1 degree steps from -90 deg, the last beam one step short of +90 deg.
    a = flaser_angles(180)
    np.testing.assert_allclose(a[[0, 90, 179]], np.deg2rad([-90.0, 0.0, 89.0]), atol=1e-12)
    # 181 and 361 beams include both ends.
    for n in (181, 361):
        a = flaser_angles(n)
        np.testing.assert_allclose([a[0], a[(n - 1) // 2], a[-1]], [-np.pi / 2, 0, np.pi / 2])
    np.testing.assert_allclose(np.diff(flaser_angles(360)), np.pi / 360)


def test_tiny_log_fields(tiny_log):
    scans = load_carmen(tiny_log)
    assert isinstance(scans, Scans)
    assert len(scans) == 3 and scans.ranges.shape == (3, 4)
    assert scans.max_range == 80.0  # the largest reading is the sentinel
    np.testing.assert_array_equal(scans.ranges[0], [1.0, 2.0, np.inf, 1.5])
    np.testing.assert_array_equal(scans.ranges[1], [3.0, np.inf, np.inf, 0.5])
    np.testing.assert_allclose(scans.poses[1], [1.0, 2.0, np.pi / 2])
    np.testing.assert_allclose(scans.timestamps, [10.0, 11.0, 12.0])
    np.testing.assert_allclose(scans.angles, -np.pi / 2 + np.pi / 4 * np.arange(4))


def test_tiny_log_hit_points_by_hand(tiny_log):
    # Scan 1 sits at (1, 2) facing +y; its beam 0 points at heading - 90 deg = +x, range 3.
    # Beam 3 points at heading - 90 + 135 deg = +y rotated by 45 deg, range 0.5.
    scans = load_carmen(tiny_log)[1]
    hits = scans.hit_points()
    expected = [[4.0, 2.0], [1.0 - 0.5 * np.sqrt(0.5), 2.0 + 0.5 * np.sqrt(0.5)]]
    np.testing.assert_allclose(hits, expected, atol=1e-12)


def test_explicit_max_range_and_slicing(tiny_log):
    scans = load_carmen(tiny_log, max_range=2.5)
    # readings >= 2.5 are no-return beams
    assert np.isinf(scans.ranges[2]).all()
    assert np.isinf(scans.ranges[1, 0])
    sub = scans[::2]
    assert len(sub) == 2
    np.testing.assert_array_equal(sub.timestamps, [10.0, 12.0])


def test_gzip_is_detected_from_content(tiny_log, tmp_path):
    plain = load_carmen(tiny_log)
    for name in ("tiny.log.gz", "no_suffix"):
        path = tmp_path / name
        path.write_bytes(gzip.compress(tiny_log.read_bytes()))
        packed = load_carmen(path)
        np.testing.assert_array_equal(packed.ranges, plain.ranges)
        np.testing.assert_array_equal(packed.poses, plain.poses)


def test_truncated_gzip_says_so(tiny_log, tmp_path):
    path = tmp_path / "cut.log.gz"
    path.write_bytes(gzip.compress(tiny_log.read_bytes())[:-6])
    with pytest.raises(ValueError, match=r"cut.log.gz: the compressed log is damaged or trunc"):
        load_carmen(path)
    with pytest.warns(UserWarning, match="damaged or truncated after line 7.*are kept"):
        scans = load_carmen(path, errors="skip")
    np.testing.assert_array_equal(scans.ranges, load_carmen(tiny_log).ranges)


def test_damaged_gzip_says_so(tiny_log, tmp_path):
    packed = gzip.compress(tiny_log.read_bytes())
    # A byte flipped just after the 10-byte header breaks the deflate stream (zlib.error);
    # one flipped in the trailer breaks only the checksum (gzip.BadGzipFile), after every line.
    body = bytearray(packed)
    body[12] ^= 0xFF
    crc = bytearray(packed)
    crc[-6] ^= 0xFF
    for name, data in (("body.log.gz", body), ("crc.log.gz", crc)):
        path = tmp_path / name
        path.write_bytes(bytes(data))
        with pytest.raises(ValueError, match=rf"{name}: the compressed log is damaged"):
            load_carmen(path)
    with pytest.warns(UserWarning, match="damaged or truncated after line 7"):
        scans = load_carmen(tmp_path / "crc.log.gz", errors="skip")
    np.testing.assert_array_equal(scans.ranges, load_carmen(tiny_log).ranges)


def test_non_ascii_bytes_and_trailing_comments(tmp_path):
    # A comment in Latin-1 and a hostname in UTF-8 do not stop the reader; a comment after a
    # message is not read as its fields.
    line = _flaser([1.0, 2.0, 3.0], [0.5, 0.0, 0.0], 4.0)
    text = b"# caf\xe9\n" + line.replace("host", "h\u00f6st").encode("utf-8")
    text += line.replace("\n", "  # a note: 1 2 3\n").encode("ascii")
    for name, data in (("plain.log", text), ("packed.log.gz", gzip.compress(text))):
        path = tmp_path / name
        path.write_bytes(data)
        scans = load_carmen(path, max_range=10.0)
        np.testing.assert_array_equal(scans.ranges, [[1.0, 2.0, 3.0]] * 2)
        np.testing.assert_array_equal(scans.timestamps, [4.0, 4.0])


def test_skip_warning_counts_the_lines_it_does_not_list(tiny_log):
    # Six bad lines: five listed by number, the sixth counted.
    bad = ["FLASER 4 1.0\n"] * 6
    tiny_log.write_text(tiny_log.read_text() + "".join(bad))  # lines 8 to 13
    listed = ", ".join(f"line {n} .3 fields[^)]*." for n in range(8, 13))
    with pytest.warns(
        UserWarning, match=rf"skipped 6 malformed laser line\(s\): {listed} and 1 more\."
    ):
        scans = load_carmen(tiny_log, errors="skip")
    assert len(scans) == 3


def test_flaser_angles_needs_two_beams():
    for n in (0, 1):
        with pytest.raises(ValueError, match="n_beams must be at least 2"):
            flaser_angles(n)


def test_robotlaser_uses_its_own_geometry(tmp_path):
    path = tmp_path / "robot.log"
    line = _robotlaser(
        [1.0, 2.0, 30.0],
        [0.5, 0.0, 0.0],
        start=-0.5,
        resolution=0.25,
        max_range=30.0,
        remissions=(7, 8),
        robot_pose=[0.0, 0.0, 0.0],  # the beams start from the laser, not the robot's centre
    )
    # A FLASER copy of the same scan: with ROBOTLASER1 present it is not read twice.
    path.write_text(line + _flaser([1.0, 2.0, 30.0], [0.5, 0.0, 0.0]))
    scans = load_carmen(path)
    assert len(scans) == 1 and scans.max_range == 30.0
    np.testing.assert_allclose(scans.angles, [-0.5, -0.25, 0.0])
    np.testing.assert_array_equal(scans.ranges[0], [1.0, 2.0, np.inf])
    assert scans.timestamps[0] == 2.0
    np.testing.assert_allclose(scans.hit_points()[0], [0.5 + np.cos(-0.5), np.sin(-0.5)])
    only_flaser = load_carmen(path, message="FLASER")
    np.testing.assert_allclose(only_flaser.angles, flaser_angles(3))


def test_robotlaser_scans_keep_angles_that_differ_between_scans(tmp_path):
    path = tmp_path / "two.log"
    path.write_text(
        _robotlaser([1.0, 2.0, 3.0], [0.0, 0.0, 0.0], start=-0.5, resolution=0.25, max_range=30.0)
        + _robotlaser([2.0, 2.0, 2.0], [1.0, 2.0, 0.3], start=0.1, resolution=0.25, max_range=30.0)
    )
    scans = load_carmen(path)
    assert scans.angles.shape == (2, 3)
    np.testing.assert_allclose(scans.angles, [[-0.5, -0.25, 0.0], [0.1, 0.35, 0.6]])
    # The second scan's first beam points at its heading 0.3 plus its own start angle 0.1.
    np.testing.assert_allclose(
        scans.hit_points()[3], [1.0 + 2.0 * np.cos(0.4), 2.0 + 2.0 * np.sin(0.4)]
    )


def test_robotlaser_max_range_is_the_smallest_stated(tmp_path):
    # Scans stating 30 and 20 m: beyond 20 m the second cannot tell a return from none.
    path = tmp_path / "two.log"
    scan = dict(start=-0.5, resolution=0.25)
    path.write_text(
        _robotlaser([1.0, 25.0, 20.0], [0.0, 0.0, 0.0], max_range=30.0, timestamp=1.0, **scan)
        + _robotlaser([1.0, 2.0, 20.0], [1.0, 0.0, 0.0], max_range=20.0, timestamp=2.0, **scan)
    )
    scans = load_carmen(path)
    assert scans.max_range == 20.0
    np.testing.assert_array_equal(scans.ranges[0], [1.0, np.inf, np.inf])


def test_robotlaser_lines_stating_an_infinite_max_range_need_max_range(tmp_path):
    # No finite range stated: the longest reading (a return at 3 m) must not be taken for
    # the sensor's range and read as a beam without a return.
    path = tmp_path / "inf.log"
    scan = dict(start=-0.5, resolution=0.25, max_range=np.inf)
    path.write_text(
        _robotlaser([1.0, 3.0, 2.0], [0.0, 0.0, 0.0], timestamp=1.0, **scan)
        + _robotlaser([1.0, 2.0, 2.5], [1.0, 0.0, 0.0], timestamp=2.0, **scan)
    )
    with pytest.raises(ValueError, match=r"state an infinite maximum range \(line 1 the first"):
        load_carmen(path)
    scans = load_carmen(path, max_range=2.5)
    assert scans.max_range == 2.5
    np.testing.assert_array_equal(scans.ranges, [[1.0, np.inf, 2.0], [1.0, 2.0, np.inf]])
    # With a line stating a finite range, that range is the log's.
    path.write_text(
        _robotlaser([1.0, 3.0, 2.0], [0.0, 0.0, 0.0], timestamp=1.0, **scan)
        + _robotlaser(
            [1.0, 2.0, 2.5], [1.0, 0.0, 0.0], timestamp=2.0, **(scan | dict(max_range=5.0))
        )
    )
    np.testing.assert_array_equal(load_carmen(path).ranges, [[1.0, 3.0, 2.0], [1.0, 2.0, 2.5]])


@pytest.mark.parametrize(
    "bad_line, reason",
    [
        ("FLASER 4 1.0 2.0 3.0\n", "fields"),
        ("FLASER four 1 2 3 4 0 0 0 0 0 0 1 host 1\n", "not an integer"),
        ("FLASER 4 1.0 x 3.0 4.0 0 0 0 0 0 0 1 host 1\n", "non-numeric"),
        ("FLASER 4 1.0 -2 3.0 4.0 0 0 0 0 0 0 1 host 1\n", "negative"),
        ("FLASER 4 1.0 2 3.0 4.0 nan 0 0 0 0 0 1 host 1\n", "non-finite"),
        # A beam count that does not match the readings: 4 readings, counts 3 and 6.
        ("FLASER 3 1 2 3 4 0 0 0 0 0 0 12.5 host 12.5\n", "15 fields, expected 12 to 14"),
        ("FLASER 3 1 2 3 4 0 0 0 0 0 0 12.5 host\n", "field 13 .'12.5'. should be the host"),
        ("FLASER 6 1 2 3 4 0 0 0 0 0 0 12.5 host 12.5\n", "non-numeric pose"),
        (
            _robotlaser([1.0, 2.0], [0, 0, 0], start=np.nan, resolution=0.1, max_range=8.0),
            "start angle must be finite",
        ),  # fmt: skip
        ("FLASER\n", "missing the beam count"),
        ("FLASER 1 2.0 0 0 0 0 0 0 1 host 1\n", "beam count is 1; a scan needs at least 2"),
        ("FLASER 4 1.0 2 3.0 4.0 0 0 0 0 0 0 nan host nan\n", "non-finite pose or timestamp"),
        # ROBOTLASER1 lines cut short: before the beam count, after the readings, and
        # before ipc_timestamp (25 of the 26 fields up to it).
        (_robot_line(_ROBOT_FIELDS[:8]), "too few fields before the readings"),
        (_robot_line(_ROBOT_FIELDS[:11]), "11 fields, too few for 2 readings"),
        (_robot_line(_ROBOT_FIELDS[:-3]), "25 fields, expected at least 26"),
        (_robot_line(_ROBOT_FIELDS[:11] + ["-1"] + _ROBOT_FIELDS[12:]), "and -1 remissions"),
        (
            _robotlaser([1.0, 2.0], [0, 0, 0], start=-0.5, resolution=0.0, max_range=8.0),
            "angular resolution and maximum range positive",
        ),
        (
            _robotlaser([1.0, 2.0], [0, 0, 0], start=-0.5, resolution=0.1, max_range=0.0),
            "angular resolution and maximum range positive",
        ),
        # An overflow warning, then "angles contains NaN or infinite values" for the whole
        # log, naming no line (so errors="skip" could not skip it).
        (
            _robotlaser([1.0, 2.0], [0, 0, 0], start=1e308, resolution=1e308, max_range=8.0),
            "the beam angles overflow",
        ),
    ],
)
def test_malformed_line_raises_with_line_number(tiny_log, bad_line, reason):
    text = tiny_log.read_text().splitlines(keepends=True)
    text.insert(3, bad_line)  # becomes line 4
    tiny_log.write_text("".join(text))
    with pytest.raises(ValueError, match=rf"line 4: malformed {bad_line.split()[0]}.*{reason}"):
        load_carmen(tiny_log)
    with pytest.warns(UserWarning, match=r"skipped 1 malformed laser line\(s\): line 4"):
        scans = load_carmen(tiny_log, errors="skip")
    assert len(scans) == 3


def test_infinite_readings_are_beams_without_a_return(tmp_path):
    # The sentinel is inferred from the finite readings; inf (or 1e400) is no return.
    path = tmp_path / "inf.log"
    lines = [_flaser([1.0, 2.0, "inf", 1.5], [0, 0, 0]), _flaser([1, "1e400", 8, 1.5], [0, 0, 0])]
    path.write_text("".join(lines))
    with pytest.warns(UserWarning, match=r"writes inf.*longest finite reading \(8 m\)") as caught:
        scans = load_carmen(path)
    assert [w.filename for w in caught] == [__file__]  # the caller's line, not the reader's
    assert scans.max_range == 8.0
    np.testing.assert_array_equal(scans.returned(), [[1, 1, 0, 1], [1, 0, 0, 1]])
    nan = tmp_path / "nan.log"
    nan.write_text(_flaser(["nan"] * 4, [0, 0, 0]))
    with pytest.raises(ValueError, match="no positive finite range reading.*pass max_range"):
        load_carmen(nan)
    zeros = tmp_path / "zeros.log"
    zeros.write_text(_flaser([0.0] * 4, [0, 0, 0]) * 12)
    with pytest.raises(ValueError, match=r"every finite range reading is 0 \(no measurement"):
        load_carmen(zeros)
    # Readings of 0 are dropped, not hits: no advice to lower max_range to the "sentinel".
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.all(load_carmen(zeros, max_range=50.0).ranges == 0.0)


def test_bad_arguments_and_empty_logs(tiny_log, tmp_path):
    with pytest.raises(ValueError, match="errors"):
        load_carmen(tiny_log, errors="ignore")
    with pytest.raises(ValueError, match="message"):
        load_carmen(tiny_log, message="RLASER")
    # Refused before the file is opened: a path that does not exist is not reached.
    for bad in (-1.0, 0.0, np.inf, np.nan):
        with pytest.raises(ValueError, match="max_range must be a positive finite number"):
            load_carmen(tmp_path / "missing.log", max_range=bad)
    # Not a length: True is not read as 1 m, nor a string compared with the ranges or read
    # as a number.
    for bad in (True, "far", "8"):
        with pytest.raises(ValueError, match="max_range must be a positive number"):
            load_carmen(tmp_path / "missing.log", max_range=bad)
    empty = tmp_path / "empty.log"
    empty.write_text("# nothing\nODOM 0 0 0 0 0 0 1 host 1\n")
    with pytest.raises(ValueError, match="no valid FLASER or ROBOTLASER1"):
        load_carmen(empty)
    with pytest.raises(ValueError, match="no valid ROBOTLASER1"):
        load_carmen(tiny_log, message="ROBOTLASER1")
    mixed = tmp_path / "mixed.log"
    mixed.write_text(_flaser([1.0, 2.0], [0, 0, 0]) + _flaser([1.0, 2.0, 3.0], [0, 0, 0]))
    with pytest.raises(ValueError, match="different beam counts"):
        load_carmen(mixed)


@pytest.mark.parametrize(
    "name, n_scans, sentinel, no_return_fraction, hit_box",
    [
        ("intel.gfs.log", 910, 81.83, 0.025, (-19.9, 18.8, -23.2, 12.8)),
        ("aces-corrected.log.gz", 440, 50.0, 0.008, (-26.4, 30.7, -47.6, 9.2)),
    ],
)
def test_shared_logs(shared_data, name, n_scans, sentinel, no_return_fraction, hit_box):
    # Figures from the data README, measured independently of this reader.
    scans = load_carmen(shared_data / name)
    assert scans.ranges.shape == (n_scans, 180)
    assert scans.max_range == pytest.approx(sentinel)
    assert np.isinf(scans.ranges).mean() == pytest.approx(no_return_fraction, abs=0.001)
    hits = scans.hit_points()
    box = (hits[:, 0].min(), hits[:, 0].max(), hits[:, 1].min(), hits[:, 1].max())
    np.testing.assert_allclose(box, hit_box, atol=0.06)
    # First and last scans against a plain split of the raw lines.
    opener = gzip.open if name.endswith(".gz") else open
    with opener(shared_data / name, "rt") as fh:
        lines = [line.split() for line in fh if line.startswith("FLASER")]
    for index in (0, -1):
        fields = lines[index]
        assert scans.timestamps[index] == float(fields[-3])
        np.testing.assert_array_equal(scans.poses[index], np.array(fields[182:185], float))


def test_max_range_above_the_sentinel_warns(tmp_path):
    # 12 readings at 40 m, the log's largest: CARMEN's sentinel. Above it, they are hits.
    lines = [_flaser([1.5, 40.0, 2.0, 40.0], [float(i), 0.0, 0.0], i) for i in range(6)]
    path = tmp_path / "log"
    path.write_text("".join(lines))
    with pytest.warns(UserWarning, match=r"12 readings equal 40 m.*max_range=100 they are hits"):
        scans = load_carmen(path, max_range=100.0)
    assert np.isfinite(scans.ranges).all()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isinf(load_carmen(path).ranges[:, 1]).all()  # the sentinel, inferred
        load_carmen(path, max_range=30.0)  # below the sentinel: no-return beams
        # At the sentinel: no-return beams too.
        assert np.isinf(load_carmen(path, max_range=40.0).ranges[:, 1]).all()
    # A largest reading seen a few times is a real one: no warning.
    path.write_text("".join(lines[:4]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_carmen(path, max_range=100.0)


def test_sentinel_warning_from_ten_repeats(tmp_path):
    # The documented threshold: the largest reading seen 10 times is the sentinel, 9 times
    # a real reading. Five scans with two 40 m readings each; then the last with one.
    lines = [_flaser([1.5, 40.0, 2.0, 40.0], [float(i), 0.0, 0.0], i) for i in range(5)]
    path = tmp_path / "log"
    path.write_text("".join(lines))
    with pytest.warns(UserWarning, match=r"10 readings equal 40 m") as caught:
        load_carmen(path, max_range=100.0)
    # The warning points at the caller, not into the reader.
    assert [w.filename for w in caught] == [__file__]
    lines[-1] = _flaser([1.5, 40.0, 2.0, 3.0], [4.0, 0.0, 0.0], 4)
    path.write_text("".join(lines))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scans = load_carmen(path, max_range=100.0)
    assert np.isfinite(scans.ranges).all()


def test_a_log_without_returns_reads_with_max_range(tmp_path):
    # Every beam without a return (an open field): no sentinel to infer, but with max_range
    # the log reads, all beams free to max_range.
    path = tmp_path / "open.log"
    path.write_text(_flaser(["inf"] * 4, [0.0, 0.0, 0.0], 1.0) * 3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scans = load_carmen(path, max_range=30.0)
    assert scans.max_range == 30.0 and np.isinf(scans.ranges).all()
    assert not scans.returned().any()
