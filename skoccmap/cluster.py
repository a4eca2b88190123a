"""Dirichlet-process Gaussian mixture clustering by collapsed Gibbs sampling with split-merge."""

import math
import warnings
from numbers import Integral, Real

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.special import gammaln, logsumexp
from sklearn.base import BaseEstimator, ClusterMixin, _fit_context
from sklearn.exceptions import ConvergenceWarning
from sklearn.utils import check_random_state
from sklearn.utils._param_validation import Interval, StrOptions
from sklearn.utils.validation import check_is_fitted, validate_data

from ._niw import (
    NIWPrior,
    StudentT,
    _log_marginal_from_posterior,
    leave_one_out_log_student_t,
    log_crp,
    log_marginal_likelihood,
    log_student_t,
    mahalanobis_sq,
    posterior,
    predictive,
    prior_predictive,
)
from ._validation import caller_stacklevel, check_magnitude, fit_or_unfitted

__all__ = ["DPGMMClusterer"]

# Rows of X evaluated at once in predict_proba: bounds the (rows, K, D) temporaries.
_CHUNK = 8192


def sufficient_statistics(X, labels, n_clusters):
    """Per-cluster count, sum and sum of outer products, from scratch.

    Parameters
    ----------
    X : ndarray of shape (n_samples, D)
    labels : ndarray of shape (n_samples,), int in ``[0, n_clusters)``
    n_clusters : int

    Returns
    -------
    n : ndarray of shape (n_clusters,)
    s : ndarray of shape (n_clusters, D)
    S : ndarray of shape (n_clusters, D, D)
    """
    D = X.shape[1]
    n = np.bincount(labels, minlength=n_clusters).astype(float)
    s = np.empty((n_clusters, D))
    S = np.empty((n_clusters, D, D))
    for d in range(D):
        s[:, d] = np.bincount(labels, weights=X[:, d], minlength=n_clusters)
        for e in range(d, D):
            S[:, d, e] = S[:, e, d] = np.bincount(
                labels, weights=X[:, d] * X[:, e], minlength=n_clusters
            )
    return n, s, S


def log_joint(n, s, S, prior, alpha):
    """Log joint ``log p(X, z)`` of the partition with the given cluster statistics.

    CRP prior on the partition times the product of the clusters' marginal likelihoods.
    """
    return log_crp(n, alpha) + log_marginal_likelihood(n, s, S, prior).sum()


def greedy_merge(n, s, S, prior, alpha):
    """Merge cluster pairs greedily while the log joint increases.

    Not a Markov move: it removes the surplus clusters of an over-split start, which
    single-site Gibbs would take many sweeps to empty, and polishes the final state.

    Returns
    -------
    mapping : ndarray of shape (n_clusters,)
        New label of each input cluster, in ``0..K'-1``.
    """
    K = len(n)
    group = np.arange(K)
    n, s, S = n.copy(), s.copy(), S.copy()
    alive = list(range(K))
    log_alpha = math.log(alpha)
    while len(alive) > 1:
        idx = np.array(alive)
        a, b = np.triu_indices(len(idx), 1)
        a, b = idx[a], idx[b]
        own = np.zeros(K)
        own[idx] = log_marginal_likelihood(n[idx], s[idx], S[idx], prior) + gammaln(n[idx])
        nm = n[a] + n[b]
        merged = log_marginal_likelihood(nm, s[a] + s[b], S[a] + S[b], prior) + gammaln(nm)
        gain = merged - log_alpha - own[a] - own[b]
        best = int(np.argmax(gain))
        if gain[best] <= 0.0:
            break
        i, j = int(a[best]), int(b[best])
        n[i] += n[j]
        s[i] += s[j]
        S[i] += S[j]
        group[group == j] = i
        alive.remove(j)
    _, mapping = np.unique(group, return_inverse=True)
    return mapping


def greedy_split(X, labels, prior, alpha, max_rounds=50):
    """Bisect clusters greedily while the log joint increases (initialisation only).

    Each cluster is tried once per round with the split-merge launch split anchored at its
    point farthest from its mean and the point farthest from that one.
    """
    labels = labels.copy()
    for _ in range(max_rounds):
        grew = False
        for k in range(int(labels.max()) + 1):
            members = np.flatnonzero(labels == k)
            if len(members) < 4:
                continue
            XS = X[members]
            far = int(np.argmax(((XS - XS.mean(0)) ** 2).sum(1)))
            other = int(np.argmax(((XS - XS[far]) ** 2).sum(1)))
            if other == far:
                continue
            log_left, log_right = _launch(XS, far, other, prior)
            right = log_right > log_left
            right[far], right[other] = False, True
            if _split_gain(XS, right, prior, alpha) > 0:
                labels[members[right]] = labels.max() + 1
                grew = True
        if not grew:
            break
    return labels


