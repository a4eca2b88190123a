"""``skoccmap map``: fit the mixture of GP experts to a CARMEN log or ROS bag and write the map.

Writes, into ``--out``: ``<name>.pgm`` + ``<name>.yaml`` (ROS map_server, trinary),
``<name>.npz`` (probability, variance, unknown mask; :meth:`skoccmap.OccupancyGrid.load`) and,
when matplotlib is installed, ``<name>.png`` (probability and uncertainty panels).
"""

import argparse
import contextlib
import math
import re
import sys
import time
import warnings
from pathlib import Path

# The Intel log's map at 0.1 m (387 x 361 cells), and the size from which a map warns
# before its fit.
_INTEL_MAP_CELLS = 387 * 361
_LARGE_MAP_CELLS = 5_000_000

LOG_HELP = (
    "CARMEN log (plain text or gzip) or ROS bag: a path ending in .bag (ROS 1), .db3 or .mcap "
    "(ROS 2 storage), or a ROS 2 bag directory"
)


OUTPUT_HELP = (
    "Writes, into --out, files named after the log (its name without .log, .gz, .bag, ...): "
    "<name>.pgm + <name>.yaml, the map for ROS map_server (trinary: occupied black, free "
    "white, unknown grey 205; origin the lower-left corner); <name>.npz, the probability, "
    "variance and unknown mask (skoccmap.OccupancyGrid.load); and, with matplotlib, "
    "<name>.png, the probability and uncertainty panels (unknown cells light blue). Files "
    "of an earlier map of the same name are overwritten, with a warning."
)


def add_arguments(parser):
    parser.epilog = OUTPUT_HELP
    parser.add_argument("log", metavar="LOG", help=LOG_HELP)
    add_model_arguments(parser)
    parser.add_argument(
        "--every-nth-scan",
        type=int,
        default=1,
        metavar="N",
        help="train on every N-th scan only (default 1: all scans)",
    )
    parser.add_argument(
        "--resolution", type=float, default=0.1, help="map cell size in metres (default 0.1)"
    )
    parser.add_argument(
        "--out", metavar="DIR", default=None, help="output folder (default: ./<log name>_map)"
    )
    parser.add_argument(
        "--unknown-variance",
        default="auto",
        help="cells with a larger predictive variance are unknown; 'auto' (default): 90%% of "
        "the model's prior variance; 'none': no unknown cells",
    )
    online = parser.add_argument_group("online mapping")
    online.add_argument(
        "--online",
        action="store_true",
        help="replay the log in time order, adding --batch-scans scans at a time with "
        "partial_fit (only the experts they touch change); prints the update time and "
        "the experts touched per batch",
    )
    online.add_argument(
        "--batch-scans",
        type=int,
        default=None,
        metavar="N",
        help="scans (after --every-nth-scan) per online update (default 10)",
    )
    online.add_argument(
        "--refit-fraction",
        type=float,
        default=None,
        metavar="F",
        help="with --online: a touched expert takes its new rows without a refit until "
        "the rows added so reach F times the rows its last fit settled; 0 refits every "
        "touched expert (default: the estimator's refit_fraction, 0.5)",
    )
    online.add_argument(
        "--snapshots",
        metavar="DIR",
        default=None,
        help="with --online: write a map snapshot (.npz, and .png with matplotlib) into DIR "
        "every --snapshot-every batches and after the last",
    )
    online.add_argument(
        "--snapshot-every",
        type=int,
        default=None,
        metavar="K",
        help="batches between snapshots (default 10)",
    )
    parser.add_argument(
        "--keep-unobserved",
        action="store_true",
        help="draw the map's extrapolation into cells no training beam crossed (by default "
        "they are unknown, as on a counting grid)",
    )


# The ROS bag reader's options (load_rosbag's arguments) at their defaults. The parser's
# defaults are None, so that an option given with a CARMEN log (where it would be ignored)
# is seen even at its default value.
_BAG_DEFAULTS = {
    "scan_topic": "/scan",
    "pose_topic": None,
    "map_frame": "map",
    "base_frame": None,
    "laser_frame": None,
    "level_tolerance": 0.01,
    "nan_readings": "no_return",
    "tf_topics": ("/tf", "/tf_static"),
}


