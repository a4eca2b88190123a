"""
========================================================
Clustering hit points: DP-GMM vs BayesianGaussianMixture
========================================================

The mixture of GP experts clusters the laser's hit points with a Dirichlet-process Gaussian
mixture, so that the number of experts follows from the data. :class:`~skoccmap.DPGMMClusterer`
samples the exact posterior of that model by collapsed Gibbs sampling with split-merge moves.
scikit-learn's :class:`~sklearn.mixture.BayesianGaussianMixture` fits the same model by
variational inference, truncated at ``n_components``; its default prior is not the paper's
(concentration ``1 / n_components`` instead of 1), so we also run it with the sampler's prior.
"""

# %%
# The hit points of the paper's simulation
# ----------------------------------------
import time

import matplotlib.pyplot as plt
import numpy as np
from sklearn.metrics import adjusted_rand_score
from sklearn.mixture import BayesianGaussianMixture

from skoccmap import DPGMMClusterer
from skoccmap.datasets import make_paper_scans

data = make_paper_scans(random_state=0)
hits = data.X[data.y == 1, :2]
print(f"{len(hits)} hit points")

# %%
# Three fits
# ----------
# The sampler's resolved prior (``mean_prior_``, ``covariance_prior_``, ...) is handed to
# BayesianGaussianMixture for the matched run; ``max_iter=1000`` because its stopping rule is
# an absolute tolerance on the lower bound.
start = time.perf_counter()
dp = DPGMMClusterer(alpha=1.0, random_state=0).fit(hits)
dp_s = time.perf_counter() - start

common = dict(
    n_components=20,
    weight_concentration_prior_type="dirichlet_process",
    max_iter=1000,
    random_state=0,
)
fits = {"DPGMMClusterer (collapsed Gibbs)": (dp.labels_, dp_s)}
for name, prior in [
    ("BayesianGaussianMixture, default prior", {}),
    (
        "BayesianGaussianMixture, the sampler's prior",
        dict(
            weight_concentration_prior=1.0,
            mean_prior=dp.mean_prior_,
            mean_precision_prior=dp.mean_precision_prior_,
            covariance_prior=dp.covariance_prior_,
            degrees_of_freedom_prior=dp.degrees_of_freedom_prior_,
        ),
    ),
]:
    start = time.perf_counter()
    bgm = BayesianGaussianMixture(**common, **prior).fit(hits)
    fits[name] = (bgm.predict(hits), time.perf_counter() - start)

for name, (labels, seconds) in fits.items():
    ari = adjusted_rand_score(dp.labels_, labels)
    print(
        f"{name}: {np.unique(labels).size} clusters used, {seconds:.2f} s, "
        f"agreement with the sampler (ARI) {ari:.2f}"
    )

# %%
# Held-out density
# ----------------
# Both give the log density of new points (``score``, the mean of ``score_samples``): each
# is fitted on half of the hits and scores the other half. The sampler's density is the
# posterior predictive given its partition, the chance of a new cluster included.
half = np.random.default_rng(0).permutation(len(hits)) < len(hits) // 2
halves = {"DPGMMClusterer": DPGMMClusterer(alpha=1.0, random_state=0).fit(hits[half])}
for name, prior in [
    ("default prior", {}),
    ("concentration 1", {"weight_concentration_prior": 1.0}),
]:
    halves[f"BayesianGaussianMixture, {name}"] = BayesianGaussianMixture(**common, **prior).fit(
        hits[half]
    )
for name, model in halves.items():
    print(f"{name}: held-out mean log density {model.score(hits[~half]):.3f}")

# %%
# The clusters
# ------------
# Walls are long, thin clusters; an expert per cluster sees the beams that ended on it.
fig, axes = plt.subplots(1, 3, figsize=(15, 4.6), layout="constrained", sharey=True)
walls = data.environment.walls.reshape(-1, 2, 2)
for ax, (name, (labels, _)) in zip(axes, fits.items(), strict=True):
    for wall in walls:
        ax.plot(wall[:, 0], wall[:, 1], "-", color="0.7", lw=1)
    ax.scatter(hits[:, 0], hits[:, 1], c=labels % 10, cmap="tab10", s=10, vmin=0, vmax=9)
    ax.set_title(f"{name}\n{np.unique(labels).size} clusters", fontsize="medium")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
axes[0].set_ylabel("y [m]")

# %%
# The sampler's trace
# -------------------
# The log joint ``log p(X, z)`` after each sweep; the fitted partition is the best sample
# seen after burn-in, its clusters then merged while the log joint rises (the line).
fig, ax = plt.subplots(figsize=(5.5, 3.5), layout="constrained")
ax.plot(np.arange(1, dp.n_iter_ + 1), dp.log_joint_, "o-", label="sample")
ax.axhline(dp.best_log_joint_, color="0.4", ls="--", label="fitted partition")
ax.legend(loc="best")
ax.set_xlabel("sweep")
ax.set_ylabel("log joint")
ax.set_title(f"DPGMMClusterer: {dp.n_iter_} sweeps")
