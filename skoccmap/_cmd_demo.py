"""``skoccmap demo``: simulate the paper's laser scans, count them and draw them."""

from pathlib import Path


def add_arguments(parser):
    parser.add_argument(
        "--out", metavar="DIR", default=None, help="folder for the figure (created if missing)"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the range noise")
    parser.add_argument(
        "--noise-std", type=float, default=0.0, help="range noise in metres (default 0)"
    )


def run(args):
    from .datasets import make_paper_scans
    from .observations import HIT, NO_RETURN, RETURN

    data = make_paper_scans(noise_std=args.noise_std, random_state=args.seed)
    names = (("hits", HIT), ("return beams", RETURN), ("no-return beams", NO_RETURN))
    counts = {name: int((data.kind == code).sum()) for name, code in names}
    scans = data.scans
    print(
        f"Simulated {len(scans)} scans x {scans.n_beams} beams "
        f"(max range {scans.max_range:g} m) in a 22 m x 18 m environment."
    )
    print("| observations | count |\n|---|---|")
    for name, count in counts.items():
        print(f"| {name} | {count} |")
    print(f"| total | {len(data.X)} |")
    if args.out is None:
        print("Pass --out DIR to save a figure of the environment and the observations.")
        return 0
    try:
        from matplotlib.figure import Figure
    except ImportError:
        print('matplotlib is not installed: pip install "skoccmap[plot]" for figures.')
        return 0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "paper_observations.png"
    _draw(Figure(figsize=(8, 6.8)), data).savefig(path, dpi=120)
    print(f"Saved {path}")
    return 0


def _draw(fig, data):
    from matplotlib.collections import LineCollection

    from .observations import HIT, NO_RETURN, RETURN

    ax = fig.add_subplot()
    walls = data.environment.walls.reshape(-1, 2, 2)
    ax.add_collection(LineCollection(walls, colors="k", linewidths=2, label="walls"))
    beams = data.X.reshape(-1, 2, 2)
    for code, color, label in ((RETURN, "tab:green", "return beams"),
                               (NO_RETURN, "tab:blue", "no-return beams")):  # fmt: skip
        ax.add_collection(
            LineCollection(beams[data.kind == code], colors=color, linewidths=0.4, label=label)
        )
    hits = data.X[data.kind == HIT]
    ax.plot(hits[:, 0], hits[:, 1], ".", color="tab:red", ms=4, label="hits")
    poses = data.scans.poses
    ax.plot(poses[:, 0], poses[:, 1], "o", color="tab:purple", ms=3, label="poses")
    extent = data.environment.extent
    ax.set_xlim(extent[0] - 0.5, extent[1] + 0.5)
    ax.set_ylim(extent[2] - 0.5, extent[3] + 0.5)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title("Simulated laser observations (Kim & Kim, ACRA 2011 setup)")
    ax.legend(loc="upper left", fontsize="small")
    return fig