class _CollapsedGibbs:
    """State of the collapsed Gibbs sampler: labels and cached per-cluster posteriors.

    For each cluster the sufficient statistics ``(n, s, S)`` are kept and updated by one
    rank-one term when a point moves; the Student-t predictive (location, inverse Cholesky
    factor of ``Psi_n``, constants) is recomputed from them for the two clusters a move touches,
    never from the points.
    """

    def __init__(self, X, labels, prior, alpha, statistics=None):
        self.X = X
        self.D = X.shape[1]
        self.prior = prior
        self.alpha = alpha
        self.labels = labels.astype(np.intp)
        self.K = int(labels.max()) + 1 if statistics is None else len(statistics[0])
        cap = max(2 * self.K, 8)
        D = self.D
        self.n = np.zeros(cap)
        self.s = np.zeros((cap, D))
        self.S = np.zeros((cap, D, D))
        self.loc = np.zeros((cap, D))
        self.chol_inv = np.zeros((cap, D, D))
        self.scale = np.zeros(cap)
        self.dof = np.zeros(cap)
        self.const = np.zeros(cap)
        self.logdet = np.zeros(cap)
        self.prior_t = prior_predictive(prior)
        if statistics is None:
            self.recompute()
        else:
            # Points outside X (a previous fit's) are held fixed in these statistics; the
            # points of X are not in them yet and are seated one at a time by ``seat``.
            K = self.K
            self.n[:K], self.s[:K], self.S[:K] = (np.array(a, dtype=float) for a in statistics)
            self.refresh(np.arange(K))

    # -- cluster bookkeeping -------------------------------------------------------------
    def recompute(self):
        """Statistics of all clusters from the labels (clears accumulated rounding)."""
        K = self.K
        self.n[:K], self.s[:K], self.S[:K] = sufficient_statistics(self.X, self.labels, K)
        self.refresh(np.arange(K))

    def refresh(self, ks):
        t, logdet = predictive(self.n[ks], self.s[ks], self.S[ks], self.prior)
        self.loc[ks] = t.loc
        self.chol_inv[ks] = t.chol_inv
        self.scale[ks] = t.scale
        self.dof[ks] = t.dof
        self.const[ks] = t.const
        self.logdet[ks] = logdet

    def _grow(self):
        for name in ("n", "s", "S", "loc", "chol_inv", "scale", "dof", "const", "logdet"):
            arr = getattr(self, name)
            setattr(self, name, np.concatenate([arr, np.zeros_like(arr)]))

    def _new_cluster(self):
        if self.K == len(self.n):
            self._grow()
        k = self.K
        self.n[k] = 0.0
        self.s[k] = 0.0
        self.S[k] = 0.0
        self.K += 1
        return k

    def _delete(self, k):
        """Remove empty cluster ``k`` by moving the last cluster into its slot."""
        last = self.K - 1
        if k != last:
            for name in ("n", "s", "S", "loc", "chol_inv", "scale", "dof", "const", "logdet"):
                arr = getattr(self, name)
                arr[k] = arr[last]
            self.labels[self.labels == last] = k
        self.K -= 1

    def log_joint(self):
        K = self.K
        n = self.n[:K]
        prior = self.prior
        lml = _log_marginal_from_posterior(
            n, prior.kappa + n, prior.nu + n, self.logdet[:K], prior
        )
        return log_crp(n, self.alpha) + lml.sum()

    # -- Neal (2000), Algorithm 3 ----------------------------------------------------------
    def conditional_draws(self, idx, uniforms):
        """Draws from the Gibbs conditionals of points ``idx``, each given all other points.

        p(z_i = k | z_-i, X) is proportional to n_k,-i t_k,-i(x_i) for existing clusters and to
        alpha t_0(x_i) for a new one (index K). All the densities come from the cached
        predictives in one vectorised step; the own cluster needs the leave-one-out predictive,
        which follows from the cached one in closed form. Each draw is exact for the current
        state, i.e. as long as no other point has moved.
        """
        K = self.K
        Xb = self.X[idx]
        own = self.labels[idx]
        t = self.cached_t()
        r = mahalanobis_sq(Xb, t)
        n = self.n[:K]
        lp = np.empty((len(idx), K + 1))
        lp[:, :K] = log_student_t(Xb, t, r) + np.log(n)
        rows = np.arange(len(idx))
        n_own = n[own]
        with np.errstate(divide="ignore"):
            loo = leave_one_out_log_student_t(
                r[rows, own], n_own, self.logdet[own], self.dof[own], self.prior
            ) + np.log(n_own - 1.0)
        # A singleton's own cluster disappears without it: staying is the "new cluster" option.
        lp[rows, own] = np.where(n_own > 1, loo, -np.inf)
        lp[:, K] = log_student_t(Xb, self.prior_t)[:, 0] + math.log(self.alpha)
        cum = np.cumsum(np.exp(lp - lp.max(1, keepdims=True)), axis=1)
        draws = (cum < uniforms[:, None] * cum[:, -1:]).sum(1)
        stays = (draws == own) | ((draws == K) & (n_own == 1))
        return draws, stays

    def seat(self, i, uniform):
        """Add point ``i`` (not yet in the statistics) to a cluster drawn from its conditional.

        p(z_i = k | z, X) is proportional to n_k t_k(x_i) for existing clusters and to
        alpha t_0(x_i) for a new one: the Chinese restaurant's seating of a new customer.
        """
        K = self.K
        x = self.X[i : i + 1]
        lp = np.empty(K + 1)
        with np.errstate(divide="ignore"):
            lp[:K] = log_student_t(x, self.cached_t())[0] + np.log(self.n[:K])
        lp[K] = log_student_t(x, self.prior_t)[0, 0] + math.log(self.alpha)
        cum = np.cumsum(np.exp(lp - lp.max()))
        k = int((cum < uniform * cum[-1]).sum())
        if k == K:
            k = self._new_cluster()
        self.n[k] += 1.0
        self.s[k] += x[0]
        self.S[k] += np.outer(x[0], x[0])
        self.labels[i] = k
        self.refresh(np.array([k]))

    def gibbs_sweep(self, rng):
        """One random-scan sweep of exact collapsed Gibbs sampling (Neal 2000, Algorithm 3).

        Points are visited one at a time in random order, but their conditionals are drawn in
        blocks: the draws of a block stay exact up to its first point that moves, so that point
        is moved (a rank-one update of two clusters' statistics) and the next block starts right
        after it. Near convergence few points move and a sweep costs a few vectorised passes.
        """
        n_samples = self.X.shape[0]
        order = rng.permutation(n_samples)
        uniforms = rng.random(n_samples)
        pos, block, n_moves = 0, 64, 0
        while pos < n_samples:
            idx = order[pos : pos + block]
            draws, stays = self.conditional_draws(idx, uniforms[pos : pos + block])
            moved = np.flatnonzero(~stays)
            if moved.size == 0:
                pos += len(idx)
                block = min(2 * block, 8192)
                continue
            first = moved[0]
            i = idx[first]
            self.move(i, self.labels[i], draws[first])
            n_moves += 1
            pos += first + 1
            block = max(16, 2 * (first + 1))
        return n_moves

    def blocked_sweep(self, rng, block_size):
        """One sweep of blocked, approximate collapsed Gibbs sampling.

        Each block of ``block_size`` points (in random order) is drawn against the statistics
        at the start of the block -- stale by the moves earlier in the same block -- and all its
        moves are applied at once. Points that draw a new cluster are then redrawn one at a
        time against the current state, with the same uniform, so that a block opens new
        clusters one by one (a fresh uniform opened one with probability ``p_new**2``, even
        at ``block_size=1``, where nothing is stale).
        """
        n_samples = self.X.shape[0]
        order = rng.permutation(n_samples)
        uniforms = rng.random(n_samples)
        n_moves = 0
        for pos in range(0, n_samples, block_size):
            idx = order[pos : pos + block_size]
            draws, stays = self.conditional_draws(idx, uniforms[pos : pos + block_size])
            K = self.K
            moving = ~stays & (draws < K)
            if np.any(moving):
                n_moves += self.move_many(idx[moving], draws[moving])
            for j in np.flatnonzero(~stays & (draws >= K)):
                i = idx[j]
                draw, stay = self.conditional_draws(np.array([i]), uniforms[pos + j : pos + j + 1])
                if not stay[0]:
                    self.move(i, self.labels[i], draw[0])
                    n_moves += 1
        return n_moves

    def move_many(self, points, targets):
        """Move ``points`` to existing clusters ``targets`` in one update of the statistics."""
        K = self.K
        sources = self.labels[points]
        Xp = self.X[points]
        n_out, s_out, S_out = sufficient_statistics(Xp, sources, K)
        n_in, s_in, S_in = sufficient_statistics(Xp, targets, K)
        self.n[:K] += n_in - n_out
        self.s[:K] += s_in - s_out
        self.S[:K] += S_in - S_out
        self.labels[points] = targets
        touched = np.union1d(sources, targets)
        self.refresh(touched)
        for k in sorted(np.flatnonzero(self.n[:K] == 0), reverse=True):
            self._delete(k)
        return len(points)

    def cached_t(self):
        K = self.K
        return StudentT(
            self.loc[:K], self.chol_inv[:K], self.scale[:K], self.dof[:K], self.const[:K]
        )

    def move(self, i, a, k):
        """Move point i from cluster a to cluster k (k == K opens a new cluster)."""
        x = self.X[i]
        xx = np.outer(x, x)
        if k == self.K:
            k = self._new_cluster()
        self.n[a] -= 1.0
        self.s[a] -= x
        self.S[a] -= xx
        self.n[k] += 1.0
        self.s[k] += x
        self.S[k] += xx
        self.labels[i] = k
        self.refresh(np.array([a, k]))
        if self.n[a] == 0:
            self._delete(a)

    # -- Jain & Neal (2004) split-merge ---------------------------------------------------
    def split_merge(self, rng):
        """One split-merge Metropolis-Hastings proposal (Jain & Neal 2004, with one final scan).

        Two distinct points i, j are drawn uniformly. The launch state of the points S of their
        cluster(s) depends only on S, i and j: seeds x_i and x_j, then a few restricted
        classification steps between the two sub-clusters. The split proposal allocates each
        point of S independently with the launch state's restricted conditional probabilities
        (a parallel final scan), so its probability q is a product and the merge move can
        evaluate the reverse split exactly. Returns True when the proposal is accepted.
        """
        X = self.X
        n_samples = X.shape[0]
        i, j = rng.choice(n_samples, 2, replace=False)
        a, b = self.labels[i], self.labels[j]
        members = np.flatnonzero((self.labels == a) | (self.labels == b))
        XS = X[members]
        pos_i = np.searchsorted(members, i)
        pos_j = np.searchsorted(members, j)
        log_q_left, log_q_right = _launch(XS, pos_i, pos_j, self.prior)
        fixed = np.zeros(len(members), dtype=bool)
        fixed[[pos_i, pos_j]] = True
        if a == b:
            right = rng.random(len(members)) < np.exp(log_q_right)
            right[pos_i], right[pos_j] = False, True
        else:
            right = self.labels[members] == b
        log_q = np.where(right, log_q_right, log_q_left)[~fixed].sum()
        delta = _split_gain(XS, right, self.prior, self.alpha)
        # delta = log p(split) - log p(merged); the split proposal has probability q.
        log_accept = delta - log_q if a == b else log_q - delta
        if math.log(rng.random()) >= log_accept:
            return False
        if a == b:
            k = self._new_cluster()
            self.labels[members[right]] = k
            self.recompute_clusters([a, k], members, right)
        else:
            self.labels[members] = a
            self.n[b] = 0.0
            self.recompute_clusters([a], members, np.zeros(len(members), dtype=bool))
            self._delete(b)
        return True

    def recompute_clusters(self, ks, members, right):
        XS = self.X[members]
        n, s, S = sufficient_statistics(XS, right.astype(np.intp), 2)
        for slot, k in enumerate(ks):
            self.n[k], self.s[k], self.S[k] = n[slot], s[slot], S[slot]
        self.refresh(np.array(ks))