def add_model_arguments(parser):
    """Options shared by ``map`` and ``evaluate``: reading the log and the mixture."""
    parser.add_argument(
        "--skip-bad-lines",
        action="store_true",
        help="CARMEN logs: skip malformed laser lines with a warning that counts them (by "
        "default a malformed line is an error naming its line number)",
    )
    bag = parser.add_argument_group("ROS bags")
    bag.add_argument(
        "--scan-topic",
        action="append",
        default=None,
        help="topic of the sensor_msgs/LaserScan messages (default /scan); repeat it to map "
        "with several lasers (--scan-topic /front_scan --scan-topic /rear_scan)",
    )
    bag.add_argument(
        "--tf-topics",
        nargs=2,
        default=None,
        metavar=("DYNAMIC", "STATIC"),
        help="the transform topics (default /tf /tf_static; e.g. /robot1/tf "
        "/robot1/tf_static for a namespaced robot)",
    )
    bag.add_argument(
        "--pose-topic",
        default=None,
        help="nav_msgs/Odometry or geometry_msgs/PoseStamped topic giving the poses (default: "
        "the transforms from --map-frame to the laser on /tf and /tf_static)",
    )
    bag.add_argument(
        "--map-frame",
        default=None,
        help="frame of the poses read from /tf (default map; odom maps with odometry alone)",
    )
    bag.add_argument(
        "--base-frame",
        default=None,
        help="with --pose-topic: frame whose pose the topic gives (default: an Odometry "
        "message's child frame; the laser's own frame for the pose messages, which name none)",
    )
    bag.add_argument(
        "--laser-frame",
        default=None,
        help="frame of the scans (default: each scan's header frame; for bags whose scans "
        "name none, or the wrong one)",
    )
    bag.add_argument(
        "--level-tolerance",
        type=float,
        default=None,
        help="radians: scans whose plane lies within this angle of the map's horizontal plane "
        "(upright or upside down) are mapped in 2-D (default 0.01); a larger value projects a "
        "tilted laser's scans onto the plane, inf always does",
    )
    bag.add_argument(
        "--nan-readings",
        default=None,
        choices=["no_return", "invalid"],
        help="NaN readings are beams without a return (no_return, the default) or dropped "
        "(invalid: scans made from a depth camera, whose NaN are pixels without depth)",
    )
    parser.add_argument(
        "--max-range",
        type=float,
        default=None,
        help="readings at or above this are no-return beams (default: the log's sentinel)",
    )
    parser.add_argument(
        "--max-expert-size",
        type=int,
        default=400,
        help="largest number of observations per GP expert (default 400)",
    )
    parser.add_argument(
        "--combiner",
        default="rbcm",
        choices=["moe", "poe", "gpoe", "bcm", "rbcm"],
        help="rule merging the experts (default rbcm)",
    )
    parser.add_argument(
        "--max-beam-length",
        type=_length_or_none,
        default=1.0,
        help="beams are cut into pieces no longer than this, in metres ('none': no bound; "
        "with --beam-end-length, --max-pieces-per-cell and --hyperparameter-beam-length "
        "none too, beams stay whole, each free beam joining the expert of the hit nearest "
        "its midpoint when that lies within 2 m and has room, else its own hit's; default 1)",
    )
    parser.add_argument(
        "--hyperparameter-beam-length",
        type=_length_or_none,
        default=1.0,
        help="the shared kernel is learned on beams cut into pieces no longer than this, "
        "in metres, whatever --max-beam-length is ('none': on the experts' own pieces; "
        "default 1)",
    )
    parser.add_argument(
        "--beam-end-length",
        type=_length_or_none,
        default=0.35,
        help="pieces of a beam halve in length towards its hit down to this, in metres "
        "('none': equal pieces; default 0.35)",
    )
    parser.add_argument(
        "--max-pieces-per-cell",
        type=_count_or_none,
        default=4,
        help="near-duplicate free pieces (same 0.2 m cell, direction and length) kept "
        "('none': every piece; default 4)",
    )
    parser.add_argument(
        "--min-hit-frequency",
        type=_fraction_or_none,
        default=0.2,
        help="leave out the hits of 0.1 m cells hit at most 3 times that free beams cross so "
        "often that hits / (hits + passes) is below this: people walking by ('none': keep "
        "every hit; default 0.2)",
    )
    parser.add_argument(
        "--learn-all-hyperparameters",
        action="store_true",
        help="learn kernel hyperparameters per expert (slow) instead of once, shared",
    )
    parser.add_argument(
        "--n-jobs",
        type=int,
        default=-1,
        help="processes fitting experts, threads predicting them (default -1: all cores)",
    )
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument(
        "--quiet",
        action="store_true",
        help="no progress messages from the fit and the prediction (what was read, the "
        "timings and the files written are still printed)",
    )


