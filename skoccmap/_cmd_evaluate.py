"""``skoccmap evaluate``: held-out AUC of the mixture against the counting grid on a CARMEN log.

The Hilbert-map protocol: every ``--holdout-every``-th scan is held out; the models train on
every ``--every-nth-scan``-th of the remaining scans; positives are the held-out hit points,
negatives points drawn uniformly along the held-out beams short of the hit
(:func:`skoccmap.metrics.heldout_auc`).
"""

import sys

from ._cmd_map import Stopwatch, add_model_arguments, load_scans, make_mixture


def add_arguments(parser):
    parser.add_argument("log", metavar="LOG", help="CARMEN log (plain text or gzip)")
    add_model_arguments(parser)
    parser.add_argument(
        "--every-nth-scan",
        type=int,
        default=10,
        metavar="N",
        help="train on every N-th of the remaining scans (default 10)",
    )
    parser.add_argument(
        "--holdout-every",
        type=int,
        default=10,
        metavar="K",
        help="hold out every K-th scan for testing (default 10)",
    )
    parser.add_argument(
        "--grid-resolution",
        type=float,
        default=0.1,
        help="cell size of the counting-grid baseline in metres (default 0.1)",
    )
    parser.add_argument(
        "--free-per-beam",
        type=int,
        default=1,
        help="free test points drawn along each held-out beam (default 1)",
    )


def run(args):
    try:
        for name in ("every_nth_scan", "free_per_beam"):
            if getattr(args, name) < 1:
                raise ValueError(f"--{name.replace('_', '-')} must be >= 1")
        if args.holdout_every < 2:
            raise ValueError("--holdout-every must be >= 2")
        if not args.grid_resolution > 0:
            raise ValueError("--grid-resolution must be positive")
        return _run(args)
    except (ValueError, OSError) as exc:
        print(f"skoccmap evaluate: error: {exc}", file=sys.stderr)
        return 2


def _run(args):
    from .baselines import OccupancyGridMap
    from .metrics import heldout_auc, split_scans

    watch = Stopwatch()
    scans = watch("read log", load_scans, args)
    # Offset half a period so held-out scans sit between training scans.
    train, test = split_scans(scans, args.holdout_every, offset=args.holdout_every // 2)
    train = train[:: args.every_nth_scan]
    X, y, _ = train.to_observations()
    print(
        f"training on {len(train)} scans ({len(X)} observations), testing on {len(test)} "
        "held-out scans"
    )
    models = {
        "mixture of GP experts": make_mixture(args),
        f"counting grid ({args.grid_resolution:g} m)": OccupancyGridMap(
            resolution=args.grid_resolution
        ),
    }
    rows = []
    for name, model in models.items():
        watch(f"fit {name}", model.fit, X, y)
        fit_s = watch.rows[-1][1]
        auc = watch(
            f"score {name}",
            heldout_auc,
            model,
            test,
            n_free_per_beam=args.free_per_beam,
            random_state=args.seed,
        )
        rows.append((name, auc, fit_s, watch.rows[-1][1]))
    print()
    print("| model | held-out AUC | fit s | predict s |")
    print("|---|---|---|---|")
    for name, auc, fit_s, predict_s in rows:
        print(f"| {name} | {auc:.4f} | {fit_s:.1f} | {predict_s:.1f} |")
    print()
    print(watch.table())
    return 0
