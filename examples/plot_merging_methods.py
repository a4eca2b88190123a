"""
=====================================
Merging GP experts: MoE, PoE and BCMs
=====================================

Each expert of :class:`~skoccmap.MixtureGPOccupancyMap` predicts a latent Gaussian at a query
point; the ``combiner`` turns them into one occupancy probability (:mod:`skoccmap.combine`):

- ``"moe"``, mixture of experts (the paper): the gate-weighted average of the experts'
  probabilities;
- ``"poe"``, product of experts: the product of the experts' Gaussians;
- ``"gpoe"``, generalised PoE: each expert's precision scaled by its gating weight;
- ``"bcm"``, Bayesian committee machine: the product, corrected for the prior counted once
  per expert;
- ``"rbcm"``, robust BCM: each expert weighted by how much it learned (its information gain
  over the prior).

First the rules on two experts along a line, then the maps they give on the paper's data.
"""

# %%
# Two experts along a line
# ------------------------
# Expert A is confident "occupied" around x = -1 and knows nothing (prior variance 4) for
# x > 1; expert B is confident "free" around x = +1 and knows nothing for x < -1. The gate
# hands over from A to B across x = 0.
import matplotlib.pyplot as plt
import numpy as np
from scipy.special import expit

from skoccmap.combine import COMBINERS, combine

x = np.linspace(-3, 3, 301)
prior_var = 4.0
know_a, know_b = expit(-3 * (x - 1)), expit(3 * (x + 1))
means = np.column_stack([2.0 * know_a, -2.0 * know_b])
variances = np.column_stack(
    [prior_var - (prior_var - 0.2) * know_a, prior_var - (prior_var - 0.2) * know_b]
)
gate = expit(-2 * x)
weights = np.column_stack([gate, 1 - gate])

fig, ax = plt.subplots(figsize=(7, 4), layout="constrained")
for method in COMBINERS:
    prior = np.full(x.shape, prior_var)
    merged = combine(means, variances, weights, method=method, prior_variance=prior)
    ax.plot(x, merged.proba, label=method)
ax.set_xlabel("x")
ax.set_ylabel("P(occupied)")
ax.set_title("Merged probability of two experts")
ax.legend()

# %%
# The maps on the paper's simulation
# ----------------------------------
# One fit, merged five ways: ``combiner`` is read at prediction, so ``set_params`` on the
# fitted model changes the rule without refitting the clusters and experts. Each map is
# scored by the ROC AUC against the true map on the observed cells of a 0.2 m grid.
import time  # noqa: E402

from skoccmap import MixtureGPOccupancyMap, OccupancyGrid  # noqa: E402
from skoccmap.datasets import make_paper_scans  # noqa: E402
from skoccmap.metrics import ground_truth_auc  # noqa: E402
from skoccmap.plotting import OccupancyMapDisplay  # noqa: E402

data = make_paper_scans(random_state=0)
extent = data.environment.extent
start = time.perf_counter()
model = MixtureGPOccupancyMap(random_state=0).fit(data.X, data.y)
print(f"fit {time.perf_counter() - start:.1f} s, {model.n_experts_} experts")
fig, axes = plt.subplots(1, len(COMBINERS), figsize=(4 * len(COMBINERS), 3.8),
                         layout="constrained", sharey=True)  # fmt: skip
for ax, method in zip(axes, COMBINERS, strict=True):
    start = time.perf_counter()
    grid = OccupancyGrid.from_estimator(
        model.set_params(combiner=method), extent=extent, resolution=0.2
    )
    seconds = time.perf_counter() - start
    auc = ground_truth_auc(grid.probability.ravel(), data.environment, 0.2, scans=data.scans)
    print(f"{method:>5}: AUC {auc:.4f}, map {seconds:.1f} s")
    OccupancyMapDisplay.from_grid(grid, kind="probability", ax=ax, colorbar=False)
    ax.set_title(f"{method}: AUC {auc:.3f}")
