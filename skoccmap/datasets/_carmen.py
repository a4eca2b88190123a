"""Reader for CARMEN laser logs (``FLASER`` and ``ROBOTLASER1`` messages).

A CARMEN log is plain text (optionally gzip-compressed), one message per line, fields separated
by whitespace, ``#`` starting a comment. Two messages carry laser scans:

``FLASER n r_1 .. r_n x y theta odom_x odom_y odom_theta ipc_timestamp hostname logger_timestamp``
    A front laser scan with the laser's pose ``(x, y, theta)`` in the world frame. The beam
    directions are implied by the beam count (a 180 degree field of view, see
    :func:`flaser_angles`).

``ROBOTLASER1 laser_type start_angle fov resolution max_range accuracy remission_mode n r_1 .. r_n
m e_1 .. e_m laser_x laser_y laser_theta robot_x robot_y robot_theta tv rv forward_safety
side_safety turn_axis ipc_timestamp hostname logger_timestamp``
    A scan that carries its own geometry: beam ``i`` points at ``start_angle + i * resolution``
    relative to the laser's heading, and ``max_range`` is the sensor's range.
"""

import gzip
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._validation import caller_stacklevel

__all__ = ["load_carmen", "flaser_angles"]

# Fields after the n readings of a FLASER line, up to and including ipc_timestamp.
_FLASER_TAIL = 7
# Fields after the remissions of a ROBOTLASER1 line, up to and including ipc_timestamp.
_ROBOTLASER_TAIL = 12


def flaser_angles(n_beams):
    """Beam angles of a ``FLASER`` scan, relative to the laser's heading.

    ``FLASER`` lines do not store their geometry; CARMEN's convention is a 180 degree field of
    view starting at ``-pi/2``. With an even beam count (180, 360) beam ``i`` points at
    ``-pi/2 + i * pi / n``; with an odd count (181, 361) the scan includes both ends and beam
    ``i`` points at ``-pi/2 + i * pi / (n - 1)``.

    Parameters
    ----------
    n_beams : int
        Number of readings in the scan (at least 2).

    Returns
    -------
    angles : ndarray of shape (n_beams,)
        Radians, counter-clockwise from the laser's heading.

    Examples
    --------
    >>> from skoccmap.datasets import flaser_angles
    >>> a = flaser_angles(181)
    >>> float(a[0]), float(a[90]), float(a[-1])
    (-1.5707963267948966, 0.0, 1.5707963267948966)
    >>> round(float(flaser_angles(180)[1] - flaser_angles(180)[0]), 6)
    0.017453
    """
    n_beams = int(n_beams)
    if n_beams < 2:
        raise ValueError(f"n_beams must be at least 2, got {n_beams}.")
    step = np.pi / (n_beams - 1 if n_beams % 2 else n_beams)
    return -np.pi / 2 + step * np.arange(n_beams)


@dataclass
class _Reading:
    lineno: int
    message: str
    pose: tuple
    ranges: np.ndarray
    angles: np.ndarray
    max_range: float  # NaN for FLASER: the log does not say
    timestamp: float


class _MalformedLine(ValueError):
    pass


def _floats(tokens, what):
    try:
        return np.array(tokens, dtype=np.float64)
    except ValueError:
        raise _MalformedLine(f"non-numeric {what}") from None


def _count(token, what):
    try:
        n = int(token)
    except ValueError:
        raise _MalformedLine(f"{what} {token!r} is not an integer") from None
    if n < 2:
        raise _MalformedLine(f"{what} is {n}; a scan needs at least 2 readings")
    return n


def _is_number(token):
    try:
        float(token)
    except ValueError:
        return False
    return True