def _split_gain(XS, right, prior, alpha):
    """``log p(X, split) - log p(X, merged)`` for points ``XS`` split by the mask ``right``."""
    n, s, S = sufficient_statistics(XS, right.astype(np.intp), 3)
    # third row: the merged cluster
    n[2], s[2], S[2] = n[0] + n[1], s[0] + s[1], S[0] + S[1]
    lml = log_marginal_likelihood(n, s, S, prior)
    lg = gammaln(n)
    return math.log(alpha) + lg[0] + lg[1] - lg[2] + lml[0] + lml[1] - lml[2]


def _launch(XS, pos_i, pos_j, prior, n_steps=2):
    """Launch state of a split-merge proposal: log P(left), log P(right) of each point.

    Depends only on the points, the two anchor positions and the prior, so that the split
    proposal and the reverse of a merge see the same distribution. The anchors start the two
    sub-clusters; each point joins the nearer anchor (in the metric of the prior scale matrix),
    then ``n_steps`` restricted classification steps reassign each point to the sub-cluster
    with the larger ``n_l t_l(x)``.
    """
    # Nearer to x_j than to x_i in the metric Psi0^{-1}: a half-space through the midpoint.
    normal = cho_solve(cho_factor(prior.psi, lower=True), XS[pos_j] - XS[pos_i])
    right = (XS - 0.5 * (XS[pos_i] + XS[pos_j])) @ normal > 0
    for step in range(n_steps + 1):
        right[pos_i], right[pos_j] = False, True
        n, s, S = sufficient_statistics(XS, right.astype(np.intp), 2)
        t, _ = predictive(n, s, S, prior)
        lp = log_student_t(XS, t) + np.log(n)
        if step == n_steps:
            norm = np.logaddexp(lp[:, 0], lp[:, 1])
            return lp[:, 0] - norm, lp[:, 1] - norm
        right = lp[:, 1] > lp[:, 0]


