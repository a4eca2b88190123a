"""Tuning: the spread of the learned shared length scale over random states.

Run standalone::

    python benchmarks/bench_length_scale.py --n-jobs 2
    python benchmarks/bench_length_scale.py --pieces 32 64 --caps none 4 --states 0 1 2 3
    python benchmarks/bench_length_scale.py --pieces 64 --every 10 --max-beam-lengths 1 2

For every combination of the number of experts whose summed evidence learns the shared
hyperparameters (``--pieces``, the estimator's ``_SHARED_PIECES``), of
``max_pieces_per_cell`` (``--caps``), of ``max_beam_length`` and
``hyperparameter_beam_length`` alike (``--max-beam-lengths``: the cut learned on,
default 1 m) and of the training sparsity (``--every``: ACES on the
Hilbert-maps protocol, seed 100, trained on every scan and on every 10th remaining scan),
:class:`skoccmap.MixtureGPOccupancyMap` is fitted up to the learned kernel (clustering,
beam pieces, learning; the experts are not fitted) with each ``--states`` random state.
Prints the learned length scales with their mean, the largest over the smallest, the
standard deviation of their logarithm (about their relative spread) and the learning's
seconds, and writes ``benchmarks/results/bench_length_scale.json``.

**Tuning data only** (ACES, as ``bench_tuning.py`` loads it): the numbers quoted for
``share_hyperparameters`` in the docstring of :class:`skoccmap.MixtureGPOccupancyMap` come
from this script.
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from itertools import product  # noqa: E402

import numpy as np  # noqa: E402
from bench_tuning import RESULTS, SEED, load_aces  # noqa: E402

import skoccmap.mixture as mixture  # noqa: E402


class _Learned(Exception):
    """Raised once the shared kernel is learned: the experts are not needed."""


class _LearnOnly(mixture.MixtureGPOccupancyMap):
    def _fit_experts(self, X, y, labels, expert, rng):
        rows = mixture._groups(labels, self.expert_cluster_.size)
        start = time.perf_counter()
        self._learn_shared(rows, expert, rng)
        # Carried by the exception: a fit that raises leaves the model unfitted.
        raise _Learned(time.perf_counter() - start, self.shared_kernel_)


def learned_length_scale(data, *, pieces, cap, beam, state, n_jobs):
    """Length scale (m) learned on ``data`` and the learning's seconds."""
    saved, mixture._SHARED_PIECES = mixture._SHARED_PIECES, pieces
    model = _LearnOnly(
        max_pieces_per_cell=cap,
        max_beam_length=beam,
        hyperparameter_beam_length=beam,
        random_state=state,
        n_jobs=n_jobs,
    )
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model.fit(data.X, data.y)
    except _Learned as done:
        seconds, kernel = done.args
    else:  # pragma: no cover - the learner always runs with the default expert
        raise RuntimeError("the shared kernel was not learned")
    finally:
        mixture._SHARED_PIECES = saved
    return float(kernel.k2.length_scale), seconds


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pieces", type=int, nargs="+", default=[32, 64])
    parser.add_argument("--caps", nargs="+", default=["none", "4"])
    parser.add_argument("--every", type=int, nargs="+", default=[1, 10])
    parser.add_argument("--max-beam-lengths", type=float, nargs="+", default=[1.0])
    parser.add_argument("--states", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--n-jobs", type=int, default=2)
    return parser.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    caps = [None if c.lower() == "none" else int(c) for c in args.caps]
    rows = []
    print("| experts learned on | max_pieces_per_cell | max_beam_length | training scans "
          "| length scales (m) | mean | max / min | sd of log % | learning s |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    for every in args.every:
        data = load_aces(SEED, every=every)
        if data is None:
            print("ACES log absent: nothing to measure")
            return
        for pieces, cap, beam in product(args.pieces, caps, args.max_beam_lengths):
            runs = [
                learned_length_scale(
                    data, pieces=pieces, cap=cap, beam=beam, state=s, n_jobs=args.n_jobs
                )
                for s in args.states
            ]
            scales = np.array([r[0] for r in runs])
            row = dict(
                pieces=pieces,
                cap=cap,
                max_beam_length=beam,
                every=every,
                states=args.states,
                length_scales=scales.tolist(),
                learn_s=[r[1] for r in runs],
            )
            rows.append(row)
            print(
                f"| {pieces} | {cap} | {beam:g} | every {every} | "
                + " / ".join(f"{v:.2f}" for v in scales)
                + f" | {scales.mean():.2f} | {scales.max() / scales.min():.2f} | "
                + f"{100 * np.std(np.log(scales), ddof=1) if len(scales) > 1 else np.nan:.1f} | "
                + f"{np.mean(row['learn_s']):.1f} |",
                flush=True,
            )
    RESULTS.mkdir(exist_ok=True)
    out = RESULTS / "bench_length_scale.json"
    out.write_text(json.dumps(dict(seed=SEED, rows=rows), indent=1))
    print(f"JSON in {out}")


if __name__ == "__main__":
    main()
