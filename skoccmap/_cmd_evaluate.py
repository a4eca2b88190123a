"""``skoccmap evaluate``: held-out AUC of the mixture against counting grids on a laser log.

The log is a CARMEN log or a ROS bag, read as ``skoccmap map`` reads it.

Two protocols choose the test scans and points (:mod:`skoccmap.metrics`):

- ``--protocol every-nth`` (default): every ``--holdout-every``-th scan is held out; negatives
  are ``--free-per-beam`` points drawn uniformly along each held-out beam short of the hit.
- ``--protocol blocks``: the Hilbert-maps protocol (:func:`skoccmap.metrics.blocks_protocol`):
  10 % of the scans held out as blocks of ``--block-size`` (40) consecutive scans at random
  starts; negatives floor(r / 2) points per held-out beam of range r <= 40 m, 0.1 m short of
  the hit.

The baselines are the counting grids of benchmark B4 (``benchmarks/README.md``): the
frequency grid of the Hilbert-maps protocol (hits / (hits + passes), unclamped) and the
log-odds grid updated scan by scan as OctoMap does (``scan_index``); the log-odds grid
with its evidence summed over all scans saturates and ranks held-out points worse (on the
Intel lab, all scans: 0.874 against 0.938 per scan).

Either way the positives are the held-out hits, the models train on every
``--train-every``-th of the remaining scans, and each of ``--seeds`` repeats the whole run,
printing the AUC per seed and their mean. A seed draws the held-out blocks (``blocks``), the
free test points and the mixture's clusters; ``every-nth`` holds out the same scans for
every seed.
"""

import sys
from functools import partial

import numpy as np

from ._cmd_map import (
    LOG_HELP,
    Stopwatch,
    add_model_arguments,
    check_hits,
    check_length,
    check_model_arguments,
    load_scans,
    make_mixture,
)

# Defaults of the options that only one protocol reads (None: the option was not given).
_EVERY_NTH_DEFAULTS = {"holdout_every": 10, "free_per_beam": 1}
_BLOCKS_DEFAULTS = {"block_size": 40}


def add_arguments(parser):
    parser.add_argument("log", metavar="LOG", help=LOG_HELP)
    add_model_arguments(parser)
    parser.add_argument(
        "--protocol",
        choices=["every-nth", "blocks"],
        default="every-nth",
        help="every-nth (default): hold out every K-th scan; blocks: the Hilbert-maps "
        "protocol, 10%% of the scans held out in blocks of consecutive scans",
    )
    parser.add_argument(
        "--train-every",
        "--every-nth-scan",
        dest="train_every",
        type=int,
        default=10,
        metavar="N",
        help="train on every N-th of the remaining scans (default 10)",
    )
    parser.add_argument(
        "--seeds",
        type=int,
        nargs="+",
        default=None,
        metavar="S",
        help="repeat the evaluation with each seed (held-out blocks of --protocol blocks, free "
        "test points, mixture) and report the mean AUC (default: --seed)",
    )
    parser.add_argument(
        "--grid-resolution",
        type=float,
        default=0.1,
        help="cell size of the counting-grid baselines in metres (default 0.1)",
    )
    every_nth = parser.add_argument_group("--protocol every-nth")
    every_nth.add_argument(
        "--holdout-every",
        type=int,
        default=None,
        metavar="K",
        help="hold out every K-th scan for testing (default 10)",
    )
    every_nth.add_argument(
        "--free-per-beam",
        type=int,
        default=None,
        help="free test points drawn along each held-out beam (default 1)",
    )
    blocks = parser.add_argument_group("--protocol blocks")
    blocks.add_argument(
        "--block-size",
        type=int,
        default=None,
        metavar="B",
        help="consecutive scans per held-out block (default 40; lower it only for short logs)",
    )


def _check_options(args):
    """Fill in the protocol's defaults; ValueError for options of the other protocol."""
    own, other = (
        (_EVERY_NTH_DEFAULTS, _BLOCKS_DEFAULTS)
        if args.protocol == "every-nth"
        else (_BLOCKS_DEFAULTS, _EVERY_NTH_DEFAULTS)
    )
    for name in other:
        if getattr(args, name) is not None:
            raise ValueError(
                f"--{name.replace('_', '-')} does not apply to --protocol {args.protocol}"
            )
    for name, default in own.items():
        if getattr(args, name) is None:
            setattr(args, name, default)
    least = {"train_every": 1, "free_per_beam": 1, "block_size": 1, "holdout_every": 2}
    for name, value in least.items():
        if getattr(args, name) is not None and getattr(args, name) < value:
            raise ValueError(f"--{name.replace('_', '-')} must be >= {value}")
    check_length("--grid-resolution", args.grid_resolution)
    option = "--seeds" if args.seeds is not None else "--seed"
    if args.seeds is None:
        args.seeds = [args.seed]
    if min(args.seeds) < 0:
        raise ValueError(f"{option} must be non-negative integers")
    if max(args.seeds) >= 2**32:
        raise ValueError(f"{option} must be below 2**32, got {max(args.seeds)}")
    if len(set(args.seeds)) < len(args.seeds):
        # A repeated seed repeats a run and would count twice in the mean.
        raise ValueError(f"--seeds must be distinct, got {' '.join(map(str, args.seeds))}")


def run(args):
    try:
        _check_options(args)
        check_model_arguments(args)
        return _run(args)
    except (ValueError, OSError) as exc:
        print(f"skoccmap evaluate: error: {exc}", file=sys.stderr)
        return 2


