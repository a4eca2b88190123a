"""
===================================================
The paper's experiment: mixture of GPs vs single GP
===================================================

Kim & Kim (ICRA 2012) map a simulated 22 m x 18 m office from 26 laser scans of 17 beams
(about 700 observations) three ways: a **mixture of GP experts** (one GP classifier per
cluster of hit points, merged by the gating weights), a **Bayesian committee machine** over
the same experts, and a **single GP** on all observations. The local experts learn and
predict much faster than the single GP, and map the walls as well.

:func:`skoccmap.experiment.run_paper_experiment` runs the whole experiment and returns the
fitted maps with their timings and scores; ``skoccmap demo`` is the same on the command
line.
"""

# %%
# Run the experiment
# ------------------
# Every map is evaluated on a 0.2 m grid and scored by the ROC AUC against the simulator's
# true map, on the cells that some beam observed.
import matplotlib.pyplot as plt

from skoccmap.experiment import (
    format_tables,
    plot_clusters,
    plot_maps,
    plot_roc,
    run_paper_experiment,
)

result = run_paper_experiment(random_state=0)
print(format_tables(result))

# %%
# The clusters (the paper's Figure 2)
# -----------------------------------
# The Dirichlet-process mixture splits the hit points into clusters; every beam with a
# return joins the cluster of the hit nearest its end (its own, but for a few beams at
# corners, where a neighbouring hit is nearer), every beam without one the cluster of the
# return beam most similar to it under the integral kernel.
fig, ax = plt.subplots(figsize=(8, 6.8), layout="constrained")
plot_clusters(result, ax=ax)

# %%
# Maps and their uncertainty (the paper's Figure 4)
# -------------------------------------------------
# The std of P(occupied), from the latent variance, is small along the walls the robot saw
# and rises towards 0.5 far from all beams; cells whose latent variance is above 90 % of the
# prior's are drawn as unknown, on both panels.
fig = plt.figure(figsize=(11, 12.6), layout="constrained")
plot_maps(result, fig=fig)

# %%
# ROC curves against the true map (the paper's Figure 5)
# ------------------------------------------------------
fig, ax = plt.subplots(figsize=(5.5, 5), layout="constrained")
plot_roc(result, ax=ax)

# %%
# How much faster are the experts?
# --------------------------------
moe, single = result.methods["moe"], result.methods["single"]
speedup = (single.fit_s + single.predict_s) / (moe.fit_s + moe.predict_s)
print(f"mixture: {speedup:.1f}x faster than the single GP, AUC {moe.auc - single.auc:+.4f}")