class DPGMMClusterer(ClusterMixin, BaseEstimator):
    """Dirichlet-process Gaussian mixture clustering by collapsed Gibbs sampling.

    The number of clusters is inferred: the partition has a Chinese-restaurant-process prior with
    concentration ``alpha``, each cluster is Gaussian with a conjugate Normal-inverse-Wishart
    prior on its mean and covariance, and the means and covariances are integrated out. The
    sampler alternates

    - sweeps of exact collapsed Gibbs sampling (Neal 2000, Algorithm 3): each point is
      reassigned from its conditional given all others, which is proportional to
      ``n_k t_k(x)`` for an existing cluster and ``alpha t_0(x)`` for a new one, where
      ``t_k`` is the cluster's posterior predictive multivariate Student-t;
    - split-merge Metropolis-Hastings moves (Jain & Neal 2004) that split or merge whole
      clusters, which single-site moves cannot do on large data.

    The state is initialised by k-means (or as given by ``init``), after which clusters are
    merged, bisected and merged again greedily while the log joint rises (a deterministic
    search, part of the initialisation only). The fitted state is the sample with the highest
    log joint ``log p(X, z)`` seen after burn-in, whose clusters are then merged greedily while
    the log joint rises: a point estimate of the partition, not a sample. On two Gaussian
    blobs of 150 points, 4 sigma apart, the best sample alone held 3 to 6 clusters for 6 of
    20 seeds (spurious clusters of 2-5 points); merged, 19 of 20 hold the two blobs.

    The Gibbs sweeps are exact: the conditionals of a block of points are evaluated in one
    vectorised step against cached per-cluster predictives (the point's own cluster through a
    closed-form leave-one-out update), and the block is cut at its first point that moves, so
    every draw sees the current state. ``block_size`` switches to faster approximate sweeps.

    Parameters
    ----------
    alpha : float, default=1.0
        Concentration of the Dirichlet process.
    mean_prior : array-like of shape (n_features,), default=None
        Prior mean ``m0`` of the cluster means. None: the mean of ``X``.
    mean_precision_prior : float, default=None
        ``kappa0``: the prior on a cluster mean is ``N(m0, Sigma / kappa0)``. None: 1.
    covariance_prior : float or array-like of shape (n_features, n_features), default=None
        Scale matrix ``Psi0`` of the inverse-Wishart prior on the cluster covariances (a float
        is a multiple of the identity). None: the empirical covariance of ``X``, plus
        ``1e-6`` times its mean variance (or ``1e-6`` for constant data) on the diagonal so that
        it is positive definite.
    degrees_of_freedom_prior : float, default=None
        ``nu0`` of the inverse-Wishart prior; must exceed ``n_features - 1``. None:
        ``n_features``.
    init : {"kmeans", "one", "random"}, default="kmeans"
        Starting partition: k-means with ``ceil(2 alpha log(1 + n / alpha))`` clusters (at most
        50), all points in one cluster, or uniformly random labels over that many clusters.
        Either way clusters are then merged, bisected and merged greedily while the log joint
        rises.
    block_size : int, default=None
        None: exact collapsed Gibbs. An int: approximate, blocked sweeps in which the points of
        each block are drawn against the statistics at the start of the block (stale by the
        moves earlier in that block) and moved together; faster when many points move per
        sweep (overlapping clusters, large data). Split-merge moves stay exact.
    n_split_merge : int, default=10
        Split-merge proposals after each Gibbs sweep.
    burn_in : int, default=5
        Sweeps before samples become candidates for the final state (capped at
        ``max_iter - 1``).
    max_iter : int, default=200
        Maximum number of sweeps.
    tol : float, default=1e-3
        Convergence threshold per sample: sampling stops once the highest log joint seen after
        burn-in has not risen by more than ``tol * n_samples`` for ``n_iter_no_change`` sweeps.
    n_iter_no_change : int, default=5
        Patience of the stopping rule, in sweeps.
    random_state : int, RandomState instance or None, default=None
        Seed of the sampler (initialisation, sweep order, proposals).
    verbose : int, default=0
        Print the log joint and the number of clusters after each sweep when positive.

    Attributes
    ----------
    labels_ : ndarray of shape (n_samples,)
        Cluster of each training point, in ``0..n_clusters_-1`` (largest cluster first).
    n_clusters_ : int
        Number of clusters of the final state.
    means_ : ndarray of shape (n_clusters, n_features)
        Posterior mean ``m_n`` of each cluster mean.
    covariances_ : ndarray of shape (n_clusters, n_features, n_features)
        ``Psi_n / nu_n``, the inverse of the posterior mean precision (as
        ``BayesianGaussianMixture.covariances_``).
    weights_ : ndarray of shape (n_clusters,)
        ``n_k / n_samples``. The mass ``alpha / (n_samples + alpha)`` of a new cluster is not
        included.
    n_iter_ : int
        Number of sweeps run.
    log_joint_ : ndarray of shape (n_iter,)
        Log joint ``log p(X, z)`` after each sweep.
    best_log_joint_ : float
        Log joint of the final state (after the merges; at least the best sample's).
    converged_ : bool
        Whether the stopping rule was met before ``max_iter``.
    mean_prior_, mean_precision_prior_, covariance_prior_, degrees_of_freedom_prior_
        The resolved prior.
    n_features_in_ : int
        Number of features seen during fit.

    See Also
    --------
    sklearn.mixture.BayesianGaussianMixture : Variational inference for the same model,
        truncated at ``n_components``.

    Notes
    -----
    Prior mapping to ``BayesianGaussianMixture(weight_concentration_prior_type=
    "dirichlet_process")``: ``weight_concentration_prior=alpha``, ``mean_prior=mean_prior_``,
    ``mean_precision_prior=mean_precision_prior_``, ``covariance_prior=covariance_prior_``,
    ``degrees_of_freedom_prior=degrees_of_freedom_prior_``. Its Wishart prior on the precision
    with inverse scale ``covariance_prior`` is exactly our inverse-Wishart prior on the covariance
    with scale matrix ``Psi0``. The defaults here are its defaults except ``alpha`` (it uses
    ``1 / n_components``) and the small diagonal term added to the default ``Psi0``.

    ``predict_proba`` returns posterior-predictive responsibilities
    ``w_k t_k(x) / sum_j w_j t_j(x)`` over the ``n_clusters_`` clusters of the final state;
    the new-cluster option is left out so that the columns are exactly the clusters.

    The split-merge proposal uses a deterministic launch state and one parallel restricted
    scan in which the points of the split cluster are allocated independently, so that the
    proposal probability is a product and every move is a valid Metropolis-Hastings step.

    References
    ----------
    R. M. Neal (2000), "Markov chain sampling methods for Dirichlet process mixture models",
    J. Comp. Graph. Stat. 9(2). S. Jain and R. M. Neal (2004), "A split-merge Markov chain Monte
    Carlo procedure for the Dirichlet process mixture model", J. Comp. Graph. Stat. 13(1).
    K. P. Murphy (2007), "Conjugate Bayesian analysis of the Gaussian distribution".

    Examples
    --------
    >>> import numpy as np
    >>> from skoccmap import DPGMMClusterer
    >>> rng = np.random.default_rng(0)
    >>> X = np.vstack([rng.normal(c, 0.3, size=(100, 2)) for c in ([0, 0], [4, 0], [0, 4])])
    >>> model = DPGMMClusterer(random_state=0).fit(X)
    >>> model.n_clusters_
    3
    >>> model.predict_proba([[4.0, 0.1]]).round(3).max()
    np.float64(1.0)
    """

    _parameter_constraints: dict = {
        "alpha": [Interval(Real, 0, None, closed="neither")],
        "mean_prior": ["array-like", None],
        "mean_precision_prior": [Interval(Real, 0, None, closed="neither"), None],
        "covariance_prior": ["array-like", Interval(Real, 0, None, closed="neither"), None],
        "degrees_of_freedom_prior": [Interval(Real, 0, None, closed="neither"), None],
        "init": [StrOptions({"kmeans", "one", "random"})],
        "block_size": [Interval(Integral, 1, None, closed="left"), None],
        "n_split_merge": [Interval(Integral, 0, None, closed="left")],
        "burn_in": [Interval(Integral, 0, None, closed="left")],
        "max_iter": [Interval(Integral, 1, None, closed="left")],
        "tol": [Interval(Real, 0, None, closed="left")],
        "n_iter_no_change": [Interval(Integral, 1, None, closed="left")],
        "random_state": ["random_state"],
        "verbose": ["verbose"],
    }

    def __init__(
        self,
        alpha=1.0,
        *,
        mean_prior=None,
        mean_precision_prior=None,
        covariance_prior=None,
        degrees_of_freedom_prior=None,
        init="kmeans",
        block_size=None,
        n_split_merge=10,
        burn_in=5,
        max_iter=200,
        tol=1e-3,
        n_iter_no_change=5,
        random_state=None,
        verbose=0,
    ):
        self.alpha = alpha
        self.mean_prior = mean_prior
        self.mean_precision_prior = mean_precision_prior
        self.covariance_prior = covariance_prior
        self.degrees_of_freedom_prior = degrees_of_freedom_prior
        self.init = init
        self.block_size = block_size
        self.n_split_merge = n_split_merge
        self.burn_in = burn_in
        self.max_iter = max_iter
        self.tol = tol
        self.n_iter_no_change = n_iter_no_change
        self.random_state = random_state
        self.verbose = verbose

    def _resolve_prior(self, X):
        D = X.shape[1]
        if self.mean_prior is None:
            mean = X.mean(0)
        else:
            mean = np.asarray(self.mean_prior, dtype=float).reshape(-1)
            if mean.shape != (D,) or not np.all(np.isfinite(mean)):
                raise ValueError(
                    f"mean_prior must be a finite array of shape ({D},), got "
                    f"{self.mean_prior!r} of shape {mean.shape}."
                )
        kappa = 1.0 if self.mean_precision_prior is None else float(self.mean_precision_prior)
        nu = (
            float(D)
            if self.degrees_of_freedom_prior is None
            else float(self.degrees_of_freedom_prior)
        )
        if nu <= D - 1:
            raise ValueError(
                f"degrees_of_freedom_prior must be greater than n_features - 1 = {D - 1}, "
                f"got {nu}."
            )
        if self.covariance_prior is None:
            psi = np.atleast_2d(np.cov(X.T))
            mean_var = np.trace(psi) / D
            psi = psi + 1e-6 * (mean_var if mean_var > 0 else 1.0) * np.eye(D)
        elif np.ndim(self.covariance_prior) == 0:  # a number, or a 0-d array of one
            scale = float(self.covariance_prior)
            if not (np.isfinite(scale) and scale > 0):
                raise ValueError(
                    f"covariance_prior must be a positive number or a ({D}, {D}) symmetric "
                    f"positive definite matrix, got {self.covariance_prior!r}."
                )
            psi = scale * np.eye(D)
        else:
            psi = np.asarray(self.covariance_prior, dtype=float)
            if psi.shape != (D, D):
                raise ValueError(f"covariance_prior must have shape ({D}, {D}), got {psi.shape}.")
            if not np.allclose(psi, psi.T) or np.any(np.linalg.eigvalsh(psi) <= 0):
                raise ValueError("covariance_prior must be symmetric positive definite.")
        return mean, kappa, nu, psi

    def _initial_labels(self, X, rng, prior):
        n_samples = X.shape[0]
        if self.init == "one":
            labels = np.zeros(n_samples, dtype=np.intp)
        else:
            k0 = math.ceil(2.0 * self.alpha * math.log1p(n_samples / self.alpha))
            k0 = int(min(max(k0, 2), 50, n_samples))
            if self.init == "random":
                labels = rng.integers(k0, size=n_samples)
            else:
                labels = _kmeans(X, k0, rng)
        _, labels = np.unique(labels, return_inverse=True)
        K = int(labels.max()) + 1
        labels = greedy_merge(*sufficient_statistics(X, labels, K), prior, self.alpha)[labels]
        labels = greedy_split(X, labels, prior, self.alpha)
        K = int(labels.max()) + 1
        return greedy_merge(*sufficient_statistics(X, labels, K), prior, self.alpha)[labels]

    @fit_or_unfitted
    @_fit_context(prefer_skip_nested_validation=True)
    def fit(self, X, y=None):
        """Sample cluster assignments of ``X``.

        Parameters
        ----------
        X : array-like of shape (n_samples, n_features)
            Points (not segments).
        y : Ignored
            Not used, present for API consistency.

        Returns
        -------
        self : DPGMMClusterer
            Fitted estimator.
        """
        X = check_magnitude(validate_data(self, X, dtype=np.float64, ensure_min_samples=2))
        rng = np.random.default_rng(check_random_state(self.random_state).randint(2**31))
        mean, kappa, nu, psi = self._resolve_prior(X)
        self.mean_prior_ = mean
        self.mean_precision_prior_ = kappa
        self.degrees_of_freedom_prior_ = nu
        self.covariance_prior_ = psi
        # Work in coordinates centred on the data mean: the raw-moment statistics then lose no
        # precision to data far from the origin.
        self._shift = X.mean(0)
        Xc = X - self._shift
        prior = NIWPrior(mean - self._shift, kappa, nu, psi)

        state = _CollapsedGibbs(Xc, self._initial_labels(Xc, rng, prior), prior, self.alpha)
        n_samples = X.shape[0]
        burn_in = min(self.burn_in, self.max_iter - 1)
        trace = []
        best, best_labels, stale = -np.inf, None, 0
        self.converged_ = False
        for sweep in range(self.max_iter):
            if self.block_size is None:
                state.gibbs_sweep(rng)
            else:
                state.blocked_sweep(rng, self.block_size)
            for _ in range(self.n_split_merge):
                state.split_merge(rng)
            state.recompute()
            current = float(state.log_joint())
            trace.append(current)
            if self.verbose:
                print(f"sweep {sweep + 1}: log joint {current:.3f}, {state.K} clusters")
            if sweep < burn_in:
                continue
            if current > best + self.tol * n_samples:
                stale = 0
            else:
                stale += 1
            if current > best:
                best, best_labels = current, state.labels.copy()
            if stale >= self.n_iter_no_change:
                self.converged_ = True
                break
        self.n_iter_ = sweep + 1
        self.log_joint_ = np.array(trace)
        # The best sample is a point estimate: a short chain often leaves a few small clusters
        # that merging would improve (two blobs came back as up to six clusters, 70 nats
        # below the two). Merge greedily while the log joint rises, as at the start.
        _, best_labels = np.unique(best_labels, return_inverse=True)
        statistics = sufficient_statistics(Xc, best_labels, int(best_labels.max()) + 1)
        best_labels = greedy_merge(*statistics, prior, self.alpha)[best_labels]
        if not self.converged_:
            warnings.warn(
                f"Sampling stopped at max_iter={self.max_iter} sweeps while the log joint was "
                "still rising; increase max_iter.",
                ConvergenceWarning,
                stacklevel=caller_stacklevel(),
            )
        self._set_final_state(Xc, best_labels, prior)
        self.best_log_joint_ = float(log_joint(*self._statistics, prior, self.alpha))
        self._prior = prior
        # The sampler's generator goes on in partial_fit: a sequence of calls is reproducible.
        self._rng = rng
        return self

    @_fit_context(prefer_skip_nested_validation=True)
    def partial_fit(self, X, y=None):
        """Add points to the fitted clusters, or open new ones (online clustering).

        The first call (on an unfitted clusterer) is :meth:`fit`. Later calls hold the
        clusters of the points seen so far fixed (their sufficient statistics) and seat the
        new points one at a time in random order, each drawn from its collapsed Gibbs
        conditional: an existing cluster ``k`` with weight ``n_k t_k(x)`` (posterior
        predictive), a new one with weight ``alpha t_0(x)`` (the Dirichlet process's new
        table: points far from every cluster open one). Then ``burn_in`` sweeps of exact
        collapsed Gibbs sampling over the new points only (each given all others) let the
        first-seated points follow the clusters opened after them. Old points keep their
        clusters, and old cluster labels keep their numbers; new clusters are numbered
        from ``n_clusters_`` on. The prior stays the one resolved by the first fit. The
        clusters' statistics are sums about the first fit's mean: points so far from it
        that their rounding would swamp a cluster's scale (for a first fit spread over
        metres, thousands of kilometres away in a direction the points spread in) are
        refused with a ValueError.

        Parameters
        ----------
        X : array-like of shape (n_samples, n_features)
            New points.
        y : Ignored
            Not used, present for API consistency.

        Returns
        -------
        self : DPGMMClusterer
            The updated estimator. ``labels_`` holds the clusters of the points of this
            call (as :class:`~sklearn.cluster.MiniBatchKMeans` does); ``n_clusters_``,
            ``means_``, ``covariances_``, ``weights_`` and the predictive cover all points
            seen.

        Examples
        --------
        >>> import numpy as np
        >>> from skoccmap import DPGMMClusterer
        >>> rng = np.random.default_rng(0)
        >>> room_a = rng.normal([0, 0], 0.3, size=(100, 2))
        >>> room_b = rng.normal([8, 0], 0.3, size=(50, 2))
        >>> model = DPGMMClusterer(random_state=0).partial_fit(room_a)
        >>> model.n_clusters_
        1
        >>> model.partial_fit(room_b).n_clusters_
        2
        >>> np.unique(model.labels_).tolist()
        [1]
        """
        if not hasattr(self, "_statistics"):
            return self.fit(X)
        X = check_magnitude(validate_data(self, X, dtype=np.float64, reset=False))
        Xc = X - self._shift
        rng = self._rng
        before = rng.bit_generator.state
        try:
            # Draws up front: the seating order and one uniform per point.
            order = rng.permutation(X.shape[0])
            uniforms = rng.random(X.shape[0])
            state = _CollapsedGibbs(
                Xc, np.zeros(X.shape[0], dtype=np.intp), self._prior, self.alpha, self._statistics
            )
            for i, u in zip(order, uniforms, strict=True):
                state.seat(i, u)
            if X.shape[0] > 1:
                for _ in range(self.burn_in):
                    state.gibbs_sweep(rng)
            K = state.K
            n, s, S = state.n[:K].copy(), state.s[:K].copy(), state.S[:K].copy()
            if not _precise(n, s, S, self._prior):
                raise np.linalg.LinAlgError("scale matrices within their rounding")
            self._set_statistics(n, s, S, self._prior)
        except np.linalg.LinAlgError:
            # The statistics are sums of x and x x^T about the first fit's mean: far enough
            # from it, the rounding of those sums outgrows the prior's scale (set by the
            # spread of the first fit's points), and a cluster's scale matrix is no longer
            # positive definite, or no longer known to its smallest eigenvalue (see
            # _precise). The clusterer stays as it was, its generator included.
            rng.bit_generator.state = before
            distance = float(np.max(np.linalg.norm(Xc, axis=1)))
            spread = float(np.sqrt(np.trace(self._prior.psi) / X.shape[1]))
            raise ValueError(
                f"X holds points {distance:.3g} from the mean of the points the clusterer "
                f"was fitted on, whose spread sets its prior scale ({spread:.3g}): that far, "
                "the clusters' statistics lose their precision. Are these points in the "
                "coordinate frame of the first fit? Fit again on all points."
            ) from None
        self.labels_ = state.labels.copy()
        return self

    def _set_final_state(self, Xc, labels, prior):
        # Largest cluster first, so that labels do not depend on slot bookkeeping.
        counts = np.bincount(labels)
        present = np.flatnonzero(counts)
        order = present[np.argsort(-counts[present], kind="stable")]
        relabel = np.empty(len(counts), dtype=np.intp)
        relabel[order] = np.arange(len(order))
        self.labels_ = relabel[labels]
        K = len(order)
        self._set_statistics(*sufficient_statistics(Xc, self.labels_, K), prior)

    def _set_statistics(self, n, s, S, prior):
        """Cluster attributes and the predictive from the clusters' sufficient statistics."""
        K = len(n)
        _, nu, mean, psi = posterior(n, s, S, prior)
        # First, as it may fail (a scale matrix not positive definite): then nothing is set.
        self._predictive, _ = predictive(n, s, S, prior)
        self._statistics = (n, s, S)
        self.n_clusters_ = K
        self.means_ = mean + self._shift
        self.covariances_ = psi / nu[:, None, None]
        self.weights_ = n / n.sum()

    def predict_proba(self, X):
        """Posterior-predictive responsibilities of the clusters for new points.

        Parameters
        ----------
        X : array-like of shape (n_samples, n_features)

        Returns
        -------
        proba : ndarray of shape (n_samples, n_clusters)
            ``w_k t_k(x)`` normalised over the clusters; rows sum to 1.
        """
        log_resp = self._log_weighted_density(X)
        return np.exp(log_resp - logsumexp(log_resp, axis=1, keepdims=True))

    def predict(self, X):
        """Most probable cluster of each point under the posterior predictive.

        Parameters
        ----------
        X : array-like of shape (n_samples, n_features)

        Returns
        -------
        labels : ndarray of shape (n_samples,)
        """
        return np.argmax(self._log_weighted_density(X), axis=1)

    def score_samples(self, X):
        """Log density of the posterior predictive at new points.

        ``log p(x | X, z) = log(sum_k n_k t_k(x) + alpha t_0(x)) - log(n + alpha)``: the
        Chinese-restaurant predictive of one more point given the partition of the final
        state (as in Algorithm 3 of Neal 2000, the cluster parameters integrated out),
        ``t_k`` the clusters' posterior predictive Student-t and ``t_0`` the prior's. The
        new-cluster term keeps it a density in ``x`` (it integrates to 1), unlike the sum
        over the fitted clusters alone (:meth:`predict_proba` leaves it out).

        Parameters
        ----------
        X : array-like of shape (n_samples, n_features)

        Returns
        -------
        log_density : ndarray of shape (n_samples,)

        Examples
        --------
        >>> import numpy as np
        >>> from skoccmap import DPGMMClusterer
        >>> rng = np.random.default_rng(0)
        >>> X = np.vstack([rng.normal(c, 0.3, size=(100, 2)) for c in ([0, 0], [4, 0])])
        >>> model = DPGMMClusterer(random_state=0).fit(X)
        >>> log_p = model.score_samples([[0.0, 0.0], [2.0, 0.0]])
        >>> bool(log_p[0] > log_p[1])
        True
        """
        return logsumexp(self._log_weighted_density(X, new_cluster=True), axis=1)

    def score(self, X, y=None):
        """Mean log density of the posterior predictive at ``X`` (see :meth:`score_samples`).

        The default score of model selection (e.g. ``GridSearchCV`` over ``alpha`` scores
        held-out points by it), as :meth:`sklearn.mixture.BayesianGaussianMixture.score`.

        Parameters
        ----------
        X : array-like of shape (n_samples, n_features)
        y : Ignored
            Not used, present for API consistency.

        Returns
        -------
        score : float
        """
        return float(np.mean(self.score_samples(X)))

    def _log_weighted_density(self, X, new_cluster=False):
        """``log w_k + log t_k(x)`` of each point and cluster, ``w = weights_``; with
        ``new_cluster``, the Chinese restaurant's ``w_k = n_k / (n + alpha)`` and a last
        column for a new cluster, of weight ``alpha / (n + alpha)`` and the prior's t."""
        check_is_fitted(self)
        X = check_magnitude(validate_data(self, X, dtype=np.float64, reset=False))
        X = X - self._shift
        t, log_w = self._predictive, np.log(self.weights_)
        if new_cluster:
            n, prior_t = self._statistics[0], prior_predictive(self._prior)
            t = StudentT(*(np.concatenate(pair) for pair in zip(t, prior_t, strict=True)))
            log_w = np.log(np.append(n, self.alpha)) - np.log(n.sum() + self.alpha)
        out = np.empty((X.shape[0], len(log_w)))
        for start in range(0, X.shape[0], _CHUNK):
            rows = slice(start, start + _CHUNK)
            out[rows] = log_student_t(X[rows], t) + log_w
        return out