def _or_none(convert, what, valid, bound):
    """An argparse type: 'none', or ``convert(text)`` that is ``valid`` (else ``bound``)."""

    def parse(text):
        if text.strip().lower() == "none":
            return None
        try:
            value = convert(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what} or 'none', got {text!r}") from None
        if not valid(value):
            raise argparse.ArgumentTypeError(f"expected {bound}, got {text!r}")
        return value

    return parse


# inf is no length: the mixture would refuse it, but only once the log has been read.
_length_or_none = _or_none(
    float, "a length in metres", lambda v: 0 < v < math.inf, "a positive finite length"
)
_count_or_none = _or_none(int, "a whole number", lambda v: v >= 1, "at least 1")
_fraction_or_none = _or_none(float, "a number", lambda v: 0 <= v <= 1, "between 0 and 1")


def make_mixture(args):
    from .mixture import MixtureGPOccupancyMap

    return MixtureGPOccupancyMap(
        combiner=args.combiner,
        max_expert_size=args.max_expert_size,
        max_beam_length=args.max_beam_length,
        hyperparameter_beam_length=args.hyperparameter_beam_length,
        beam_end_length=args.beam_end_length,
        max_pieces_per_cell=args.max_pieces_per_cell,
        min_hit_frequency=args.min_hit_frequency,
        share_hyperparameters=not args.learn_all_hyperparameters,
        n_jobs=args.n_jobs,
        random_state=args.seed,
        verbose=0 if args.quiet else 1,
    )


def load_scans(args):
    """Read the log or bag, printing what was read; ValueError on a bad input or option."""
    from .datasets._rosbag import is_rosbag

    if not Path(args.log).exists():
        # Before the reader options, whose advice would assume the path is a CARMEN log.
        raise FileNotFoundError(2, "No such file or directory", str(args.log))
    if Path(args.log).is_dir() and not is_rosbag(args.log):
        raise ValueError(
            f"{args.log} is a folder but not a ROS 2 bag (no metadata.yaml, .db3 or .mcap "
            "in it); pass a CARMEN log file or a bag"
        )
    bag = is_rosbag(args.log)
    _check_reader_options(args, bag)
    scans = _load_bag(args) if bag else _load_carmen(args)
    print(
        f"{args.log}: {len(scans)} scans x {scans.n_beams} beams, max range {scans.max_range:g} m"
    )
    return scans


def _check_reader_options(args, bag):
    """ValueError for a ROS bag option given with a CARMEN log, or the reverse."""
    if bag:
        given = ["--skip-bad-lines"] if getattr(args, "skip_bad_lines", False) else []
        kind, other = "CARMEN logs", "a ROS bag"
    else:
        given = [
            "--" + name.replace("_", "-")
            for name in _BAG_DEFAULTS
            if getattr(args, name, None) is not None
        ]
        kind, other = "ROS bags", "a CARMEN log"
    if given:
        verb = "applies" if len(given) == 1 else "apply"
        raise ValueError(f"{', '.join(given)} {verb} only to {kind}; {args.log} is {other}")


def _load_carmen(args):
    """``load_carmen`` with the command's option names in its errors and warnings."""
    from .datasets import load_carmen
    from .datasets._carmen import SKIP_HINT

    errors = "skip" if getattr(args, "skip_bad_lines", False) else "raise"
    try:
        with _warnings_as_the_commands(args, ["max_range"]):
            scans = load_carmen(args.log, max_range=args.max_range, errors=errors)
    except ValueError as exc:
        hint = "Pass --skip-bad-lines to skip malformed lines with a warning."
        message = _option_names(str(exc).replace(SKIP_HINT, hint), ["max_range"])
        raise ValueError(message) from None
    return scans


