"""EPGaussianProcessClassifier vs scikit-learn's GaussianProcessClassifier (Laplace), same run.

Workloads, on one core, on a 2-D synthetic problem with label noise:

- ``fixed``: one fit with fixed hyperparameters (``optimizer=None``), C(4) * RBF(1).
- ``learn``: a full fit with hyperparameter learning by L-BFGS-B from C(1) * RBF(1), bounds
  (1e-3, 1e3) for both estimators (no restarts).

Prints a markdown table and writes ``benchmarks/results/bench_ep.json``. Run::

    python benchmarks/bench_ep.py            # n = 1000 and 2000
    python benchmarks/bench_ep.py --sizes 1000 --repeat 5
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from sklearn.base import clone  # noqa: E402
from sklearn.gaussian_process import GaussianProcessClassifier  # noqa: E402
from sklearn.gaussian_process.kernels import RBF  # noqa: E402
from sklearn.gaussian_process.kernels import ConstantKernel as C  # noqa: E402
from sklearn.metrics import roc_auc_score  # noqa: E402

from skoccmap.classifier import EPGaussianProcessClassifier  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "bench_ep.json"


def make_data(n, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-3, 3, size=(n, 2))
    latent = np.sin(1.5 * X[:, 0]) + np.cos(X[:, 1])
    y = (latent + 0.3 * rng.standard_normal(n) > 0).astype(int)
    return X, y


def timed_fit(estimator, X, y, repeat):
    times = []
    for _ in range(repeat):
        model = clone(estimator)
        start = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model.fit(X, y)
        times.append(time.perf_counter() - start)
    return min(times), model


def run(sizes, repeat):
    rows = []
    X_test, y_test = make_data(2000, seed=123)
    for n in sizes:
        X, y = make_data(n)
        fixed = C(4.0) * RBF(1.0)
        learn = C(1.0, (1e-3, 1e3)) * RBF(1.0, (1e-3, 1e3))
        cases = [
            (
                "fixed",
                EPGaussianProcessClassifier(fixed, optimizer=None),
                GaussianProcessClassifier(fixed, optimizer=None),
                repeat,
            ),
            ("learn", EPGaussianProcessClassifier(learn), GaussianProcessClassifier(learn), 1),
        ]
        for workload, ours, theirs, rep in cases:
            t_ours, m_ours = timed_fit(ours, X, y, rep)
            t_sk, m_sk = timed_fit(theirs, X, y, rep)
            row = {
                "workload": workload,
                "n": n,
                "ep_fit_s": t_ours,
                "sklearn_fit_s": t_sk,
                "ratio_ep_over_sklearn": t_ours / t_sk,
                "ep_n_iter": int(m_ours.n_iter_),
                "ep_kernel": str(m_ours.kernel_),
                "sklearn_kernel": str(m_sk.kernel_),
                "ep_auc": roc_auc_score(y_test, m_ours.predict_proba(X_test)[:, 1]),
                "sklearn_auc": roc_auc_score(y_test, m_sk.predict_proba(X_test)[:, 1]),
                "ep_log_marginal_likelihood": m_ours.log_marginal_likelihood_value_,
            }
            rows.append(row)
            print_row(row)
    return rows


def print_row(row):
    print(
        f"| {row['workload']} | {row['n']} | {row['ep_fit_s']:.2f} | {row['sklearn_fit_s']:.2f} "
        f"| {row['ratio_ep_over_sklearn']:.2f} | {row['ep_n_iter']} | {row['ep_auc']:.3f} "
        f"| {row['sklearn_auc']:.3f} | {row['ep_kernel']} | {row['sklearn_kernel']} |",
        flush=True,
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 2000])
    parser.add_argument("--repeat", type=int, default=3, help="repeats of the fixed fits (min)")
    args = parser.parse_args()
    print(
        "| workload | n | EP fit s | sklearn fit s | EP / sklearn | EP sweeps | EP AUC "
        "| sklearn AUC | EP kernel | sklearn kernel |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    rows = run(args.sizes, args.repeat)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    meta = {
        "machine": platform.platform(),
        "cpu_count": os.cpu_count(),
        "load_average": os.getloadavg() if hasattr(os, "getloadavg") else None,
        "threads": 1,
    }
    RESULTS.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    print(f"\nwritten {RESULTS}")


if __name__ == "__main__":
    main()