# A cluster's scale matrix is refused when the rounding of its raw-moment formula could
# reach this fraction of its smallest eigenvalue.
_SCALE_ROUNDING = 0.1


def _precise(n, s, S, prior):
    """Whether every cluster's posterior scale matrix ``Psi_n`` stands above the rounding
    of ``Psi0 + S + kappa0 m0 m0^T - kappa_n m_n m_n^T``, whose terms grow with the square
    of the points' distance from the origin of the statistics.

    Each term is positive semi-definite, so the rounding of entry (i, j) is at most a few
    eps times ``sqrt(size_i size_j)``, ``size`` the terms' diagonals summed. With every
    coordinate divided by ``sqrt(size_i)`` the rounding is at most ``8 eps D`` in norm, and
    ``Psi_n`` is known to ``_SCALE_ROUNDING`` of its smallest eigenvalue when that
    eigenvalue is at least ten times it. Per coordinate, so that a coordinate the points
    share exactly (the height of a level 2-D laser's rows) is not held to the others' size.
    """
    kappa, _, mean, psi = posterior(n, s, S, prior)
    size = (
        np.diagonal(S, axis1=1, axis2=2)
        + kappa[:, None] * mean**2
        + np.diag(prior.psi)
        + prior.kappa * prior.mean**2
    )
    scale = 1.0 / np.sqrt(size)
    scaled = psi * scale[:, :, None] * scale[:, None, :]
    rounding = 8 * np.finfo(float).eps * psi.shape[1]
    return bool(np.all(rounding <= _SCALE_ROUNDING * np.linalg.eigvalsh(scaled)[:, 0]))


def _kmeans(X, n_clusters, rng):
    """Labels of a short k-means run (k-means++ seeding, a few Lloyd iterations)."""
    from sklearn.cluster import KMeans

    seed = int(rng.integers(2**31))
    model = KMeans(n_clusters=n_clusters, n_init=1, max_iter=20, random_state=seed)
    with warnings.catch_warnings():
        # Duplicate points may leave fewer distinct clusters than asked; that is fine here.
        warnings.simplefilter("ignore", ConvergenceWarning)
        return model.fit_predict(X)