@contextlib.contextmanager
def _warnings_as_the_commands(args, names):
    """Print the warnings of a log reader as the command's own (``skoccmap map: warning:``),
    with the command's option names for the reader's arguments ``names``; also when the
    reader then fails."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", UserWarning)
        try:
            yield
        finally:
            command = getattr(args, "command", None) or "map"
            for warning in caught:
                message = _option_names(str(warning.message), names)
                print(f"skoccmap {command}: warning: {message}", file=sys.stderr)


def _option_names(message, names):
    """The library's hints name its arguments (``max_range=100``); the command's user knows
    the options (``--max-range 100``)."""
    for name in names:
        option = "--" + name.replace("_", "-")
        message = re.sub(rf"\b{name}=(?=[\s.,]|$)", option, message)
        message = re.sub(rf"\b{name}=", option + " ", message)
    return message


def _bag_option(args, name):
    """A ROS bag reader option as given, or its default."""
    value = getattr(args, name, None)
    if isinstance(value, list) and len(value) == 1:  # one --scan-topic
        value = value[0]
    return _BAG_DEFAULTS[name] if value is None else value


def _load_bag(args):
    """``load_rosbag`` with the command's option names in its errors and warnings."""
    from .datasets import load_rosbag

    names = [*_BAG_DEFAULTS, "max_range"]
    try:
        with _warnings_as_the_commands(args, names):
            options = {name: _bag_option(args, name) for name in _BAG_DEFAULTS}
            scans = load_rosbag(args.log, **options, max_range=args.max_range)
    except ImportError as exc:
        raise ValueError(str(exc)) from None  # reported like any bad input, without a trace
    except ValueError as exc:
        raise ValueError(_option_names(str(exc), names)) from None
    if scans.n_dims != 2:
        tolerance = _bag_option(args, "level_tolerance")
        raise ValueError(
            f"{args.log}: the laser is not level (3-D poses) within --level-tolerance "
            f"{tolerance:g} rad; skoccmap map draws 2-D maps. A larger --level-tolerance "
            "projects the scans onto the horizontal plane."
        )
    return scans


class Stopwatch:
    """Named wall-clock timings, printed as a table at the end."""

    def __init__(self):
        self.rows = []

    def __call__(self, name, func, *args, **kwargs):
        tic = time.perf_counter()
        result = func(*args, **kwargs)
        self.rows.append((name, time.perf_counter() - tic))
        return result

    def table(self):
        lines = ["| step | seconds |", "|---|---|"]
        lines += [f"| {name} | {seconds:.1f} |" for name, seconds in self.rows]
        total = sum(seconds for _, seconds in self.rows)
        return "\n".join(lines + [f"| total | {total:.1f} |"])


def _unknown_variance(text):
    if text.lower() == "none":
        return None
    if text == "auto":
        return "auto"
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"--unknown-variance must be auto, none or a number: {text!r}") from None
    if not value > 0:
        raise ValueError(f"--unknown-variance must be positive, got {value}")
    return value


def run(args):
    created = []
    try:
        if args.every_nth_scan < 1:
            raise ValueError(f"--every-nth-scan must be >= 1, got {args.every_nth_scan}")
        check_length("--resolution", args.resolution)
        _check_online_options(args)
        check_model_arguments(args)
        unknown_variance = _unknown_variance(args.unknown_variance)
        out = Path(args.out) if args.out else Path(f"{log_stem(args.log)}_map")
        _output_folder(out, "--out", created)
        if args.snapshots:
            _output_folder(Path(args.snapshots), "--snapshots", created)
        return _run(args, unknown_variance, out)
    except (ValueError, OSError) as exc:
        remove_empty(created)
        print(f"skoccmap map: error: {exc}", file=sys.stderr)
        return 2


def remove_empty(created):
    """Remove the folders of ``created`` (made for a run that failed) that it left empty,
    deepest first."""
    for folder in sorted(created, key=lambda f: len(f.parts), reverse=True):
        if folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()


# Defaults of the options only --online reads (None: the option was not given).
_ONLINE_DEFAULTS = {
    "batch_scans": 10,
    "refit_fraction": None,
    "snapshots": None,
    "snapshot_every": 10,
}


def _check_online_options(args):
    """Fill in --online's defaults; ValueError for its options without it, or out of range."""
    given = [
        f"--{name.replace('_', '-')}"
        for name in _ONLINE_DEFAULTS
        if getattr(args, name) is not None
    ]
    if not args.online:
        if given:
            verb = "applies" if len(given) == 1 else "apply"
            raise ValueError(f"{', '.join(given)} {verb} only with --online")
        return
    for name, default in _ONLINE_DEFAULTS.items():
        if getattr(args, name) is None:
            setattr(args, name, default)
    if args.batch_scans < 1:
        raise ValueError(f"--batch-scans must be >= 1, got {args.batch_scans}")
    if args.refit_fraction is not None and not args.refit_fraction >= 0:
        raise ValueError(f"--refit-fraction must be >= 0, got {args.refit_fraction}")
    if args.snapshot_every < 1:
        raise ValueError(f"--snapshot-every must be >= 1, got {args.snapshot_every}")