def _parse_flaser(tokens, lineno):
    if len(tokens) < 2:
        raise _MalformedLine("missing the beam count")
    n = _count(tokens[1], "beam count")
    # A beam count that does not match the readings shifts every later field: the tail
    # must end at ipc_timestamp, or go on with a hostname (not a number) and perhaps the
    # logger_timestamp.
    short = 2 + n + _FLASER_TAIL
    if not short <= len(tokens) <= short + 2:
        raise _MalformedLine(
            f"{len(tokens)} fields, expected {short} to {short + 2} for {n} readings"
        )
    if len(tokens) > short and _is_number(tokens[short]):
        raise _MalformedLine(
            f"field {short + 1} ({tokens[short]!r}) should be the hostname: the beam count "
            f"{n} does not match the readings"
        )
    ranges = _floats(tokens[2 : 2 + n], "range reading")
    tail = _floats(tokens[2 + n : 2 + n + _FLASER_TAIL], "pose, odometry or timestamp")
    pose, timestamp = tail[:3], tail[6]
    return _Reading(lineno, "FLASER", pose, ranges, flaser_angles(n), np.nan, timestamp)


def _parse_robotlaser(tokens, lineno):
    if len(tokens) < 9:
        raise _MalformedLine("too few fields before the readings")
    start, fov, resolution, max_range = _floats(tokens[2:6], "laser geometry")
    n = _count(tokens[8], "beam count")
    if len(tokens) < 10 + n:
        raise _MalformedLine(f"{len(tokens)} fields, too few for {n} readings")
    ranges = _floats(tokens[9 : 9 + n], "range reading")
    try:
        n_remissions = int(tokens[9 + n])
    except ValueError:
        raise _MalformedLine("remission count is not an integer") from None
    tail = 10 + n + n_remissions
    if n_remissions < 0 or len(tokens) < tail + _ROBOTLASER_TAIL:
        raise _MalformedLine(
            f"{len(tokens)} fields, expected at least {tail + _ROBOTLASER_TAIL} for {n} readings "
            f"and {n_remissions} remissions"
        )
    pose = _floats(tokens[tail : tail + 3], "laser pose")
    timestamp = _floats(tokens[tail + 11 : tail + 12], "timestamp")[0]
    if not (np.isfinite(start) and np.isfinite(resolution) and resolution > 0 and max_range > 0):
        raise _MalformedLine(
            "start angle must be finite, angular resolution and maximum range positive"
        )
    with np.errstate(over="ignore", invalid="ignore"):
        angles = start + resolution * np.arange(n)
    if not np.all(np.isfinite(angles)):
        # Caught here, the line is named (and errors="skip" can skip it).
        raise _MalformedLine("the beam angles overflow (start angle or angular resolution)")
    return _Reading(lineno, "ROBOTLASER1", pose, ranges, angles, max_range, timestamp)


_PARSERS = {"FLASER": _parse_flaser, "ROBOTLASER1": _parse_robotlaser}


def _open_text(path):
    path = Path(path)
    with open(path, "rb") as fh:
        magic = fh.read(2)
    if magic == b"\x1f\x8b":  # gzip, whatever the file is called
        return gzip.open(path, "rt", encoding="ascii", errors="replace")
    return open(path, encoding="ascii", errors="replace")


# The hint of a malformed-line error; the ``skoccmap`` command replaces it by its option.
SKIP_HINT = "Pass errors='skip' to skip malformed lines with a warning."


def _lines(fh, path, errors, skipped):
    """The file's lines; a compressed log that ends early raises, or with ``errors="skip"``
    ends there with the rest counted as skipped."""
    lineno = 0
    try:
        for lineno, line in enumerate(fh, start=1):
            yield lineno, line
    except (EOFError, gzip.BadGzipFile, zlib.error) as exc:
        if errors == "raise":
            raise ValueError(
                f"{path}: the compressed log is damaged or truncated after line {lineno} "
                f"({exc}). {SKIP_HINT}"
            ) from None
        warnings.warn(
            f"{path}: the compressed log is damaged or truncated after line {lineno} ({exc}); "
            "the scans read up to there are kept.",
            UserWarning,
            stacklevel=caller_stacklevel(),
        )


def _read_lines(path, messages, errors):
    readings, skipped = [], []
    with _open_text(path) as fh:
        for lineno, line in _lines(fh, path, errors, skipped):
            tokens = line.split("#", 1)[0].split()
            if not tokens or tokens[0] not in messages:
                continue
            try:
                reading = _PARSERS[tokens[0]](tokens, lineno)
                if not (np.all(np.isfinite(reading.pose)) and np.isfinite(reading.timestamp)):
                    raise _MalformedLine("non-finite pose or timestamp")
                if np.any(reading.ranges < 0):
                    raise _MalformedLine("negative range reading")
            except _MalformedLine as exc:
                if errors == "raise":
                    raise ValueError(
                        f"{path}, line {lineno}: malformed {tokens[0]} message: {exc}. {SKIP_HINT}"
                    ) from None
                skipped.append((lineno, str(exc)))
                continue
            readings.append(reading)
    return readings, skipped