def _split(scans, args, seed):
    """Training scans, held-out scans and labelled test points of one seed."""
    from .metrics import blocks_protocol, heldout_points, split_scans

    # The library's messages name its arguments; the command's user knows the options.
    if args.protocol == "blocks" and len(scans) <= args.block_size:
        raise ValueError(
            f"--block-size {args.block_size} leaves no training scan of the log's "
            f"{len(scans)}: use a smaller --block-size"
        )
    if args.protocol != "blocks" and len(scans) <= args.holdout_every // 2:
        raise ValueError(
            f"--holdout-every {args.holdout_every} holds out no scan of the log's "
            f"{len(scans)}: use a smaller --holdout-every"
        )
    if args.protocol == "blocks":
        protocol = blocks_protocol(
            scans, train_every=args.train_every, block_size=args.block_size, random_state=seed
        )
        return protocol.train, protocol.test, protocol.points, protocol.labels
    # Offset half a period so held-out scans sit between training scans.
    train, test = split_scans(scans, args.holdout_every, offset=args.holdout_every // 2)
    try:
        points, labels = heldout_points(
            test, n_free_per_beam=args.free_per_beam, random_state=seed
        )
    except ValueError as exc:
        message = str(exc).replace("n_free_per_beam=", "--free-per-beam ")
        raise ValueError(message.replace("n_free_per_beam", "--free-per-beam")) from None
    return train[:: args.train_every], test, points, labels


def _protocol_line(args):
    """The test set's definition, so that a table of numbers says how they were made."""
    from .metrics import (
        _FREE_MARGIN,
        HILBERT_BLOCK_SIZE,
        HILBERT_FREE_MARGIN,
        HILBERT_HELDOUT_FRACTION,
        HILBERT_MAX_BEAM_RANGE,
    )

    if args.protocol == "blocks":
        own = args.block_size == HILBERT_BLOCK_SIZE
        blocks = "" if own else f" (the protocol's: {HILBERT_BLOCK_SIZE})"
        test = (
            f"{HILBERT_HELDOUT_FRACTION:.0%} of the scans held out in blocks of "
            f"{args.block_size} consecutive scans{blocks}, floor(r / 2) free points (at least "
            f"one) per held-out beam of range r <= {HILBERT_MAX_BEAM_RANGE:g} m, "
            f"{HILBERT_FREE_MARGIN:g} m short of the hit"
        )
    else:
        k = args.holdout_every
        test = (
            f"1 in {k} scans held out from scan {k // 2}, {args.free_per_beam} free "
            f"point(s) per held-out beam, {_FREE_MARGIN:g} m short of the hit"
        )
    return (
        f"protocol {args.protocol}: {test}; training on 1 in {args.train_every} of the "
        f"remaining scans, seeds {', '.join(map(str, args.seeds))}"
    )


def _models(args, seed):
    from .baselines import FrequencyGridMap, OccupancyGridMap

    cell = f"{args.grid_resolution:g} m"
    return {
        "mixture of GP experts": make_mixture(args).set_params(random_state=seed),
        f"frequency grid ({cell})": FrequencyGridMap(resolution=args.grid_resolution),
        f"log-odds grid per scan ({cell})": OccupancyGridMap(resolution=args.grid_resolution),
    }


def _fit_arguments(model, scan_index):
    """Keyword arguments of ``model.fit`` beyond ``X, y``: the log-odds grid's scans."""
    from .baselines import OccupancyGridMap

    return {"scan_index": scan_index} if isinstance(model, OccupancyGridMap) else {}


def _run(args):
    from .metrics import _auc, _check_both_classes, _positive_proba
    from .observations import as_segments

    watch = Stopwatch()
    scans = watch("read log", load_scans, args)
    check_hits(scans, args.log, "scans")
    print(_protocol_line(args))
    results = {}  # model name -> list of (auc, fit s, predict s), one per seed
    for seed in args.seeds:
        train, test, points, labels = _split(scans, args, seed)
        _check_both_classes(labels, "held-out point")
        X, y, _, scan_index = train.to_observations(return_scan_index=True)
        print(
            f"seed {seed}: training on {len(train)} scans ({len(X)} observations), testing on "
            f"{len(test)} held-out scans ({int(labels.sum())} hits, "
            f"{int((labels == 0).sum())} free points)"
        )
        queries = as_segments(points)
        for name, model in _models(args, seed).items():
            fit = partial(model.fit, **_fit_arguments(model, scan_index))
            watch(f"fit {name} (seed {seed})", fit, X, y)
            fit_s = watch.rows[-1][1]
            proba = watch(f"score {name} (seed {seed})", _positive_proba, model, queries)
            auc = _auc(labels, proba, "held-out point")
            results.setdefault(name, []).append((auc, fit_s, watch.rows[-1][1]))
    print()
    print(_table(results, args.seeds))
    print()
    print(watch.table())
    return 0


def _table(results, seeds):
    """Markdown table: the AUC per seed (and their mean when there are several), timings."""
    if len(seeds) == 1:
        columns = ["held-out AUC"]
    else:
        columns = [f"AUC seed {seed}" for seed in seeds] + ["mean AUC"]
    lines = [
        "| model | " + " | ".join(columns) + " | fit s | predict s |",
        "|---" * (len(columns) + 3) + "|",
    ]
    for name, rows in results.items():
        aucs, fit_s, predict_s = np.array(rows).T
        values = list(aucs) + ([aucs.mean()] if len(seeds) > 1 else [])
        cells = [f"{v:.4f}" for v in values] + [f"{fit_s.mean():.1f}", f"{predict_s.mean():.1f}"]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