def check_hits(scans, log, what):
    """Refuse, in the log's terms, scans with fewer than the 2 hits a map needs."""
    n_hits = int(scans.returned().sum())
    if n_hits < 2:
        n_unread = int(scans.unread().sum())
        unread = f", {n_unread} read 0 (no measurement)" if n_unread else ""
        raise ValueError(
            f"{log}: {n_hits} beam(s) of the {len(scans)} {what} return a hit{unread} (the "
            f"others read at or beyond the maximum range, {scans.max_range:g} m); a map "
            "needs at least 2 hits. Check --max-range."
        )


def check_model_arguments(args):
    """The mixture's options a fit would refuse, refused before the log is read."""
    if args.max_expert_size < 2:
        raise ValueError(f"--max-expert-size must be >= 2, got {args.max_expert_size}")
    check_jobs_and_seed(args.n_jobs, getattr(args, "seed", 0))
    if args.max_range is not None:
        check_length("--max-range", args.max_range)
    tolerance = _bag_option(args, "level_tolerance")
    if not tolerance >= 0:
        raise ValueError(f"--level-tolerance must be >= 0 radians, got {tolerance}")


def check_length(option, value, *, zero=False):
    """A length option refused unless finite and positive (or at least 0 with ``zero``)."""
    if not (math.isfinite(value) and (value >= 0 if zero else value > 0)):
        what = "a finite length >= 0" if zero else "a positive finite length"
        raise ValueError(f"{option} must be {what}, got {value:g}")


def check_jobs_and_seed(n_jobs, seed):
    """--n-jobs and --seed as the estimators take them, refused in the options' names."""
    if n_jobs == 0:
        raise ValueError("--n-jobs must not be 0 (-1: all cores, 1: one)")
    if not 0 <= seed < 2**32:
        raise ValueError(f"--seed must be an integer in [0, 2**32), got {seed}")


# Suffixes the default output names drop: the log's name stays otherwise whole, so that
# intel.2024-06-01.log and intel.2024-06-02.log get maps of their own.
_LOG_SUFFIXES = (".gz", ".log", ".gfs", ".clf", ".txt", ".bag", ".db3", ".mcap")


def log_stem(log):
    """The log's file name without its known suffixes ("map" if nothing is left)."""
    name = Path(log).name
    for suffix in _LOG_SUFFIXES:
        if name.lower().endswith(suffix) and len(name) > len(suffix):
            name = name[: -len(suffix)]
    return name.strip(".") or "map"


def _output_folder(folder, option, created):
    """Create ``folder`` now, before any work that would be lost if it cannot be; a folder
    made here (and every parent made with it) is appended to ``created``."""
    if folder.is_dir():
        return
    if folder.exists():
        raise ValueError(f"{option} {folder} exists and is not a folder")
    missing = [f for f in (folder, *folder.parents) if not f.exists()]
    try:
        folder.mkdir(parents=True)
    except OSError as exc:
        raise ValueError(f"{option} {folder}: cannot create the folder ({exc.strerror})") from None
    created.extend(missing)


def _run(args, unknown_variance, out):
    import numpy as np

    from .grid import _grid_from_extent

    watch = Stopwatch()
    scans = watch("read log", load_scans, args)
    train = scans[:: args.every_nth_scan]
    hits = train.hit_points()
    if len(hits):
        # The map's size is known before the fit: refuse a grid too large now, not after,
        # and say a large one's size before its cost is paid.
        _announce_grid(_grid_from_extent(hits, args.resolution)[1], args.resolution)
    check_hits(train, args.log, "training scans")
    X, y, kind = watch("observations", train.to_observations)
    counts = np.bincount(kind, minlength=3)
    print(
        f"training on {len(train)} scans: {len(X)} observations ({counts[0]} hits, "
        f"{counts[1]} return beams, {counts[2]} no-return beams)"
    )
    if args.online:
        model = watch("online replay", _replay, args, train, unknown_variance)
    else:
        model = watch("fit mixture", make_mixture(args).fit, X, y)
    print(f"fitted {model.n_experts_} experts")
    grid = watch("predict grid", _grid, args, model, train, unknown_variance, not args.quiet)
    print(f"map: {grid.shape[1]} x {grid.shape[0]} cells at {grid.resolution:g} m")
    stem = out / log_stem(args.log)
    if _named(stem, ".yaml").exists():
        print(f"skoccmap map: warning: overwriting the map in {stem}.*", file=sys.stderr)
    written = watch("write map files", _write, grid, stem)
    print(watch.table())
    for path in written:
        print(f"wrote {path}")
    return 0