# A log's largest reading repeated this often is taken for its no-return sentinel (a
# returned range is read to a few mm: no wall returns exactly the farthest range 10 times).
_SENTINEL_REPEATS = 10


def _infer_flaser_max_range(readings, path):
    # CARMEN writes the sensor's maximum range for beams without a return, so the largest
    # reading of the log is the sentinel (81.83 m in the Intel log, 50 m in ACES). An
    # infinite reading is a beam without a return whatever the sentinel.
    finite = [r.ranges[np.isfinite(r.ranges)] for r in readings]
    largest = max((f.max() for f in finite if f.size), default=None)
    if largest is None or not largest > 0:
        if largest == 0:
            raise ValueError(
                f"{path}: every finite range reading is 0 (no measurement, dropped): the "
                "log holds no beam to map."
            )
        raise ValueError(
            f"{path}: no positive finite range reading to infer the maximum range from; "
            "pass max_range=."
        )
    if any(np.isinf(r.ranges).any() for r in readings):
        warnings.warn(
            f"{path}: the log writes inf for beams without a return, so the maximum range "
            f"is taken as its longest finite reading ({largest:g} m), which becomes a beam "
            "without a return too. Pass max_range= with the sensor's range.",
            UserWarning,
            stacklevel=caller_stacklevel(),
        )
    return float(largest)


def _warn_if_sentinel_below(ranges, max_range, path):
    """Warn when a FLASER log's largest reading, repeated as CARMEN's no-return sentinel,
    lies below ``max_range``: those beams would become hits at the sentinel's range."""
    finite = ranges[np.isfinite(ranges)]
    if finite.size == 0:
        return
    largest = finite.max()
    n = int(np.count_nonzero(finite == largest))
    # Readings of 0 are dropped as "no measurement", not read as hits.
    if 0 < largest < max_range and n >= _SENTINEL_REPEATS:
        warnings.warn(
            f"{path}: {n} readings equal {largest:g} m, the log's largest, as CARMEN writes "
            f"for beams without a return; with max_range={max_range:g} they are hits "
            f"{largest:g} m away. Pass max_range={largest:g}, or leave it out, to read them "
            "as beams without a return.",
            UserWarning,
            stacklevel=caller_stacklevel(),
        )


