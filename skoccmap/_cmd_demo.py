"""``skoccmap demo``: the simulation experiment of Kim & Kim (ICRA 2012) in one command.

Fits the mixture of GP experts, the Bayesian committee machine and the single GP to the
paper's simulated scans, prints Table 1 (observations per cluster), Table 2 (learning and
inference times) and the AUC of each map against the true map, and writes into ``--out``
Figure 2 (clustered data), Figure 4 (maps and uncertainty), Figure 5 (ROC curves) as PNG
(with matplotlib) and every map as a ROS map_server PGM + YAML pair.
"""

import sys

_DEFAULT_OUT = "skoccmap_demo"


def add_arguments(parser):
    parser.add_argument(
        "--out",
        metavar="DIR",
        default=_DEFAULT_OUT,
        help=f"folder for figures and maps, created if missing (default ./{_DEFAULT_OUT})",
    )
    parser.add_argument(
        "--methods",
        default="moe,bcm,single",
        help="comma-separated maps to fit among moe, bcm, single (default: all three)",
    )
    parser.add_argument(
        "--resolution", type=float, default=0.2, help="map cell size in metres (default 0.2)"
    )
    parser.add_argument(
        "--noise-std", type=float, default=0.0, help="range noise in metres (default 0)"
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="the single GP reuses the mixture's learned kernel instead of learning its own "
        "(a smoke run; its learning time then excludes hyperparameter learning)",
    )
    parser.add_argument(
        "--n-jobs", type=int, default=1, help="parallel expert fits (default 1; -1: all cores)"
    )
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--quiet", action="store_true", help="no progress messages")


def _check_options(args, methods):
    """The options the experiment would refuse in its own words, refused in theirs."""
    from ._cmd_map import check_jobs_and_seed, check_length
    from .experiment import METHODS, _check_methods

    try:
        _check_methods(methods)
    except ValueError:
        raise ValueError(
            f"--methods must name distinct maps among {', '.join(METHODS)}, got {args.methods!r}"
        ) from None
    check_length("--resolution", args.resolution)
    check_length("--noise-std", args.noise_std, zero=True)
    check_jobs_and_seed(args.n_jobs, args.seed)


def run(args):
    from pathlib import Path

    from ._cmd_map import _option_names, _output_folder, remove_empty
    from .experiment import format_tables, run_paper_experiment, save_figures, save_maps

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    created = []
    try:
        _check_options(args, methods)
        # Before the fits: a folder that cannot be made would fail only after them.
        _output_folder(Path(args.out), "--out", created)
        result = run_paper_experiment(
            methods,
            resolution=args.resolution,
            noise_std=args.noise_std,
            single_hyperparameters="from_mixture" if args.quick else "learn",
            random_state=args.seed,
            n_jobs=args.n_jobs,
            verbose=0 if args.quiet else 1,
        )
    except (ValueError, OSError) as exc:
        remove_empty(created)
        message = _option_names(str(exc), ["noise_std"])
        print(f"skoccmap demo: error: {message}", file=sys.stderr)
        return 2
    print()
    print(format_tables(result))
    if args.quick and "single" in result.methods:
        print("(--quick: the single GP used the mixture's kernel; no hyperparameter learning)")
    print()
    for path in save_maps(result, args.out):
        print(f"Saved {path} and {path.with_suffix('.pgm').name} (ROS map_server)")
    try:
        paths = save_figures(result, args.out)
    except ImportError:
        print('matplotlib is not installed: pip install "skoccmap[plot]" for Figures 2, 4, 5.')
        return 0
    for path in paths:
        print(f"Saved {path}")
    return 0