def _announce_grid(counts, resolution):
    counts = [int(c) for c in counts]
    cells = math.prod(counts)
    print(f"map grid: {' x '.join(map(str, counts))} cells at {resolution:g} m")
    if cells > _LARGE_MAP_CELLS:
        print(
            f"skoccmap map: warning: the map has {cells:,} cells to predict, "
            f"{cells / _INTEL_MAP_CELLS:.0f} times the Intel log's at 0.1 m: a reading far "
            "off the map stretches the extent taken from the hits (check --max-range), or "
            "a coarser --resolution may be what you want",
            file=sys.stderr,
        )


def _grid(args, model, train, unknown_variance, verbose):
    from .grid import OccupancyGrid

    # Cover the hit points: no-return beams reach far outside the building.
    return OccupancyGrid.from_estimator(
        model,
        train.hit_points(),
        args.resolution,
        unknown_variance=unknown_variance,
        observed_by=None if args.keep_unobserved else train,
        chunk_size=8192,  # small chunks: frequent progress, bounded memory
        verbose=1 if verbose else 0,
    )


def _replay(args, train, unknown_variance):
    """``partial_fit`` batch by batch in time order; a line per batch, optional snapshots."""
    import numpy as np

    # One line per batch: the mixture's own progress messages would bury them.
    model = make_mixture(args).set_params(verbose=0)
    if args.refit_fraction is not None:
        model.set_params(refit_fraction=args.refit_fraction)
    snapshots = Path(args.snapshots) if args.snapshots else None
    starts = range(0, len(train), args.batch_scans)
    held = ([], [])
    print("| batch | scans seen | observations | update s | experts touched | experts |")
    print("|---|---|---|---|---|---|")
    for b, first in enumerate(starts, 1):
        seen = train[: first + args.batch_scans]
        X, y, _ = train[first : first + args.batch_scans].to_observations()
        if len(X) == 0:  # every reading 0: nothing to learn
            continue
        if not hasattr(model, "n_experts_"):
            # The first update needs beams and two hits (to cluster): until then, batches
            # pile up.
            X, y = np.vstack([*held[0], X]), np.concatenate([*held[1], y])
            if y.sum() < 2 or y.min() == y.max():
                held = ([X], [y])
                continue
        tic = time.perf_counter()
        model.partial_fit(X, y, classes=[0, 1])
        seconds = time.perf_counter() - tic
        print(
            f"| {b} | {len(seen)} | {len(X)} | {seconds:.2f} | "
            f"{model.touched_experts_.size} | {model.n_experts_} |",
            flush=True,
        )
        if snapshots is not None and (b % args.snapshot_every == 0 or b == len(starts)):
            grid = _grid(args, model, seen, unknown_variance, False)
            stem = snapshots / f"batch_{b:05d}"
            grid.save(_named(stem, ".npz"))
            png = _save_png(grid, _named(stem, ".png"))
            print(f"wrote snapshot {stem}.npz" + ("" if png is None else f" and {png}"))
    if not hasattr(model, "n_experts_"):
        raise ValueError("the scans hold fewer than 2 hits or no beam: nothing to map")
    return model


def _named(stem, suffix):
    """``stem`` + ``suffix``, appended: with_suffix would cut a dotted log name."""
    return stem.with_name(stem.name + suffix)


def _write(grid, stem):
    written = list(grid.save_map_server(stem))
    grid.save(_named(stem, ".npz"))
    written.append(_named(stem, ".npz"))
    png = _save_png(grid, _named(stem, ".png"))
    return written if png is None else written + [png]


def _save_png(grid, path):
    try:
        from matplotlib.figure import Figure
    except ImportError:
        print('matplotlib is not installed: pip install "skoccmap[plot]" for the PNG.')
        return None
    from .plotting import OccupancyMapDisplay

    n_panels = 2 if grid.variance is not None else 1
    fig = Figure(figsize=(7 * n_panels, 6.5), layout="constrained")
    axes = fig.subplots(1, n_panels, squeeze=False)[0]
    OccupancyMapDisplay.from_grid(grid, ax=list(axes))
    fig.savefig(path, dpi=150)
    return path