def load_carmen(path, *, max_range=None, message=None, errors="raise"):
    """Load the laser scans of a CARMEN log.

    Parameters
    ----------
    path : str or path-like
        The log, plain text or gzip-compressed (detected from the content, so ``.gz`` or not).
    max_range : float or None, default=None
        Readings at or above ``max_range`` are beams without a return (free space up to
        ``max_range``). ``None`` infers it: ``ROBOTLASER1`` lines state the sensor's maximum
        range (the smallest finite stated value is used; lines that all state ``inf`` need
        ``max_range``); for ``FLASER`` lines it is the largest
        finite reading in the log, because CARMEN writes the maximum range for beams that
        return nothing (an infinite reading is a beam without a return too). Pass it
        explicitly for a log in which no beam reaches the maximum range, otherwise its
        longest real reading becomes a no-return beam. A ``max_range`` above a ``FLASER``
        log's largest reading warns when that reading repeats 10 times or more: it is the
        log's sentinel, and its beams would become hits at the sentinel's range.
    message : {"FLASER", "ROBOTLASER1"} or None, default=None
        Which laser message to read. ``None`` reads ``ROBOTLASER1`` lines when the log has any
        (many logs store the same scans as both, and ``ROBOTLASER1`` carries its own geometry),
        else ``FLASER`` lines.
    errors : {"raise", "skip"}, default="raise"
        What to do with a malformed laser line: raise a ``ValueError`` naming the line number, or
        skip it and warn once with the count and the first line numbers.

    Returns
    -------
    scans : skoccmap.observations.Scans
        ``poses`` (n_scans, 3) laser poses ``[x, y, theta]``; ``ranges`` (n_scans, n_beams) with
        no-return beams set to ``inf``; ``angles`` (n_beams,) relative to the laser heading, or
        (n_scans, n_beams) when they differ between scans; ``max_range``; ``timestamps``
        (the ``ipc_timestamp`` field). Slice it for sparser training (``scans[::10]``) and turn it
        into observations with ``scans.to_observations()``.

    Raises
    ------
    ValueError
        If the file holds no laser message of the requested kind, a laser line is malformed
        (with ``errors="raise"``; a ``FLASER`` line must hold exactly its beam count of
        readings), or the scans have different beam counts.

    Examples
    --------
    >>> import tempfile, os
    >>> from skoccmap.datasets import load_carmen
    >>> line = "FLASER 4 1.0 2.0 80.0 1.5 0 0 0 0 0 0 12.5 host 12.5\\n"
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     path = os.path.join(tmp, "tiny.log")
    ...     with open(path, "w") as fh:
    ...         _ = fh.write("# a comment\\n" + line + line.replace("12.5", "13.0"))
    ...     scans = load_carmen(path)
    >>> len(scans), scans.ranges.shape, scans.max_range
    (2, (2, 4), 80.0)
    >>> scans.ranges[0]
    array([1. , 2. , inf, 1.5])
    """
    if errors not in ("raise", "skip"):
        raise ValueError(f"errors must be 'raise' or 'skip', got {errors!r}.")
    if message not in (None, "FLASER", "ROBOTLASER1"):
        raise ValueError(f"message must be None, 'FLASER' or 'ROBOTLASER1', got {message!r}.")
    if max_range is not None:
        from ..observations import _check_max_range

        max_range = _check_max_range(max_range)
    kinds = (message,) if message else tuple(_PARSERS)
    readings, skipped = _read_lines(path, kinds, errors)
    if skipped:
        shown = ", ".join(f"line {n} ({why})" for n, why in skipped[:5])
        more = f" and {len(skipped) - 5} more" if len(skipped) > 5 else ""
        warnings.warn(
            f"{path}: skipped {len(skipped)} malformed laser line(s): {shown}{more}.",
            UserWarning,
            stacklevel=caller_stacklevel(),
        )
    if message is None and any(r.message == "ROBOTLASER1" for r in readings):
        readings = [r for r in readings if r.message == "ROBOTLASER1"]
    if not readings:
        what = message or "FLASER or ROBOTLASER1"
        raise ValueError(f"{path} holds no valid {what} laser message.")
    return _to_scans(readings, max_range, path)


def _to_scans(readings, max_range, path):
    from ..observations import Scans

    counts = {r.ranges.size for r in readings}
    if len(counts) > 1:
        raise ValueError(
            f"{path}: laser scans have different beam counts {sorted(counts)}; "
            "select one laser with message='FLASER' or message='ROBOTLASER1'."
        )
    stated = [r.max_range for r in readings if np.isfinite(r.max_range)]
    robot = [r for r in readings if r.message == "ROBOTLASER1"]
    if max_range is None and robot and not stated:
        # The FLASER rule (the longest reading is the sentinel) would read a real return
        # as a beam without one, without a word.
        raise ValueError(
            f"{path}: the ROBOTLASER1 lines state an infinite maximum range (line "
            f"{robot[0].lineno} the first), which does not tell which readings are beams "
            "without a return; pass max_range= with the sensor's range."
        )
    ranges = np.vstack([r.ranges for r in readings])
    if max_range is None:
        max_range = min(stated) if stated else _infer_flaser_max_range(readings, path)
    elif not stated:
        _warn_if_sentinel_below(ranges, max_range, path)
    ranges[ranges >= max_range] = np.inf
    angles = np.vstack([r.angles for r in readings])
    if np.all(angles == angles[0]):
        angles = angles[0].copy()
    return Scans(
        poses=np.vstack([r.pose for r in readings]),
        ranges=ranges,
        angles=angles,
        max_range=float(max_range),
        timestamps=np.array([r.timestamp for r in readings]),
    )
