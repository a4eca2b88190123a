"""Mixture of Gaussian-process experts for occupancy mapping (Kim & Kim, ICRA 2012).

The hit points are clustered; every observation joins a cluster; one GP classifier (an
*expert*) is fitted per cluster; at query time a gating function ``p(cluster | x)`` weighs
the experts, whose latent predictions are merged by a rule of :mod:`skoccmap.combine`.
"""

import copy
import sys
import time
from functools import partial
from numbers import Integral, Real

import numpy as np
from sklearn import get_config
from sklearn.base import BaseEstimator, ClassifierMixin, _fit_context, clone
from sklearn.utils import check_random_state, gen_batches
from sklearn.utils._param_validation import HasMethods, Interval, StrOptions
from sklearn.utils.multiclass import check_classification_targets
from sklearn.utils.parallel import Parallel, delayed
from sklearn.utils.validation import check_is_fitted, validate_data

from ._beams import (
    _NO_RETURN_REFERENCES,
    _assign_no_return,
    _beam_pieces,
    _hit_tree,
    _midpoints,
    _observation_kinds,
    _similarity_length_scale,
)
from ._experts import (
    _append_rows,
    _appended,
    _ConstantExpert,
    _default_expert,
    _default_kernel,
    _fit_expert,
    _integral_parts,
    _is_binary_ep,
    _learns_kernel,
    _prior_variance,
    _takes_kernel_matrix,
    _warn_once_each,
)
from ._integrals import _POINT_CHUNK, point_row_pairs
from ._partition import (
    _best,
    _bisect,
    _groups,
    _merge_small,
    _nearest_with_room,
    _piece_gates,
    _PieceGate,  # noqa: F401 (models pickled before the gates moved name it here)
    _query_max,
    _query_workers,
    _split_hits,
)
from ._reach import ExpertReach, _extent, kernel_reach, threads_pay
from ._shared_kernel import (
    learn_shared_kernel,
    warn_at_bounds,
    warn_beyond_extent,
    window_pieces,
)
from ._thinning import thin_free_pieces
from ._transient import CellCounts
from ._validation import (
    check_known_labels,
    check_magnitude,
    fit_or_unfitted,
    non_finite_explained,
    unfitted_on_error,
    validate_queries,
    warn,
    warn_if_coarse_float32,
    warn_unless_metres,
)
from .combine import COMBINERS, combine_pairs
from .observations import HIT, NO_RETURN, RETURN

__all__ = ["MixtureGPOccupancyMap"]

# Training points of the gpc gating classifier (a GP over cluster labels is cubic in them).
_GATING_GPC_MAX_SAMPLES = 300
# Pieces (experts or windows) whose summed evidence learns the shared hyperparameters, at a
# cost that does not grow with the map: a few dozen fix one or two hyperparameters, but
# which 64 are drawn moves the length scale by about a tenth on a dense log (see
# share_hyperparameters); rows per window when experts are not size-bounded.
_SHARED_PIECES = 128
_SHARED_WINDOW_ROWS = 400
# gating="coverage" counts an expert's cells within the distance at which the kernel falls
# to this fraction of its peak: half a length scale for the squared exponential.
_COVERAGE_TOLERANCE = float(np.exp(-1.0 / 8.0))
# gating_threshold="auto", by gate (see the parameter's docstring for the measurements):
# relative to the best-covered expert's share for the coverage gate, absolute otherwise.
_AUTO_GATING_THRESHOLD = {"coverage": 0.35, "clusterer": 1e-3, "gpc": 1e-3}
# Hits a free piece may join under piece_assignment="nearest_hit", nearest first: with
# dense scans the nearest ones fill up (see _nearest_with_room).
_NEAREST_HITS = 32
# Cells (metres) in which ``min_hit_frequency`` counts hits and passes: the counting grid of
# the Hilbert-maps protocol.
_HIT_CELL_SIZE = 0.1
# ... and a cell hit more often than this is lasting structure whatever its frequency: a
# passer-by leaves a few hits per cell, a wall seen from many poses collects more.
_MAX_TRANSIENT_HITS = 3


def _as_segment_rows(X, layout):
    """Segment rows ``[start, end]`` of ``X`` read with the given layout.

    Coordinates beyond 1e100 are refused (``check_magnitude``): in fit they ran the
    no-return assignment into inf and NaN before the beams' pieces stopped on an
    OverflowError, in prediction the spatial index stopped on SciPy's "floating point
    overflow" and a long query segment got a prior variance of 0.
    """
    X = check_magnitude(X)
    if layout == "points":
        return np.hstack([X, X])
    if X.shape[1] % 2:
        # "feature(s)" wording: the message sklearn's checks look for on 1-column input.
        raise ValueError(
            f"X has {X.shape[1]} feature(s); with layout='segments' MixtureGPOccupancyMap "
            "needs segment rows [start_1..start_D, end_1..end_D] with an even number of "
            "columns (2*D). Pass layout='points' for rows that are points."
        )
    return X


def _check_training_rows(X, y_enc, classes):
    """The checks every batch of training rows passes, in ``fit`` and each ``partial_fit``:
    labels the right way round, and coordinates in metres (a warning)."""
    _check_hits_are_points(X, y_enc == 1, classes)
    d = X.shape[1] // 2
    warn_unless_metres(X[:, :d], X[:, d:])


def _check_hits_are_points(X, occupied, classes):
    """Refuse labels the wrong way round, and warn where the hits are not points.

    Hits (``classes[1]``) are zero-length rows and beams have a length. Rows labelled
    occupied that are mostly segments, beside free rows that are all points, are labels
    reversed (``1 - y``, or strings whose order puts "miss" last): the map would be
    inverted. Most occupied rows with a length otherwise (points of 2 coordinates read as
    1-D segments, columns scaled each on its own, or surface segments) give a map the
    defaults were not made for.
    """
    dim = X.shape[1] // 2
    classes = classes.tolist()  # labels as Python scalars: 1, not np.int64(1)
    has_length = np.any(X[:, :dim] != X[:, dim:], axis=1)
    if not np.any(occupied) or 2 * np.count_nonzero(has_length[occupied]) <= occupied.sum():
        return
    if np.any(~occupied) and not np.any(has_length[~occupied]):
        raise ValueError(
            f"The rows labelled occupied (y == {classes[1]!r}, the larger label) are mostly "
            f"segments of positive length, and every row labelled free (y == {classes[0]!r}) "
            "is a point: the labels look reversed. Hits are zero-length rows [x, x] and take "
            "the larger label; beams are segments from the sensor to the hit."
        )
    hint = (
        " X has 2 columns, read as 1-D segments [start, end]: if its rows are 2-D points, "
        "pass layout='points', or beams as segments and hits as "
        "skoccmap.as_segments(points)."
        if dim == 1
        else " Were the start and end columns transformed each on its own (a "
        "StandardScaler in a pipeline does so)? Give the map coordinates in metres, starts "
        "and ends alike."
    )
    warn(
        f"Most rows labelled occupied (y == {classes[1]!r}) are segments of positive "
        f"length, where hits are zero-length rows [x, x].{hint}",
        UserWarning,
    )


def _check_two_classes(classes):
    if classes.size != 2:
        # scikit-learn's checks ask a binary classifier to say so of more classes.
        refusal = "Only binary classification is supported. " if classes.size > 2 else ""
        raise ValueError(
            f"{refusal}MixtureGPOccupancyMap needs y with exactly 2 classes (free and "
            f"occupied), got {classes.size} class(es): {classes.tolist()}."
        )


def _log(verbose, message):
    if verbose:
        print(f"[MixtureGPOccupancyMap] {message}", file=sys.stdout, flush=True)


def _warn_if_every_hit_transient(transient_hit, bound):
    """A map whose every hit was left out as transient shows no obstacle: say so."""
    if transient_hit.size and transient_hit.all():
        warn(
            f"Every hit was left out as transient (min_hit_frequency={bound}): free beams "
            "cross each hit's cell far more often than it is hit, so the map shows no "
            "obstacle. Set min_hit_frequency=None to keep every hit.",
            UserWarning,
        )


# ---------------------------------------------------------------------------------------
# The estimator
# ---------------------------------------------------------------------------------------


class MixtureGPOccupancyMap(ClassifierMixin, BaseEstimator):
    """Occupancy map from a mixture of Gaussian-process experts (Kim & Kim, ICRA 2012).

    ``fit`` clusters the hit points, assigns every observation to a cluster, fits one GP
    classifier per cluster (in parallel) and a gating function ``p(cluster | x)``;
    ``predict_proba`` merges the experts' latent predictions with ``combiner``.

    Observations are segment rows ``[start_1..start_D, end_1..end_D]`` (see
    :func:`skoccmap.observations.as_segments`); ``y`` holds two class labels, the larger
    one (``classes_[1]``, i.e. 1 in {0, 1}) meaning *occupied*: its rows are the hit
    points and are clustered; the others are laser beams (free space).

    Parameters
    ----------
    clusterer : estimator, default=None
        Clusters the hit points (the start coordinates of the occupied rows, shape
        ``(n_hits, D)``). Anything with ``fit`` and ``predict`` works; ``labels_`` is used
        when present. With ``gating="clusterer"`` its ``predict_proba`` (if any) gives the
        gating weights, otherwise its hard ``predict``. ``None`` means
        :class:`~skoccmap.DPGMMClusterer` with default parameters.
    expert : estimator, default=None
        Binary classifier cloned once per cluster; it must have ``fit`` and
        ``latent_mean_and_variance``. Its prior latent variance is read from its
        ``kernel_``; an expert that exposes none has prior variance 1 (the probit's
        scale), e.g. in :meth:`prior_variance`. ``None`` means
        :class:`~skoccmap.EPGaussianProcessClassifier` with
        ``ConstantKernel(1e3, "fixed") * IntegralKernel()`` and ``tol=1e-4``: only the
        length scale is learned. Occupancy data are nearly separable, so the EP evidence
        grows with the signal variance until the map saturates: learned within [1e-2,
        1e5] on the tuning data it ends at the upper bound on the office and the paper's
        world (1e5, with a ``ConvergenceWarning``) and fits take 1.4-3.5 times as long
        (``benchmarks/bench_tuning.py``, tuning seed 100). Fixed at 1e2 / 1e3 / 1e4 it
        finds 79.1 / 90.3 / 96.1 % of the sparse paper's world's walls, at office ECE
        0.058 / 0.042 / 0.035, and ranks ACES' held-out points 0.9650 / 0.9683 / 0.9660.
        1e4 would find those walls, but the length scale it learns is 36-43 % longer
        (ACES), so a query consults more experts (10.2 against 7.3 on ACES' every scan),
        and on B2's world at 3 million observations it ranks the cells 0.9919 against
        0.9949 (``benchmarks/README.md``). 1e3 ranks ACES best of the fixed values.
        The default expert's EP stops at ``tol=1e-4`` (no site would change by more than
        1e-4 of its marginal; the classifier's own default is 1e-6): on the tuning data
        (ACES seed 100, the sparse worlds' seed 100) every score is the same to the
        printed digit (ACES held-out AUC 0.9673 on every 10th scan and 0.9761 on every
        scan; the worlds' AUC, phantoms, free space, walls, ECE and Brier) with the same
        learned length scale, probabilities move by at most 3e-4, and an expert's EP
        takes a fifth fewer sweeps (18.8 against 23.5 on ACES' every 10th scan).
        An expert whose ``kernel`` is None (e.g. ``EPGaussianProcessClassifier(tol=1e-3)``,
        to change EP's settings) gets the default kernel above: its own default would read
        a beam's ``[start, end]`` columns as one point (an RBF over four coordinates).
    gating : {"coverage", "clusterer", "gpc"}, default="coverage"
        The weight ``p(expert | x)`` of each expert within reach of a query: it chooses
        the experts consulted (see ``gating_threshold``), and weighs them under
        ``combiner="moe"`` (the product rules weigh by confidence). ``"coverage"``: the
        expert's share of the training data near the query, counted as the index's cells
        (an eighth of ``reach_`` wide) that hold its segments' midpoints, each weighted by
        ``exp(-d**2 / (2 w**2))`` of its distance ``d`` to the query, with ``w =
        coverage_width_`` (half a length scale for the default kernel) and up to three
        widths; where no expert has data that near, equal weights (and the clusterer's
        gate when ``reach_`` is infinite: no cells are indexed). ``"clusterer"``: the
        clusterer's posterior responsibilities at the query's midpoint, shared among a
        split cluster's experts by Gaussian gates fitted to their pieces. ``"gpc"``: a GP
        classifier over the expert labels of the training observations' midpoints (the
        paper's gate; sklearn's ``GaussianProcessClassifier`` with a fixed RBF kernel, on
        300 points shared equally among the experts, at least one from each). The
        clusterer's densities describe the hits: an expert's free pieces up to
        ``nearest_hit_radius`` from its hits (a room seen through a door, the
        corridor wall's expert) lie where its cluster's density, thin along its wall, is
        below the threshold, and queries there were sent to experts with no data near
        them (grey fans behind the doors of the dense office). On the tuning data
        (``benchmarks/bench_tuning.py --only gating``, seed 100, 2026-12-02, when the
        coverage counted the cells along the segments, at threshold 0.5; the midpoints'
        count is compared under ``gating_threshold``) ``"coverage"`` / ``"clusterer"``
        (threshold 1e-3) give ACES held-out AUC
        0.963 / 0.962 with 2.3 / 5.2 experts per query trained on every 10th scan, 0.978
        / 0.977 with 13.8 / 11.8 trained on every scan; the dense office finds 100.0 /
        92.5 % of its far free cells at ECE 0.025 / 0.051 (6.0 / 6.3 experts per query),
        the dense paper's world 99.0 / 97.8 % at ECE 0.024 / 0.030; the sparse office and
        paper's world score the same (ECE 0.041 / 0.038 on the office). The clusterer's
        gate with no threshold (every expert within reach: 18.8 experts per query on
        ACES, 206 on ACES with every scan) scores as the coverage gate: the data were
        there, the gate skipped them. ``"coverage"`` and ``"clusterer"`` are read at
        predict time, as ``combiner`` and ``gating_threshold`` are: they can be changed
        with ``set_params`` between predictions. ``"gpc"`` is learned by :meth:`fit`, and
        set afterwards on a model fitted without it, prediction asks for a new fit.
    combiner : {"moe", "poe", "gpoe", "bcm", "rbcm"}, default="rbcm"
        Merging rule, see :mod:`skoccmap.combine`. The robust BCM is the default by
        measurement on tuning data (``benchmarks/bench_tuning.py --only combiner``: ACES,
        blocks protocol, every 10th scan, seed 100; the office and the paper's world,
        noise seed 100; with the coverage gate): ACES held-out AUC rbcm 0.963, bcm
        0.964, poe 0.964, gpoe 0.967, moe 0.955; walls found on the office (paper's
        world) rbcm 0.980 (0.903), bcm 0.975 (0.893), poe 0.975 (0.893), gpoe 0.973
        (0.889), moe 0.945 (0.856), at ECE 0.041 / 0.033 / 0.033 / 0.038 / 0.047 on the
        office. ``"gpoe"`` ranks ACES' held-out points best; rbcm finds the most walls,
        at an ECE still under 0.05. The mixture (``"moe"``, the
        paper's rule) lets an expert that knows nothing about a query (latent mean 0,
        probability 1/2) dilute one that does; the product rules weigh experts by their
        confidence.
    max_cluster_samples : int or None, default=4000
        The clusterer is fitted on at most this many hit points, drawn uniformly without
        replacement; every hit is then labelled by the clusterer's ``predict``. Clustering
        is the one step whose cost grows faster than linearly (collapsed Gibbs sweeps over
        all hits, and more of them as clusters crowd); a few thousand hits already fix the
        clusters' shapes, and the experts are cut to ``max_expert_size`` anyway. ``None``
        clusters all hits.
    min_expert_size : int, default=20
        Clusters with fewer observations are merged into the cluster with the nearest hit
        centroid (their gate is the sum of the merged clusters' responsibilities). A
        near-empty cluster learns nothing, and its broad predictive density would otherwise
        win the gate far from all hits. 1 disables merging.
    max_expert_size : int or None, default=400
        Clusters with more observations are split until every piece has at most this many:
        the cluster's hits are cut at the median along their principal axis, each hit
        weighted by the beam pieces that follow it (see ``piece_assignment``), and every
        piece stays with its hit (so an expert holds walls with the free space in front of
        them; a hit that alone carries more pieces stays whole). Experts are gated by
        Gaussians fitted to their pieces' midpoints within the cluster's gate. This bounds
        the cost of each expert, so fit time grows about linearly with the number of
        observations. ``None`` disables splitting (the paper's model; cubic cost in the
        cluster size). Sizes count the rows experts are fitted on (beam pieces). On the
        tuning data (``benchmarks/bench_tuning.py``) 200 / 400 / 800 give ACES held-out AUC
        0.944 / 0.951 / 0.947 with 312 / 157 / 79 experts (fit 9 / 17 / 49 s on one shared
        core) and office walls found 0.976 / 0.983 / 0.985: 800 costs about three times the
        fit of 400 for no better ranking.
    max_beam_length : float or None, default=1.0
        Beams longer than this (metres) are cut into pieces no longer than it after the
        assignment; ``piece_assignment`` says which expert each piece joins. Under the
        integral kernel a whole beam observes only the *average* of the latent function
        along it, which leaves the function free to stay high next to the wall the beam
        ended at: walls drawn thick and truly free cells marked occupied. ``None`` sets no
        bound; with ``beam_end_length=None``, ``piece_assignment="beam"`` and
        ``max_pieces_per_cell=None`` too, every beam stays whole and with its hit (with
        ``min_hit_frequency=None`` and ``hyperparameter_beam_length=None`` as well, the
        paper's beams; :mod:`skoccmap.experiment` builds the paper's whole model). Chosen with
        ``piece_assignment="beam"`` on tuning data (``benchmarks/bench_tuning.py``: the
        office and the paper's world with noise seed 100, and the ACES log;
        ``benchmarks/bench_quality.py`` reports other seeds and Intel). Whole beams mark
        16.0 % of the office's far free cells occupied and draw its walls 0.5 m thick (0.2 m
        with the defaults; ECE 0.35). With 0.35 m end pieces (``beam_end_length``) the
        office's phantoms are nearly gone without any bound (0.11 %), and no bound / 2 m / 1
        m / 0.5 m give office ECE 0.061 / 0.050 / 0.038 / 0.032 and ACES held-out AUC 0.918
        / 0.911 / 0.951 / 0.948 (whole beams 0.901); 0.5 m pieces find fewer walls (office
        0.974 against 0.983, paper's world 0.886 against 0.900) and need 1.5 times the
        experts of 1 m on ACES (231 against 157). (Each bound learned its own length scale
        in these numbers; the shared kernel is now learned on the cut of
        ``hyperparameter_beam_length`` whatever the bound.)
    beam_end_length : float or None, default=0.35
        Beams with a return are cut into pieces that halve in length towards their hit,
        down to this length (metres), before the ``max_beam_length`` pieces: the
        free-space evidence is finest next to the wall, which keeps the occupied band thin
        and the probabilities calibrated. On the tuning data (noise seed 100, 1 m pieces,
        scored by :func:`~skoccmap.metrics.map_quality`; ``benchmarks/bench_tuning.py``)
        ``None`` / 0.5 / 0.35 / 0.25 give ECE 0.095 / 0.056 / 0.038 / 0.024 on the office,
        0.042 / 0.029 / 0.023 / 0.019 on the paper's world and 0.104 / 0.046 / 0.021 /
        0.009 on the dense 3-D room, and find 99.5 / 99.1 / 98.3 / 97.3 %, 97.7 / 92.3 /
        90.0 / 86.1 % and 99.1 / 98.5 / 98.0 / 97.3 % of their walls: shorter end pieces
        pin free space closer to the wall, calibrated but with fewer of the cells that
        touch a wall marked occupied. 0.35 is the longest of these that keeps the ECE
        under 0.05 on every world. ACES held-out AUC is 0.951-0.952 with all four.
        ``None`` cuts beams into equal pieces only. No-return beams are cut the other
        way: pieces double in length away from the sensor, from ``max_beam_length``, so
        that a beam leaving the map for the sensor's maximum range costs a few rows.
    max_pieces_per_cell : int or None, default=4
        Free pieces that share a cell of ``piece_cell_size`` metres (by midpoint), a
        direction (bins of about 22.5 degrees, either way along the beam) and a length
        (within a factor of two) are near-duplicates: at most this many of them are kept,
        drawn at random, before the experts are formed; hits are all kept. On a dense log,
        where the robot passes the same corridors again and again, this cuts experts, fit
        and prediction, and keeps the learned length scale from following the density of
        the scans (see ``share_hyperparameters``). ``partial_fit`` counts the pieces
        earlier updates kept, so that a map built online keeps as many pieces as one fit
        on all its rows. ``None`` keeps every piece. On the tuning data
        (``benchmarks/bench_tuning.py --only max_pieces_per_cell``, seed 100) ``None`` /
        16 / 8 / 4 / 2 give ACES trained on every scan held-out AUC 0.9775 / 0.9769 /
        0.9731 / 0.9782 / 0.9761 with 13.8 / 12.5 / 7.9 / 7.6 / 5.3 experts per query
        (302 / 268 / 192 / 160 / 110 us per point, 1732 / 1607 / 1346 / 1087 / 743
        experts) and a length scale of 1.67 / 1.54 / 1.10 / 1.22 / 1.02 m; on every 10th
        scan 0.9622 / 0.9637 / 0.9645 / 0.9603 / 0.9589 (``None`` against 4 with random
        states 1 and 2, ``--datasets aces --random-state 1`` and ``2``: 0.9619 / 0.9643 and
        0.9556 / 0.9561) and 1.16 / 1.46 / 1.24 / 1.21
        / 1.10 m. The dense office finds 99.9 / 99.9 / 99.9 / 100.0 / 100.0 % of its walls
        at ECE 0.025 / 0.024 / 0.024 / 0.025 / 0.028 with 6.0 / 5.6 / 5.2 / 4.6 / 3.6
        experts per query; the sparse worlds barely change (office walls 98.0 % down to
        97.8 % at 2). 4 is the smallest cap that keeps every score of keeping all pieces.
    piece_cell_size : float, default=0.2
        Side (metres) of the cells ``max_pieces_per_cell`` counts pieces in. Coarser
        cells keep fewer pieces on dense logs and lose held-out AUC: on the tuning data
        (``benchmarks/bench_tuning.py --only piece_cell_size``, seed 100) 0.2 / 0.3 / 0.4
        / 0.6 give ACES 0.9603 / 0.9549 / 0.9554 / 0.9554 trained on every 10th scan, and
        0.9782 / 0.9732 / 0.9733 / 0.9720 with 7.6 / 5.6 / 4.3 / 4.0 experts per query
        trained on every scan; the simulated worlds change by at most 0.4 points of walls
        found.
    min_hit_frequency : float or None, default=0.2
        Leaves out of the experts' rows the hits that the free beams contradict: a hit
        whose 0.1 m cell counts ``hits / (hits + passes)`` below this and holds at most 3
        hits (hits and free rows counted as :class:`~skoccmap.baselines.FrequencyGridMap`
        counts them, over every row seen, :meth:`partial_fit` calls included) is taken for
        a transient obstacle -- someone walking by, a door that moved -- and marked in
        ``transient_hits_``; its beam stays free evidence, and the pieces that would have
        followed it follow the nearest hit that is not transient. An expert's probit is
        nearly a step at the default signal variance, so it meets every label it is
        given: three hits of a passer-by among dozens of beams draw a dark blob a length
        scale wide in ACES' corridors, where a counting grid, which weighs hits against
        passes, draws free space. 0.2 (about the free threshold of ROS' map_server, 0.196:
        a hit is left out where a counting grid would call its cell free) clears those
        corridors. A passer-by leaves a few hits per cell; a cell hit more than 3 times is
        lasting structure, however many beams cross it: where the passes of a log do not
        quite align, beams cross wall cells that other passes hit, and without that bound
        0.2 left out 11.6 % of ACES' hits trained on every scan, many of them on walls.
        ``None`` keeps every hit (the paper's model). Chosen on the tuning data
        (``benchmarks/bench_tuning.py --only min_hit_frequency``, seed 100): ``None`` /
        0.1 / 0.2 / 0.3 / 0.4 / 0.5 leave out 0 / 0.5 / 2.8 / 7.0 / 12.1 / 14.9 % of
        ACES' hits trained on every 10th scan, at held-out AUC 0.9603 / 0.9630 / 0.9683 /
        0.9688 / 0.9706 / 0.9670, and 0 / 5.1 / 7.0 / 8.2 / 9.1 / 9.5 % trained on every
        scan, at 0.9782 / 0.9776 / 0.9769 / 0.9780 / 0.9743 / 0.9701 (at 0.2 without the
        bound on the hits per cell: 11.6 %, 0.9745). The simulated worlds, where nothing
        moves, keep every score up to 0.2; from 0.3 up the office leaves out grazed wall
        hits (0.45 % at 0.3, 1.28 % at 0.4) and its phantoms rise from 0.01 to 0.03 %,
        and from 0.4 up the paper's world finds a point fewer of its walls. The held-out
        AUC of a dense log falls in part because of the protocol: its held-out hits include
        the people of the held-out scans (about a fifth of ACES' held-out hits lie in
        cells the training beams call transient). Look at ``transient_hits_`` to see
        what was left out. The cells are counted from the first row's: every row must lie
        within about 1e8 m of it in 2-D and 52 km in 3-D, and the free beams may pass at
        most 2**25 cells (0.34 km^2 in 2-D, 33 500 m^3 in 3-D); a ValueError says so
        otherwise (pass ``None`` for larger maps).
    piece_assignment : {"nearest_hit", "beam"}, default="nearest_hit"
        Which expert a free piece (of a beam cut by ``max_beam_length`` and
        ``beam_end_length``) joins. ``"beam"``: its beam's, i.e. its hit's (the paper's
        rule; a no-return beam's is that of its most similar return beam), so an expert's
        free space runs back along its beams to every pose that saw its walls, and the
        experts overlap wherever the robot drove. ``"nearest_hit"``: the expert of the
        nearest hit to the piece's midpoint within ``nearest_hit_radius`` that has room. A
        hit takes at most ``max_expert_size // 2`` pieces, the nearest that ask it; a piece
        whose nearest hit is full asks the next nearest, up to its 32 nearest, and keeps
        its beam's expert (as under ``"beam"``) when all are full or none lies within the
        radius. An expert then holds its walls with the free space around them: fewer
        experts reach a query, and those that do hold all the evidence near it. (Sending
        the pieces of a full hit back to their beams instead left experts tens of metres
        long on dense logs, where most hits are full.) Hits always join their own
        cluster's expert. The shared hyperparameters are learned on the experts of the
        paper's rule either way (see
        ``share_hyperparameters``). On the tuning data (``benchmarks/bench_tuning.py``, seed
        100) ``"nearest_hit"`` / ``"beam"`` give ACES held-out AUC 0.962 / 0.951 with 5.2 /
        10.6 experts per query (219 / 354 us per point); on the dense paper's world 0.44 /
        1.68 % phantoms, 97.8 / 95.5 % free found, 95.9 / 95.4 % walls found and ECE 0.030 /
        0.045; the sparse paper's world finds 90.3 / 90.0 % of its walls, the office 98.0 /
        98.3 % (ECE 0.038 / 0.037), the sparse 3-D room 93.5 / 93.3 %.
    nearest_hit_radius : float, default=2.0
        With ``piece_assignment="nearest_hit"``: a free piece further than this (metres)
        from every hit stays with its beam's hit. Without the bound, a hit at the edge
        of open space gathers all of it, and an expert is never split below one hit, so
        in a large hall one expert would grow without bound. On the tuning data
        (``benchmarks/bench_tuning.py``, seed 100) 1 / 2 / 4 m give ACES held-out AUC
        0.962 / 0.959 / 0.963 with 8.6 / 6.4 / 6.7 experts per query, and on the dense
        paper's world find 96.7 / 96.8 / 95.3 % of the walls with 0.49 / 0.42 / 0.47 %
        phantoms: the AUCs are within one fit's spread over random states, and 2 m
        consults the fewest experts (measured while the pieces of a full hit went back
        to their beams).
    share_hyperparameters : bool, default=True
        Learn the expert's kernel hyperparameters once and give every expert that fitted
        kernel with ``optimizer=None``. They maximise the summed EP log evidence of up to
        128 experts drawn at random (product-of-experts training of distributed GPs,
        Deisenroth & Ng 2015), each on its own piece of the map. On the tuning data
        (``benchmarks/bench_length_scale.py``: ACES, random states 0-3) 32 experts with every
        piece kept learn 1.65 / 2.08 / 1.49 / 1.32 m with every scan and 1.37 / 1.08 / 1.20
        / 1.17 m with every 10th; 64 with ``max_pieces_per_cell=4`` learn 1.12 / 1.00 /
        1.00 / 1.12 m and 1.13 / 1.18 / 1.03 / 1.03 m: the cap removes the drift with the
        density, the larger draw halves the spread. 128 instead of 64 (random states 0-5)
        move the length scale between every scan and every 10th by at most 22.6 % instead
        of 27.3 %, and resampling the experts' evidence curves of two ACES fits at each
        density (ad hoc) puts a move beyond 30 % at 7.7 % of draws with 64 and none of 400
        with 128
        (a sparse log with at most 128 experts learns on all of them), at twice the
        learning time (19.3 against 9.9 s with every scan). It costs most on small maps,
        where the learning dominates the fit. These are the experts of the paper's
        rule (``piece_assignment="beam"``: a cluster's walls with the whole beams that saw
        them), also when the fitted experts hold the pieces nearest to their hits
        (``"nearest_hit"``; see there). A hyperparameter that ends at a bound raises a
        ``ConvergenceWarning``, as does a length scale learned beyond the extent of the
        training data (the map would be nearly constant). The expert must have ``kernel``
        and ``optimizer`` parameters. ``False`` lets every expert learn its own (the paper's
        model): on the tuning data (``benchmarks/bench_tuning.py``) ACES held-out AUC drops
        from 0.951 to 0.859, 1.4 % of the office's far free cells are marked occupied (0.05
        % shared), the paper's world finds 0.49 of its walls (0.90 shared), and ``reach_``
        grows from 3.8 m to 307 m on ACES.
    hyperparameter_window : float or None, default=None
        Where the shared hyperparameters are learned (``share_hyperparameters=True``).
        ``None``: on the data of up to 128 experts (of the paper's rule) drawn at random. A
        radius in metres: on up to 128 windows of that radius, each centred on a random hit
        and holding at most ``max_expert_size`` rows drawn at random from the rows whose
        midpoint lies within it. A window covers the same area with the same number of rows
        however dense the scans, while an expert's data cover a smaller area as scans
        accumulate, so the length scale learned on windows does not follow the density of
        the scans. On the tuning data (``benchmarks/bench_tuning.py``, ACES) ``None`` /
        1.5 / 3 / 6 learn (with 32 pieces, every free piece kept) 1.25 / 0.54 / 0.72 /
        0.60 m with every 10th training scan and 1.15 / 0.48 / 0.59 / 0.65 m with every
        scan (changes of 9 / 12 / 22 / 9 %; the draw of pieces moves each by tens of
        percent), for held-out AUC 0.951 / 0.915 / 0.932 / 0.921 (every 10th) and 0.970 /
        0.970 / 0.972 / 0.972 (every scan); the office finds 98.3 / 99.5 / 98.9 / 99.1 % of
        its walls (ECE 0.038 / 0.056 / 0.041 / 0.043) and the paper's world 90.0 / 96.8 /
        93.5 / 90.5 %. The windows' shorter length scale extrapolates less into space the
        training scans barely saw, which costs held-out AUC on sparse scans: ``None`` stays
        the default.
    hyperparameter_beam_length : float or None, default=1.0
        The shared hyperparameters (``share_hyperparameters=True``) are learned on the beams
        cut at this length (metres), as ``max_beam_length`` cuts them (with the same
        ``beam_end_length`` and thinning), whatever bound the experts use. The EP evidence
        of cut beams depends on how finely they are cut: each piece is one more constraint
        on the latent function, and a longer length scale ties more constraints together, so
        finer pieces learn longer length scales (on the tuning log, ACES every 10th scan,
        random state 0, bounds of 0.5 / 1 / 2 m learned 1.51 / 1.13 / 0.76 m). Learned on
        one cut, the kernel no longer follows the bound, and the length scale of the finer
        cut ranked held-out points better with either bound there: 2 m pieces scored 0.9611
        with the length scale learned on 1 m pieces (1.245 m) against 0.9475 with their own
        (0.936 m), and 1 m pieces 0.9683 against 0.9587 (``benchmarks/README.md``; ad hoc,
        seed 100). The default equals ``max_beam_length``'s, so a default fit learns on the
        experts' own pieces; with another bound, the learning pieces are cut and kept beside
        the experts' (and updated by :meth:`partial_fit`). ``None`` learns on the experts'
        own pieces, whatever they are (the paper's model, which learns on whole beams).
    hyperparameter_growth : float or None, default=2.0
        :meth:`partial_fit` re-learns the shared hyperparameters, and refits every expert
        with them (as :meth:`refit_hyperparameters` does), whenever the training rows
        (beam pieces) have grown by this factor since they were last learned. Learned on
        the first batch only, the length scale fits a few scans of the map: replaying the
        first 120 training scans of Intel (``benchmarks/bench_online.py``, every 2nd scan,
        batches of 5, never re-learned; measured with 0.5 m end pieces, the default then)
        ends at 1.30 m against 1.16 m for one fit on the
        same scans, and held-out AUC 0.919 against 0.935; one
        :meth:`refit_hyperparameters` call at the end gives 0.937. With the default the
        same replay re-learns at 10, 20, 45 and 95 scans and ends at 1.20 m and AUC 0.924.
        On the first 200 scans (re-learned at 190 scans too) it ends at 0.90 m and AUC
        0.946, against 0.928 never re-learned, and 1.35 m and 0.932 for the fit. The
        length scale learned from 32 pieces (the number then, now up to 128 experts)
        varied by tens of percent from one draw to another, and the AUC with it: one fit of
        the 120 scans gave 0.929 to 0.935 over four seeds. With the 0.35 m end pieces the
        default replay ends 0.004 below the fit's AUC on both prefixes (0.932 against
        0.935 at 120 scans, 0.947 against 0.951 at 200). Re-learning at a fixed growth
        factor refits all experts a logarithmic number of times, i.e. a constant amortised
        cost per added row; 2 was not tuned.
        ``None`` keeps the first batch's hyperparameters. Only with
        ``share_hyperparameters=True`` and hyperparameters to learn.
    refit_fraction : float, default=0.5
        How :meth:`partial_fit` updates the experts a batch touches. An expert keeps the
        EP sites of the rows it has and takes its new rows by EP on their sites alone,
        with its current posterior at the new rows (jointly) as their prior
        (:func:`~skoccmap.ep.ep_append_sites`): about the cost of predicting the new
        rows, and the map shows every row at once. Held, the old sites drift from EP's
        fixed point on all rows; once the rows added so reach this fraction of the rows
        its last fit on all its rows settled, the expert is refitted (EP warm-started
        from all its sites). New experts and experts fitted on one class are refitted at
        once; an expert split off another holds that one's sites of its rows;
        :meth:`refit_hyperparameters` refits every expert. 0 refits every touched
        expert. Replaying the simulated office (tuning seed 100, 60 poses x 90 beams in
        batches of 6, :func:`~skoccmap.metrics.map_quality` on the cells seen so far;
        ``benchmarks/bench_online.py --office-steps``), 0.5 draws after every update the
        map of refitting every touched expert within 0.0002 in AUC, 0.01 points in
        phantom rate, 0.1 in free and walls found and 0.001 in ECE; 1 and 2 within
        0.0006, 0.12, 0.4 and 0.003. On the tuning log (ACES, every 2nd training scan
        replayed in batches of 5, ``benchmarks/bench_online.py --log``, CPU times) 0 /
        0.5 / 2 give a median update over the last half of 7.1 / 4.9 / 4.1 % of one
        fit's time, a log-log slope of update time against scans seen of 0.48 / 0.30 /
        0.27 and held-out AUC 0.9735 / 0.9735 / 0.9734 against the fit's 0.9745. 0.5
        keeps the held sites closest to EP's fixed point with an update under the 5 %
        target; no value meets the 0.2 slope target on ACES, where a batch's long beams
        reach more experts as the map grows (99 per update over the last half).
    gating_threshold : float or "auto", default="auto"
        Of the experts within reach of a query (see ``reach_tolerance``), those whose
        gating weight there is below this are skipped (the one with the largest weight is
        always kept); with ``gating="coverage"`` the threshold is relative to the largest
        weight at the query (0.35 skips the experts with less than 35 % of the data near
        the query of the best-covered one), with the other gates absolute. 0 consults every
        expert within reach. PoE, BCM and rBCM use the gate only to choose experts: under
        them a ``"clusterer"`` or ``"gpc"`` gate's threshold drops experts that hold data
        near the query, and the map jumps where they drop out (a seam of 0.24 in
        P(occupied) across the paper's world with ``combiner="bcm"`` and 1e-3, none with 0;
        :func:`skoccmap.experiment.make_models`). ``"auto"``: 0.35 with
        ``gating="coverage"``, 1e-3 with the other gates. With the coverage gate, on the
        tuning data (``benchmarks/bench_tuning.py --only gating_threshold``, seed 100) 0.5
        / 0.35 / 0.2 / 0.1 give ACES held-out AUC 0.9744 / 0.9755 / 0.9765 / 0.9772 with
        3.5 / 4.9 / 7.1 / 10.1 experts per query trained on every scan, 0.9665 / 0.9669 /
        0.9674 / 0.9671 with 1.5 / 1.8 / 2.3 / 3.0 trained on every 10th; the sparse
        office's ECE is 0.045 / 0.042 / 0.040 / 0.039, the dense office's 0.026 / 0.025 /
        0.025 / 0.025, and walls, free space and phantoms move by at most 0.2 % in the
        office and paper's world, sparse and dense. 0.35 keeps the scores of the gate that
        counted cells along the segments at 0.5 (ACES 0.9761 / 0.9673, office ECE 0.042)
        to 0.0006 of AUC with 4.9 experts per query against 7.1 on every ACES scan; that
        gate needed 0.6 to consult 5.4, at 0.9746. An absolute threshold on the coverage
        shares fails where dozens of experts overlap, every one of them holding a few
        percent of the data: 0.05 kept 2.2 experts per query on the full Intel log (B3)
        and scored held-out AUC 0.893 against the clusterer's 0.989. Higher relative
        thresholds lose the dense logs (ACES with every scan: 0.6 / 0.7 / 0.8 give 0.9734 /
        0.9721 / 0.9703 with 2.8 / 2.2 / 1.7 experts per query): where hundreds of poses
        saw a corridor its data fill several experts of about equal coverage.
    reach_tolerance : float, default=1e-2
        Sets the *reach* ``reach_``: the distance beyond which the fitted kernel between
        two points stays below ``reach_tolerance`` times its value at distance 0. An
        expert whose training segments all lie further than that from a query is not
        consulted there: every entry of its kernel row is below the tolerance (the
        integral kernel is an average of the point kernel along the segments), so it
        would predict close to its prior, which the product rules ignore and the mixture
        of experts should not be diluted by. For the squared-exponential kernel the reach
        is ``sqrt(2 ln(1 / reach_tolerance))`` length scales (3.03 at 1e-2). A query with
        no expert within reach gets the prior (probability 1/2, prior variance). On the
        tuning data (``benchmarks/bench_tuning.py``) 1e-1 / 1e-2 / 1e-3 give the same
        scores to four decimals (ACES held-out AUC 0.9513) with 8.36 / 8.61 / 8.72 experts
        consulted per ACES query.
    return_radius : float, default=0.1
        A beam is a *return* beam when a hit lies within this distance (metres) of its
        end; it then joins that hit's cluster. Other beams are *no-return* beams and join
        the cluster of the return beam most similar to them under the integral kernel
        with the expert kernel's length scale (the paper's rule; see Notes). Keep it a
        few cm above the ``free_margin`` of
        :func:`~skoccmap.observations.scans_to_observations` (0.05 m).
    kernel_cache_size : float, default=256
        Memory (MB) for the training kernel matrices of the experts, kept between
        :meth:`partial_fit` calls (their lower triangles, of the most recently fitted
        experts). The refit of a kept expert evaluates the kernel only between its new
        rows and all its rows, and reuses the rest: an update adds tens of rows to each of
        dozens of experts of hundreds, and evaluating the integral kernel over segments was
        about half the cost of a refit. Replaying Intel (``benchmarks/bench_online.py``)
        a refitted expert has a quarter of its rows new on median, and the kernel's share
        of the refits falls to about a quarter. A 400-row expert's triangle takes 0.64
        MB. Used
        only when the experts' kernel is fixed (``share_hyperparameters=True``, or an
        expert without optimiser); :meth:`refit_hyperparameters` empties it. Refits match
        those without the cache to rounding (entries of ``k(new, old)`` are evaluated with
        the new row first). 0 keeps none. Not pickled.
    layout : {"segments", "points"}, default="segments"
        How rows of ``X`` are read. ``"segments"``: ``[start, end]`` rows with ``2 * D``
        columns, as everywhere in skoccmap (odd column counts are rejected).
        ``"points"``: every row is a point with ``D = n_columns`` coordinates (e.g. free
        points sampled along beams); rows become zero-length segments before they reach
        the experts, and every free point joins the cluster of its nearest hit. Changed
        after :meth:`fit`, prediction asks for a new fit.
    n_jobs : int, default=None
        Experts fitted, and the terms of the shared hyperparameters' evidence computed, in
        parallel with :class:`sklearn.utils.parallel.Parallel`; honours
        ``joblib.parallel_config`` (e.g. ``backend="dask"``). Prediction runs the experts
        of each query chunk in as many threads. ``None`` means 1 unless in a joblib
        context.
    random_state : int, RandomState instance or None, default=None
        Seeds the clusterer and, drawn up front, one seed per expert; results do not
        depend on ``n_jobs``.
    verbose : int, default=0
        Progress of clustering, experts (k of K) and prediction; higher is chattier.

    Attributes
    ----------
    classes_ : ndarray of shape (2,)
        Class labels; ``classes_[1]`` is *occupied*.
    n_features_in_ : int
        Number of columns of ``X`` (``2 * D`` with segments, ``D`` with points).
    clusterer_ : estimator
        The fitted clusterer.
    observation_kind_ : ndarray of shape (n_samples,)
        ``HIT``, ``RETURN`` or ``NO_RETURN`` code (:mod:`skoccmap.observations`) per row;
        with ``layout="points"`` free points are marked ``RETURN`` (they follow that rule).
    transient_hits_ : ndarray of shape (n_samples,) of bool
        Hits left out of the experts as transient (see ``min_hit_frequency``); with
        :meth:`partial_fit`, every row seen, in order. A hit is judged by the rows seen
        when it arrives: later beams do not take out a hit already fitted.
    cluster_labels_ : ndarray of shape (n_samples,)
        Expert index (0 .. ``n_experts_ - 1``) of every training row's anchor hit: a
        hit's own expert; a beam's pieces join the experts ``piece_assignment`` says
        (with ``"beam"`` all of them this one).
    expert_cluster_ : ndarray of shape (n_experts,)
        Merged cluster (0 .. ``n_clusters_ - 1``) each expert's piece belongs to.
    cluster_ids_ : ndarray
        Labels of the clusterer that received hit points, in order.
    cluster_merge_ : ndarray of shape (n_cluster_ids,)
        Merged cluster of each of the clusterer's clusters (see ``min_expert_size``).
    n_clusters_ : int
        Number of clusters after merging small ones.
    n_experts_ : int
        Number of experts.
    experts_ : list of estimators
        Fitted experts. An :class:`~skoccmap.EPGaussianProcessClassifier` expert of
        one-class pieces (walls without the free space in front of them) is fitted on that
        class, with its kernel as given; another expert of them is a constant (prior
        variance, smoothed class frequency), to which ``combiner="rbcm"`` gives no weight.
    gating_ : estimator or None
        The fitted gating classifier when ``gating="gpc"`` and there are several experts.
    shared_kernel_ : kernel or None
        The kernel learned once when ``share_hyperparameters=True``.
    coverage_width_ : float
        Width of the coverage gate (``gating="coverage"``): the distance at which the
        experts' kernels fall to ``exp(-1/8)`` of their peak, half a length scale for the
        squared exponential; ``inf`` with ``reach_``.
    reach_ : float
        Distance within which an expert's training data can inform a query (see
        ``reach_tolerance``); ``inf`` when an expert's kernel does not decay or is not
        exposed as ``kernel_``, and then every expert is a candidate everywhere.
    touched_experts_ : ndarray of int
        Experts fitted, refitted or given new rows (see ``refit_fraction``) by the last
        :meth:`fit`, :meth:`partial_fit` or :meth:`refit_hyperparameters` call: all of
        them after a fit.

    See Also
    --------
    skoccmap.EPGaussianProcessClassifier : a single GP classifier on all data.
    skoccmap.combine : the merging rules.

    Notes
    -----
    No-return beams are compared with at most 1000 return beams drawn uniformly (a new
    sample for every few hundred no-return beams; all of them below that): the most
    similar of all return beams is a search whose cost grows with the square of the
    number of observations, while a uniform sample of return beams covers the same
    clusters.

    Prediction is local: ``fit`` indexes every expert's training segments on a grid
    (:class:`skoccmap._reach.ExpertReach`), and a point query looks up the experts with
    data within ``reach_`` of it (and possibly some within half a reach more, the grid's
    slack) in a table; only those are gated and consulted, and the merging rule sees only
    them (the mixture of experts renormalises its gate over them, the BCM counts them).
    Nothing of size (queries x experts) is formed, except by ``gating="gpc"``, whose
    classifier is dense over experts. Gating of a query segment uses its midpoint (a
    query cell is a zero-length segment, so its midpoint is the cell centre). Queries are
    predicted in chunks of nearby queries, sized by sklearn's ``working_memory``, and
    each expert predicts its queries of a chunk in one call.

    A fitted map keeps each expert's Cholesky factor (its lower triangle, ``4 n^2`` bytes
    for ``n`` rows), so that prediction needs no factorisation; the factors are most of a
    map's memory and of its pickle. Every 20th scan of the Intel log (16 368 rows, 121
    experts of up to 384 rows) pickles to 66 MB, 50 MB of them the experts'; the size
    grows with the rows times ``max_expert_size``.

    References
    ----------
    S. Kim and J. Kim, "Building occupancy maps with a mixture of Gaussian processes",
    ICRA 2012.

    M. P. Deisenroth and J. W. Ng, "Distributed Gaussian processes", ICML 2015.

    Examples
    --------
    >>> import numpy as np
    >>> from sklearn.cluster import KMeans
    >>> from sklearn.gaussian_process import GaussianProcessClassifier
    >>> from skoccmap import MixtureGPOccupancyMap
    >>> from skoccmap.observations import as_segments
    >>> rng = np.random.default_rng(0)
    >>> points = rng.uniform(-3, 3, size=(120, 2))
    >>> y = (np.abs(points[:, 0]) > 2).astype(int)
    >>> X = as_segments(points)
    >>> model = MixtureGPOccupancyMap(
    ...     clusterer=KMeans(2, n_init=3, random_state=0),
    ...     expert=GaussianProcessClassifier(), random_state=0).fit(X, y)
    >>> model.n_experts_
    2
    >>> model.predict(as_segments([[2.8, 0.0], [0.0, 0.0]]))
    array([1, 0])
    """

    _parameter_constraints: dict = {
        "clusterer": [HasMethods(["fit", "predict"]), None],
        "expert": [HasMethods(["fit", "latent_mean_and_variance"]), None],
        "gating": [StrOptions({"coverage", "clusterer", "gpc"})],
        "combiner": [StrOptions(set(COMBINERS))],
        "max_cluster_samples": [Interval(Integral, 2, None, closed="left"), None],
        "min_expert_size": [Interval(Integral, 1, None, closed="left")],
        "max_expert_size": [Interval(Integral, 2, None, closed="left"), None],
        "max_beam_length": [Interval(Real, 0, None, closed="neither"), None],
        "beam_end_length": [Interval(Real, 0, None, closed="neither"), None],
        "max_pieces_per_cell": [Interval(Integral, 1, None, closed="left"), None],
        "piece_cell_size": [Interval(Real, 0, None, closed="neither")],
        "min_hit_frequency": [Interval(Real, 0, 1, closed="both"), None],
        "piece_assignment": [StrOptions({"nearest_hit", "beam"})],
        "nearest_hit_radius": [Interval(Real, 0, None, closed="left")],
        "share_hyperparameters": ["boolean"],
        "hyperparameter_window": [Interval(Real, 0, None, closed="neither"), None],
        "hyperparameter_beam_length": [Interval(Real, 0, None, closed="neither"), None],
        "hyperparameter_growth": [Interval(Real, 1, None, closed="neither"), None],
        "refit_fraction": [Interval(Real, 0, None, closed="left")],
        "gating_threshold": [Interval(Real, 0, 1, closed="left"), StrOptions({"auto"})],
        "reach_tolerance": [Interval(Real, 0, 1, closed="neither")],
        "return_radius": [Interval(Real, 0, None, closed="left")],
        "kernel_cache_size": [Interval(Real, 0, None, closed="left")],
        "layout": [StrOptions({"segments", "points"})],
        "n_jobs": [
            Interval(Integral, None, -1, closed="right"),
            Interval(Integral, 1, None, closed="left"),
            None,
        ],
        "random_state": ["random_state"],
        "verbose": ["verbose"],
    }

    def __init__(
        self,
        clusterer=None,
        expert=None,
        *,
        gating="coverage",
        combiner="rbcm",
        max_cluster_samples=4000,
        min_expert_size=20,
        max_expert_size=400,
        max_beam_length=1.0,
        beam_end_length=0.35,
        max_pieces_per_cell=4,
        piece_cell_size=0.2,
        min_hit_frequency=0.2,
        piece_assignment="nearest_hit",
        nearest_hit_radius=2.0,
        share_hyperparameters=True,
        hyperparameter_window=None,
        hyperparameter_beam_length=1.0,
        hyperparameter_growth=2.0,
        refit_fraction=0.5,
        gating_threshold="auto",
        reach_tolerance=1e-2,
        return_radius=0.1,
        kernel_cache_size=256,
        layout="segments",
        n_jobs=None,
        random_state=None,
        verbose=0,
    ):
        self.clusterer = clusterer
        self.expert = expert
        self.gating = gating
        self.combiner = combiner
        self.max_cluster_samples = max_cluster_samples
        self.min_expert_size = min_expert_size
        self.max_expert_size = max_expert_size
        self.max_beam_length = max_beam_length
        self.beam_end_length = beam_end_length
        self.max_pieces_per_cell = max_pieces_per_cell
        self.piece_cell_size = piece_cell_size
        self.min_hit_frequency = min_hit_frequency
        self.piece_assignment = piece_assignment
        self.nearest_hit_radius = nearest_hit_radius
        self.share_hyperparameters = share_hyperparameters
        self.hyperparameter_window = hyperparameter_window
        self.hyperparameter_beam_length = hyperparameter_beam_length
        self.hyperparameter_growth = hyperparameter_growth
        self.refit_fraction = refit_fraction
        self.gating_threshold = gating_threshold
        self.reach_tolerance = reach_tolerance
        self.return_radius = return_radius
        self.kernel_cache_size = kernel_cache_size
        self.layout = layout
        self.n_jobs = n_jobs
        self.random_state = random_state
        self.verbose = verbose

    def __sklearn_tags__(self):
        tags = super().__sklearn_tags__()
        tags.classifier_tags.multi_class = False
        return tags

    def __getstate__(self):
        # The kernel cache only speeds up later partial_fit calls; a pickled map (and a
        # deep copy) goes without it.
        state = super().__getstate__()
        state.pop("_kernel_cache", None)
        return state

    # -- fit -------------------------------------------------------------------------

    @fit_or_unfitted
    @_fit_context(prefer_skip_nested_validation=False)
    def fit(self, X, y):
        """Cluster, assign, fit the experts and the gate.

        Parameters
        ----------
        X : array-like of shape (n_samples, 2 * D)
            Segment rows ``[start, end]``; hits are zero-length segments.
        y : array-like of shape (n_samples,)
            Two class labels; ``classes_[1]`` (the larger) marks hit points.

        Returns
        -------
        self : MixtureGPOccupancyMap
            Fitted estimator.
        """
        with non_finite_explained("observations"):
            X_in, (X, y) = X, validate_data(self, X, y, dtype=np.float64)
        warn_if_coarse_float32(X_in, X)
        check_classification_targets(y)
        classes, y_enc = np.unique(y, return_inverse=True)
        _check_two_classes(classes)
        return self._fit(X, y_enc, classes)

    def _fit(self, X, y_enc, classes):
        """``fit`` on validated rows (in ``layout``) and encoded labels (1 = occupied)."""
        X = _as_segment_rows(X, self.layout)
        _check_training_rows(X, y_enc, classes)
        self.classes_ = classes
        rng = check_random_state(self.random_state)
        start = time.perf_counter()
        self._fitted_with = {"layout": self.layout, "gating": self.gating}

        occupied = y_enc == 1
        if self.clusterer is None and occupied.sum() < 2:
            # Before DPGMMClusterer's own check, which names an array the user never passed.
            raise ValueError(
                f"{type(self).__name__} clusters the hit points (rows of the occupied class) "
                f"and needs at least 2 of them, got {int(occupied.sum())}."
            )
        expert = self._make_expert()
        labels, anchor = self._cluster_and_assign(X, occupied, expert, rng)
        _log(
            self.verbose,
            f"clustering done: {self.cluster_ids_.size} cluster(s), "
            f"{self.n_clusters_} after merging small ones ({time.perf_counter() - start:.1f} s)",
        )
        # Beams are cut after the assignment, and experts are sized by the rows they are
        # fitted on (pieces).
        pieces, source = _beam_pieces(
            X, self.observation_kind_, self.max_beam_length, self.beam_end_length
        )
        self.transient_hits_, self._cell_counts = self._transient_hits(X, occupied, None)
        _warn_if_every_hit_transient(self.transient_hits_[occupied], self.min_hit_frequency)
        if self.min_hit_frequency is not None:
            _log(
                self.verbose,
                f"{int(self.transient_hits_.sum())} of {int(occupied.sum())} hits left out as "
                f"transient (min_hit_frequency={self.min_hit_frequency})",
            )
        pieces, source = self._thinned(pieces, source, y_enc, rng, self.transient_hits_)
        d = X.shape[1] // 2
        hits, row_hit = X[occupied, :d], (np.cumsum(occupied) - 1)[anchor]
        piece_hit = self._piece_hits(
            pieces, y_enc[source], row_hit[source], hits, self.transient_hits_[occupied]
        )
        hit_expert = self._split_clusters(hits, labels[occupied], pieces, piece_hit)
        piece_expert = hit_expert[piece_hit]
        self.cluster_labels_ = hit_expert[row_hit]
        self.n_experts_ = int(self.expert_cluster_.size)
        self._kernel_cache = {}
        self._rng = rng
        self._hits, self._hit_expert, self._row_hit = hits, hit_expert, row_hit
        self._pieces, self._piece_y = pieces, y_enc[source]
        self._piece_expert, self._piece_hit = piece_expert, piece_hit
        self._piece_beam_hit = row_hit[source]
        self._learning = None
        if self._cuts_own_learning_pieces(expert):
            self._learning = self._learning_pieces(
                X, self.observation_kind_, y_enc, row_hit, self.transient_hits_, rng
            )
        self.experts_ = self._fit_experts(pieces, self._piece_y, piece_expert, expert, rng)
        _log(
            self.verbose,
            f"{self.n_experts_} expert(s) fitted ({time.perf_counter() - start:.1f} s)",
        )
        kernels = self._kernels()
        self.reach_ = self._reach(pieces, kernels)
        self.coverage_width_ = self._reach(pieces, kernels, _COVERAGE_TOLERANCE)
        self._reach_kernels = None if kernels is None else frozenset(kernels)
        self._reach_index = ExpertReach(pieces, piece_expert, self.n_experts_, self.reach_)
        self.gating_ = (
            self._fit_gpc_gate(pieces, piece_expert, rng) if self.gating == "gpc" else None
        )
        self._piece_settled = np.ones(pieces.shape[0], dtype=bool)
        self._learned_rows = pieces.shape[0]
        self.touched_experts_ = np.arange(self.n_experts_)
        return self

    def _transient_hits(self, X, occupied, counts):
        """Rows that are hits contradicted by the free rows (``min_hit_frequency``),
        counting these rows and those of ``counts`` (the rows seen before, or None), and
        the counts with these rows added (a new object: ``partial_fit`` commits it with the
        rest of its update)."""
        transient = np.zeros(X.shape[0], dtype=bool)
        if self.min_hit_frequency is None:
            return transient, counts
        d = X.shape[1] // 2
        counts = CellCounts(_HIT_CELL_SIZE, d) if counts is None else copy.copy(counts)
        counts.add(X, occupied)
        left_out = counts.transient(X[occupied, d:], self.min_hit_frequency, _MAX_TRANSIENT_HITS)
        transient[np.flatnonzero(occupied)[left_out]] = True
        return transient, counts

    def _thinned(self, pieces, source, y_enc, rng, transient, kept=None):
        """``pieces`` and ``source`` without the transient hits and the free pieces
        ``max_pieces_per_cell`` drops.

        One selection of ``pieces``: with millions of pieces, each copy costs hundreds of
        MB. Transient hits' pieces are hit pieces, which thinning never drops, so the
        order of the two rules does not matter.
        """
        keep = ~transient[source]
        if self.max_pieces_per_cell is not None:
            keep &= thin_free_pieces(
                pieces,
                y_enc[source] != 1,
                cell_size=self.piece_cell_size,
                max_per_cell=self.max_pieces_per_cell,
                random_state=rng,
                kept=kept,
            )
        if np.all(keep):
            return pieces, source
        return pieces[keep], source[keep]

    def _piece_hits(self, pieces, piece_y, anchor_hit, hits, transient_hit):
        """The hit (index into ``hits``) each piece follows, and so its expert.

        Transient hits (``transient_hit``, see ``min_hit_frequency``) take no pieces:
        pieces that would follow one follow the hit nearest to it that is not transient,
        so that no expert is left with the free space around a passer-by and no hit.

        ``anchor_hit`` is the anchor hit of each piece's row, which ``"beam"`` keeps.
        ``"nearest_hit"``: a free piece within ``nearest_hit_radius`` of a hit follows the
        hit nearest to its midpoint that has room, so that an expert holds the free space
        around its hits rather than whole beams across the map; one further out keeps its
        row's anchor, so that no hit gathers the open space around it (an expert is never
        split below one hit). A hit has room for ``max_expert_size // 2`` pieces (see
        :func:`_nearest_with_room`).
        """
        lasting = np.flatnonzero(~transient_hit)
        if lasting.size == 0:
            return anchor_hit
        tree = _hit_tree(hits[lasting])
        piece_hit = anchor_hit.copy()
        moved = transient_hit[piece_hit]
        if np.any(moved):
            piece_hit[moved] = lasting[tree.query(hits[piece_hit[moved]])[1]]
        if self.piece_assignment == "beam":
            return piece_hit
        free = np.flatnonzero(piece_y != 1)
        # A hit takes at most half an expert of pieces: with dense scans thousands lie
        # around one hit, and an expert is never split below one.
        cap = np.inf if self.max_expert_size is None else max(self.max_expert_size // 2, 1)
        chosen = _nearest_with_room(
            tree,
            _midpoints(pieces[free]),
            self.nearest_hit_radius,
            cap,
            _NEAREST_HITS,
            workers=_query_workers(self.n_jobs),
        )
        taken = chosen >= 0
        piece_hit[free[taken]] = lasting[chosen[taken]]
        return piece_hit

    # -- online mapping --------------------------------------------------------------

    @_fit_context(prefer_skip_nested_validation=False)
    def partial_fit(self, X, y, classes=None):
        """Add observations to the map, refitting only the experts they touch.

        The first call fits as :meth:`fit` does (a model fitted by :meth:`fit` takes later
        calls as well). Later calls, with the clusters, shared hyperparameters and reach of
        the map so far held fixed:

        1. The new hits join clusters by the clusterer's ``partial_fit`` (for
           :class:`~skoccmap.DPGMMClusterer`: seated by the posterior predictive, or in a
           new cluster where the Dirichlet process's new-table probability wins, as when
           the robot enters a new room); clusterers without ``partial_fit`` ``predict``
           existing clusters. A new cluster with fewer than ``min_expert_size`` rows joins
           the cluster with the nearest hit centroid; others get a new expert.
        2. Within a split cluster a hit joins the piece whose gate weighs it most. Beams
           follow their hit as in :meth:`fit` (a return beam the hit at its end, among old
           and new hits; a no-return beam the hit of the most similar return beam of the
           batch, or the hit nearest to its midpoint if the batch has none) and are cut
           into the same pieces.
        3. Experts that received rows take them, in parallel. Most add them to their
           fit, EP running on the new rows' sites alone; an expert is refitted once the
           rows added so reach ``refit_fraction`` of those its last fit settled, and at
           once when new, split or fitted on one class. An expert grown past
           ``max_expert_size`` is bisected on its hits as clusters are in :meth:`fit`.
           A refit EP expert starts from the site parameters it has (zeros for new
           rows): EP reaches the same fixed point in fewer sweeps.
        4. The gates of the touched clusters, the clusterer's predictive, the reach and
           the spatial index of prediction are updated.

        Untouched experts stay the same objects. The training rows (cut into pieces)
        are kept, so memory grows linearly with the data; :meth:`refit_hyperparameters`
        re-learns the shared hyperparameters from all of them, and so does an update
        that grows the rows by ``hyperparameter_growth`` since they were last learned
        (it then refits every expert instead of step 3's). Parameters changed by
        ``set_params`` between calls apply to the later batches, except ``expert`` (taken
        up by the next re-learn of shared hyperparameters, which refits every expert with
        it, or else the next :meth:`fit`), ``clusterer`` (the fitted ``clusterer_`` serves
        until the next :meth:`fit`) and ``layout`` or a ``"gpc"`` gate (refused: they
        shape what :meth:`fit` builds).

        Parameters
        ----------
        X : array-like of shape (n_samples, 2 * D)
            New segment rows; ``n_features_in_`` is fixed by the first call.
        y : array-like of shape (n_samples,)
            Labels from ``classes``. After the first call one class is fine (a batch of
            free space only), and so is an empty batch (nothing is updated).
        classes : array-like of shape (2,), default=None
            All labels, needed on the first call unless ``y`` holds both; later calls may
            omit it, or must repeat ``classes_``.

        Returns
        -------
        self : MixtureGPOccupancyMap
            The updated estimator; ``touched_experts_`` lists the experts updated by the
            last call.

        Examples
        --------
        >>> import numpy as np
        >>> from sklearn.gaussian_process.kernels import ConstantKernel
        >>> from skoccmap import EPGaussianProcessClassifier, IntegralKernel
        >>> from skoccmap import MixtureGPOccupancyMap
        >>> from skoccmap.datasets import make_office_scans
        >>> scans = make_office_scans(random_state=0).scans
        >>> expert = EPGaussianProcessClassifier(
        ...     ConstantKernel(100.0, "fixed") * IntegralKernel(1.0, "fixed"), optimizer=None)
        >>> model = MixtureGPOccupancyMap(expert=expert, random_state=0)
        >>> for first in range(0, 12, 4):
        ...     X, y, _ = scans[first : first + 4].to_observations()
        ...     model = model.partial_fit(X, y, classes=[0, 1])
        >>> model.n_features_in_, bool(model.touched_experts_.size < model.n_experts_)
        (4, True)
        """
        if not hasattr(self, "_pieces"):
            # A first call that raises leaves the model unfitted, as fit does.
            with unfitted_on_error(self):
                with non_finite_explained("observations"):
                    X_in, (X, y) = X, validate_data(self, X, y, dtype=np.float64)
                warn_if_coarse_float32(X_in, X)
                check_classification_targets(y)
                present = np.unique(y)
                if present.size == 1:
                    raise ValueError(
                        "The first call to partial_fit needs both classes in y: hit points to "
                        f"cluster and beams (free space); y holds {present.tolist()} only. "
                        "Later calls may hold one class."
                    )
                if classes is None:
                    classes = present
                classes = np.unique(np.asarray(classes))
                _check_two_classes(classes)
                check_known_labels(y, classes)
                return self._fit(X, np.searchsorted(classes, y), classes)
        check_is_fitted(self)
        X_in, (X, y) = X, validate_queries(self, X, y)
        warn_if_coarse_float32(X_in, X)
        if X.shape[0] == 0:
            # A batch whose readings all failed (zeros): nothing to learn, nothing touched.
            self.touched_experts_ = np.empty(0, dtype=np.intp)
            return self
        check_classification_targets(y)
        if classes is not None and not np.array_equal(np.unique(classes), self.classes_):
            raise ValueError(
                f"classes={np.unique(classes).tolist()} differs from the classes of the "
                f"first call, {self.classes_.tolist()}."
            )
        check_known_labels(y, self.classes_)
        self._check_fitted_with()
        X, y_enc = _as_segment_rows(X, self.layout), np.searchsorted(self.classes_, y)
        # The checks of the first call: a later batch with its labels reversed (beams as
        # hits) or in millimetres would otherwise join the map without a word.
        _check_training_rows(X, y_enc, self.classes_)
        self._update(X, y_enc)
        return self

    def refit_hyperparameters(self):
        """Re-learn the shared hyperparameters on all data so far and refit every expert.

        :meth:`partial_fit` keeps the hyperparameters learned by the first fit, or last
        re-learned when the rows grew by ``hyperparameter_growth``; this learns them again
        now as :meth:`fit` does (from up to 128 experts' pieces), refits all experts
        (warm-started from their sites), and updates the reach and the spatial index.
        Clusters and pieces stay.

        Returns
        -------
        self : MixtureGPOccupancyMap
            The refitted estimator (``touched_experts_`` lists every expert).

        Examples
        --------
        >>> import numpy as np
        >>> from skoccmap import MixtureGPOccupancyMap
        >>> from skoccmap.datasets import make_paper_scans
        >>> data = make_paper_scans(random_state=0)
        >>> model = MixtureGPOccupancyMap(max_expert_size=300, random_state=0)
        >>> model = model.fit(data.X, data.y).refit_hyperparameters()
        >>> model.touched_experts_.size == model.n_experts_
        True
        """
        check_is_fitted(self)
        if not self.share_hyperparameters:
            raise ValueError("refit_hyperparameters needs share_hyperparameters=True.")
        rows = _groups(self._piece_expert, self.n_experts_)
        self._relearn_shared(rows, self.experts_, rows, np.arange(self.n_experts_))
        self._update_index()
        return self

    def _relearn_shared(self, rows, old_experts, old_rows, origin):
        """Learn the shared kernel on the training state and refit every expert with it.

        ``old_experts``, ``old_rows`` and ``origin`` give each expert its warm start, as in
        :meth:`_refit_experts`.
        """
        expert = self._make_expert()
        # The kept kernel matrices are of the old hyperparameters.
        self._kernel_cache = {}
        base = self._learn_shared(rows, expert, self._rng)
        self._expert_base = base
        self._learned_rows = self._pieces.shape[0]
        everyone = np.arange(self.n_experts_)
        self.experts_ = self._refit_experts(
            everyone, rows, self._piece_y, old_experts, old_rows, origin
        )
        self._piece_settled = np.ones(self._pieces.shape[0], dtype=bool)
        self.touched_experts_ = everyone

    def _relearns_at(self, n_rows):
        """Whether an update to ``n_rows`` training rows re-learns the shared kernel."""
        if self.hyperparameter_growth is None or not self.share_hyperparameters:
            return False
        if not _learns_kernel(self._make_expert()):
            return False
        return n_rows >= self.hyperparameter_growth * self._learned_rows

    def _new_hit_clusters(self, hits):
        """Clusterer label of each new hit (the clusterer learns them when it can)."""
        if hasattr(self.clusterer_, "partial_fit"):
            self.clusterer_.partial_fit(hits)
            raw = getattr(self.clusterer_, "labels_", None)
            if raw is not None and len(raw) == hits.shape[0]:
                return np.asarray(raw)
        return np.asarray(self.clusterer_.predict(hits))

    def _new_anchors(self, X, occupied, all_hits, n_old_hits, rng):
        """Observation kinds of new rows and the (global) hit index each row follows."""
        d = X.shape[1] // 2
        n = X.shape[0]
        kinds = np.full(n, NO_RETURN, dtype=np.intp)
        kinds[occupied] = HIT
        anchor = np.full(n, -1, dtype=np.intp)
        anchor[occupied] = n_old_hits + np.arange(int(occupied.sum()))
        beams = np.flatnonzero(~occupied)
        radius = np.inf if self.layout == "points" else self.return_radius
        if beams.size:
            ends = X[beams, d:]
            if np.isfinite(radius):
                # Only the hits near the batch: the tree costs what the batch covers.
                lo, hi = ends.min(axis=0) - radius, ends.max(axis=0) + radius
                near = np.flatnonzero(np.all((all_hits >= lo) & (all_hits <= hi), axis=1))
            else:
                near = np.arange(all_hits.shape[0])
            if near.size:
                dist, idx = _hit_tree(all_hits[near]).query(ends, distance_upper_bound=radius)
                is_ret = dist <= radius
                kinds[beams[is_ret]] = RETURN
                anchor[beams[is_ret]] = near[idx[is_ret]]
        is_nr = kinds == NO_RETURN
        if np.any(is_nr):
            is_ret = kinds == RETURN
            if np.any(is_ret):
                anchor[is_nr] = _assign_no_return(
                    X[is_nr],
                    X[is_ret],
                    anchor[is_ret],
                    self._similarity_length_scale(self._make_expert(), d),
                    max_references=_NO_RETURN_REFERENCES,
                    random_state=rng,
                    n_jobs=self.n_jobs,
                )
            else:
                anchor[is_nr] = _hit_tree(all_hits).query(_midpoints(X[is_nr]))[1]
        return kinds, anchor

    def _update(self, X, y_enc):
        """One :meth:`partial_fit` step after the first (see there)."""
        start = time.perf_counter()
        rng = self._rng
        d = X.shape[1] // 2
        occupied = y_enc == 1
        new_hits = X[occupied, :d]
        n_old_hits, n_old_pieces = self._hits.shape[0], self._pieces.shape[0]
        n_old_experts = self.n_experts_
        all_hits = np.vstack([self._hits, new_hits])
        # First, as it changes nothing: a batch it refuses (a reading far off the map)
        # leaves the clusterer and the random state as they were.
        transient, cell_counts = self._transient_hits(X, occupied, self._cell_counts)

        # 1. Cluster and expert of each new hit.
        raw = self._new_hit_clusters(new_hits) if new_hits.shape[0] else np.empty(0, int)
        kinds, anchor = self._new_anchors(X, occupied, all_hits, n_old_hits, rng)
        rows_per_hit = np.bincount(anchor[anchor >= n_old_hits] - n_old_hits, minlength=raw.size)
        hit_expert, expert_cluster, cluster_ids, cluster_merge = self._new_hit_experts(
            new_hits, raw, rows_per_hit
        )
        n_clusters = int(cluster_merge.max()) + 1 if cluster_merge.size else 1
        all_hit_expert = np.concatenate([self._hit_expert, hit_expert])

        # 2. Pieces of the new rows, appended to the training state. Old pieces keep
        # their hit even where a new hit lies nearer.
        pieces, source = _beam_pieces(X, kinds, self.max_beam_length, self.beam_end_length)
        pieces, source = self._thinned(
            pieces, source, y_enc, rng, transient, kept=self._pieces[self._piece_y != 1]
        )
        hit_rows = np.concatenate([self.observation_kind_, kinds]) == HIT
        transient_hit = np.concatenate([self.transient_hits_, transient])[hit_rows]
        _warn_if_every_hit_transient(transient_hit, self.min_hit_frequency)
        new_piece_hit = self._piece_hits(
            pieces, y_enc[source], anchor[source], all_hits, transient_hit
        )
        learning = self._learning
        if learning is not None:
            new = self._learning_pieces(
                X, kinds, y_enc, anchor, transient, rng, kept=learning[0][learning[1] != 1]
            )
            learning = tuple(np.concatenate(pair) for pair in zip(learning, new, strict=True))
        all_pieces = np.vstack([self._pieces, pieces])
        piece_y = np.concatenate([self._piece_y, y_enc[source]])
        piece_hit = np.concatenate([self._piece_hit, new_piece_hit])
        piece_beam_hit = np.concatenate([self._piece_beam_hit, anchor[source]])
        piece_expert = np.concatenate([self._piece_expert, all_hit_expert[new_piece_hit]])
        row_hit = np.concatenate([self._row_hit, anchor])
        touched = set(np.unique(all_hit_expert[new_piece_hit]).tolist())

        # 3. Experts grown past max_expert_size: bisected.
        rows = self._split_grown(
            touched, expert_cluster, all_hits, all_hit_expert, piece_expert, piece_hit
        )
        n_experts = len(expert_cluster)
        # A split can leave an expert exactly its old rows (the new ones all split off):
        # it is unchanged, not touched.
        old_groups = _groups(self._piece_expert, n_old_experts)
        touched = {
            k for k in touched if k >= n_old_experts or not np.array_equal(rows[k], old_groups[k])
        }

        # 4. Experts numbered cluster by cluster (a cluster's experts are contiguous, in
        # the order of its gate's columns); untouched clusters keep their order.
        expert_cluster = np.asarray(expert_cluster, dtype=np.intp)
        order = np.lexsort((np.arange(n_experts), expert_cluster))
        renumber = np.empty(n_experts, dtype=np.intp)
        renumber[order] = np.arange(n_experts)
        all_hit_expert = renumber[all_hit_expert]
        piece_expert = renumber[piece_expert]
        row_expert = all_hit_expert[row_hit]
        rows = [rows[k] for k in order]
        touched = np.sort(renumber[sorted(touched)])
        expert_cluster = expert_cluster[order]
        first_expert = np.searchsorted(expert_cluster, np.arange(n_clusters))
        old_experts = [None] * n_experts
        for k in range(n_old_experts):
            old_experts[renumber[k]] = self.experts_[k]
        # Rows each old expert was fitted on (all of its pieces, in order), by new number.
        old_rows = [np.empty(0, np.intp)] * n_experts
        for k in range(n_old_experts):
            old_rows[renumber[k]] = old_groups[k]
        # Experts split off an old one start from its sites as well.
        origin = np.arange(n_experts)
        for k in touched:
            first_piece = rows[k][0] if rows[k].size else 0
            if old_experts[k] is None and first_piece < n_old_pieces:
                origin[k] = renumber[self._piece_expert[first_piece]]

        # 5. Gates of the touched clusters.
        piece_gates = _piece_gates(
            expert_cluster,
            n_clusters,
            all_pieces,
            piece_expert,
            clusters=np.unique(expert_cluster[touched]),
            gates=self._piece_gates,
        )

        # 6. Refit the touched experts that are due, and add the new rows to the others
        # (in parallel, warm-started); or refit every expert with re-learned
        # hyperparameters once the data have grown enough (after the commit).
        relearn = self._relearns_at(all_pieces.shape[0])
        experts = old_experts
        piece_settled = np.concatenate([self._piece_settled, np.zeros(pieces.shape[0], bool)])
        if not relearn:
            due = self._due(touched, rows, old_experts, old_rows, origin, piece_settled)
            experts = self._refit_experts(
                touched, rows, piece_y, old_experts, old_rows, origin, all_pieces, due
            )
            for k in touched[due]:
                piece_settled[rows[k]] = True

        # Commit.
        self.cluster_ids_, self.cluster_merge_ = cluster_ids, cluster_merge
        self.n_clusters_, self.n_experts_ = n_clusters, n_experts
        self.expert_cluster_, self._first_expert = expert_cluster, first_expert
        self._piece_gates = piece_gates
        self.experts_ = experts
        self.touched_experts_ = touched
        self.observation_kind_ = np.concatenate([self.observation_kind_, kinds])
        self.transient_hits_ = np.concatenate([self.transient_hits_, transient])
        self._cell_counts = cell_counts
        self.cluster_labels_ = row_expert
        self._hits, self._hit_expert = all_hits, all_hit_expert
        self._row_hit = row_hit
        self._pieces, self._piece_y = all_pieces, piece_y
        self._piece_expert, self._piece_hit = piece_expert, piece_hit
        self._piece_beam_hit = piece_beam_hit
        self._learning = learning
        self._piece_settled = piece_settled
        if relearn:
            self._relearn_shared(rows, old_experts, old_rows, origin)
            self._update_index()
        else:
            previous = np.full(n_experts, -1, dtype=np.intp)
            previous[renumber[:n_old_experts]] = np.arange(n_old_experts)
            self._update_index(touched, previous)
        if self.gating == "gpc":
            self.gating_ = self._fit_gpc_gate(all_pieces, piece_expert, rng)
        # A gpc gate not refitted with this update no longer knows the experts.
        self._fitted_with = {"layout": self.layout, "gating": self.gating}
        _log(
            self.verbose,
            f"partial_fit: {touched.size} of {n_experts} expert(s) updated "
            f"({time.perf_counter() - start:.1f} s)",
        )

    def _new_hit_experts(self, new_hits, raw, rows_per_hit):
        """Cluster and expert of each new hit of :meth:`_update`, from its clusterer
        label ``raw`` and the number of rows it anchors ``rows_per_hit``.

        A label the clusterer gave before keeps its cluster. An unseen one becomes a new
        cluster with an expert of its own when its hits anchor ``min_expert_size`` rows,
        and otherwise joins the old cluster whose hits' centroid is nearest. A hit of a
        cluster split into several experts joins the one whose piece gate weighs it most.

        Returns the new hits' experts (new experts numbered after the old ones), the
        cluster of every expert (a list), and the updated ``cluster_ids_`` and
        ``cluster_merge_``.
        """
        n_old_clusters = self.n_clusters_
        pos = np.searchsorted(self.cluster_ids_, raw).clip(0, self.cluster_ids_.size - 1)
        known = self.cluster_ids_[pos] == raw
        hit_cluster = np.where(known, self.cluster_merge_[pos], -1)
        cluster_ids, cluster_merge = self.cluster_ids_, self.cluster_merge_
        expert_cluster = list(self.expert_cluster_)
        hit_expert = np.full(raw.size, -1, dtype=np.intp)
        unseen = np.unique(raw[~known])
        if unseen.size:
            old_cluster = self.expert_cluster_[self._hit_expert]
            counts = np.bincount(old_cluster, minlength=n_old_clusters)
            sums = [
                np.bincount(old_cluster, weights=coordinate, minlength=n_old_clusters)
                for coordinate in self._hits.T
            ]
            centroids = np.column_stack(sums) / np.maximum(counts, 1)[:, None]
            merge = []
            for u in unseen:
                mine = np.flatnonzero(raw == u)
                if rows_per_hit[mine].sum() >= self.min_expert_size:
                    c = n_old_clusters + sum(m >= n_old_clusters for m in merge)
                    hit_expert[mine] = len(expert_cluster)
                    expert_cluster.append(c)
                else:
                    dist = np.linalg.norm(centroids - new_hits[mine].mean(axis=0), axis=1)
                    c = int(np.argmin(np.where(counts > 0, dist, np.inf)))
                merge.append(c)
                hit_cluster[mine] = c
            cluster_ids = np.concatenate([self.cluster_ids_, unseen])
            cluster_merge = np.concatenate([self.cluster_merge_, merge])
            order = np.argsort(cluster_ids, kind="stable")
            cluster_ids, cluster_merge = cluster_ids[order], cluster_merge[order]
        for c in np.unique(hit_cluster[hit_expert < 0]):
            mine = np.flatnonzero((hit_cluster == c) & (hit_expert < 0))
            gate = self._piece_gates[c]
            pick = 0 if gate is None else np.argmax(gate.predict_proba(new_hits[mine]), axis=1)
            hit_expert[mine] = self._first_expert[c] + pick
        return hit_expert, expert_cluster, cluster_ids, cluster_merge

    def _split_grown(self, touched, expert_cluster, hits, hit_expert, piece_expert, piece_hit):
        """Bisect the hits of each ``touched`` expert grown past ``max_expert_size``
        (weighted by the pieces they anchor), as :func:`_split_hits` does in ``fit``.

        Updates in place: the parts after the first become new experts, appended to
        ``expert_cluster`` (in their expert's cluster) and added to ``touched``, and
        ``hit_expert`` and ``piece_expert`` follow them. Returns the pieces of each expert.
        """
        rows = _groups(piece_expert, len(expert_cluster))
        if self.max_expert_size is None:
            return rows
        n_experts = len(expert_cluster)
        for k in sorted(touched):
            if rows[k].size <= self.max_expert_size:
                continue
            mine = np.flatnonzero(hit_expert == k)
            weight = np.bincount(piece_hit[rows[k]], minlength=hits.shape[0])[mine]
            parts = _bisect(hits[mine], self.max_expert_size, weight)
            for part in parts[1:]:
                hit_expert[mine[part]] = len(expert_cluster)
                touched.add(len(expert_cluster))
                expert_cluster.append(expert_cluster[k])
            if len(parts) > 1:
                piece_expert[rows[k]] = hit_expert[piece_hit[rows[k]]]
        if len(expert_cluster) > n_experts:
            rows = _groups(piece_expert, len(expert_cluster))
        return rows

    def _due(self, touched, rows, old_experts, old_rows, origin, settled):
        """Which ``touched`` experts :meth:`partial_fit` refits (see ``refit_fraction``).

        An expert whose rows have EP sites from the expert it comes from (itself, or the
        one it was split off) takes its other rows by EP on their sites alone, unless the
        rows not settled by a fit on all of an expert's rows reach ``refit_fraction`` of
        those settled: then, as for a new expert, a count or an expert fitted on one
        class, it is refitted.
        """
        due = np.ones(len(touched), dtype=bool)
        for i, k in enumerate(touched):
            source = old_experts[origin[k]]
            if getattr(source, "n_classes_", 0) != 2 or not hasattr(source, "site_nu_"):
                continue
            if np.ptp(source.y_train_) == 0:
                continue  # fitted on one class: its saturated sites cannot hold new rows
            split = not _appended(k, rows, old_rows, origin)
            if split and not _takes_kernel_matrix(self._expert_base):
                continue  # the expert learns its kernel: a split one is fitted anyway
            n_settled = np.count_nonzero(settled[rows[k]])
            due[i] = rows[k].size - n_settled >= self.refit_fraction * max(n_settled, 1)
        return due

    def _refit_experts(
        self, touched, rows, piece_y, old_experts, old_rows, origin, pieces=None, due=None
    ):
        """Experts list with the ``touched`` ones fitted on their rows, in parallel.

        Expert ``k`` starts from the sites its ``origin`` expert had on the same pieces
        (``old_rows`` are the pieces each old expert was fitted on), zeros elsewhere. Those
        ``due`` (all by default) run EP on all their sites; the others hold the sites they
        have and run EP on their new rows' sites alone.
        """
        pieces = self._pieces if pieces is None else pieces
        due = np.ones(len(touched), dtype=bool) if due is None else due
        base = self._expert_base
        seeds = self._rng.randint(np.iinfo(np.int32).max, size=len(touched))
        has_seed = "random_state" in base.get_params()

        def prepared(j):
            est = clone(base)
            if has_seed:
                est.set_params(random_state=int(seeds[j]))
            return est

        def sites(k):
            # The origin's sites of k's rows (zeros for rows it had not), and which it had.
            old = old_experts[origin[k]]
            tau = getattr(old, "site_precision_", None)
            source = old_rows[origin[k]]
            if tau is None or np.shape(tau) != source.shape:
                return None, None
            where = np.searchsorted(source, rows[k]).clip(0, max(source.size - 1, 0))
            found = source[where] == rows[k]
            return (
                np.where(found, tau[where], 0.0),
                np.where(found, old.site_nu_[where], 0.0),
            ), found

        cache = getattr(self, "_kernel_cache", {})
        keep = self.kernel_cache_size > 0

        def previous(k):
            # The old expert's kernel matrix, and the row of it each row of k had.
            lower = cache.get(old_experts[origin[k]]) if keep else None
            source = old_rows[origin[k]]
            if lower is None or lower.size != source.size * (source.size + 1) // 2:
                return None
            where = np.searchsorted(source, rows[k]).clip(0, max(source.size - 1, 0))
            return lower, np.where(source[where] == rows[k], where, -1)

        # Experts not due whose rows were only appended to an old binary EP expert take
        # them on its factor; the others are fitted, holding the sites they have.
        appends = [
            not due[j]
            and hasattr(old_experts[k], "_absorbed")
            and getattr(old_experts[k], "n_classes_", 0) == 2
            and _appended(k, rows, old_rows, origin)
            for j, k in enumerate(touched)
        ]

        def task(j, k):
            # A call with its arguments bound; wrapped by ``delayed`` only for the workers.
            start, found = sites(k)
            if appends[j]:
                return partial(
                    _append_rows,
                    old_experts[k],
                    prepared(j),
                    pieces[rows[k]],
                    piece_y[rows[k]],
                    old_rows[k].size,
                    start,
                    previous=previous(k),
                    keep_kernel=keep,
                )
            return partial(
                _fit_expert,
                prepared(j),
                pieces[rows[k]],
                piece_y[rows[k]],
                start,
                previous=previous(k),
                keep_kernel=keep,
                hold=None if due[j] else found,
            )

        # Appending rows costs about a prediction, less than shipping the expert and its
        # kernel matrix to a worker and back: this process appends while the workers
        # refit the experts that are due.
        tasks = [task(j, k) for j, k in enumerate(touched)]
        here = [i for i, local in enumerate(appends) if local]
        away = [i for i, local in enumerate(appends) if not local]
        fits = Parallel(
            n_jobs=self.n_jobs, verbose=max(self.verbose - 1, 0), return_as="generator"
        )(delayed(tasks[i])() for i in away)
        results = [None] * len(tasks)
        for i in here:
            results[i] = tasks[i]()
        for i, result in zip(away, fits, strict=True):
            results[i] = result
        _warn_once_each([w for _, w, _ in results], len(touched))
        experts = list(old_experts)
        for k, (est, _, _) in zip(touched, results, strict=True):
            experts[k] = est
        self._cache_kernels(
            [est for est, _, _ in results], [lower for _, _, lower in results], experts
        )
        return experts

    def _cache_kernels(self, fitted, lowers, experts):
        """Keep the kernel matrices of the ``fitted`` experts, within ``kernel_cache_size``.

        The cache maps an expert (the object) to its packed matrix, the most recently
        fitted last; matrices of experts no longer in ``experts`` (refitted or split) are
        dropped, then the oldest until the cache fits its budget.
        """
        cache = self.__dict__.setdefault("_kernel_cache", {})
        for est, lower in zip(fitted, lowers, strict=True):
            if lower is not None:
                cache.pop(est, None)
                cache[est] = lower
        alive = {id(est) for est in experts}
        for est in [est for est in cache if id(est) not in alive]:
            del cache[est]
        budget = self.kernel_cache_size * 2**20
        total = sum(lower.nbytes for lower in cache.values())
        while cache and total > budget:
            total -= cache.pop(next(iter(cache))).nbytes

    def _update_index(self, touched=None, previous=None):
        """Reach and spatial index of prediction from all training pieces.

        With ``touched`` (experts whose pieces changed) and ``previous`` (every expert's
        number in the current index, -1 if new), and the experts' kernels as when the
        reach was found, the reach stays and only the touched experts' entries of the
        index are recomputed (:meth:`ExpertReach.updated`, equal to a rebuild on the same
        grid). The reach is probed on a grid scaled by the data's extent, so a rebuild
        from scratch could move it by a few percent as the map grows; any value from the
        probes bounds the kernel below the tolerance beyond it.
        """
        kernels = self._kernels()
        index = getattr(self, "_reach_index", None)
        if (
            touched is not None
            and index is not None
            and np.isfinite(self.reach_)
            and kernels is not None
            and frozenset(kernels) == getattr(self, "_reach_kernels", None)
        ):
            self._reach_index = index.updated(
                self._pieces, self._piece_expert, self.n_experts_, touched, previous
            )
            return
        self.reach_ = self._reach(self._pieces, kernels)
        self.coverage_width_ = self._reach(self._pieces, kernels, _COVERAGE_TOLERANCE)
        self._reach_kernels = None if kernels is None else frozenset(kernels)
        self._reach_index = ExpertReach(
            self._pieces, self._piece_expert, self.n_experts_, self.reach_
        )

    def _kernels(self):
        """The experts' distinct fitted kernels by repr; None if one exposes none."""
        kernels = {}
        for est in self.experts_:
            kernel = getattr(est, "kernel_", None)
            if kernel is None and not isinstance(est, _ConstantExpert):
                return None
            if kernel is not None:
                kernels.setdefault(repr(kernel), kernel)
        return kernels

    def _reach(self, pieces, kernels=None, tolerance=None):
        """Distance beyond which the experts' kernels fall below ``tolerance`` of their
        peak (``reach_tolerance`` by default).

        The largest over the experts' fitted kernels (one kernel when shared); ``inf``
        when an expert exposes no ``kernel_`` or its kernel does not decay.
        """
        kernels = self._kernels() if kernels is None else kernels
        if kernels is None:
            return np.inf
        tolerance = self.reach_tolerance if tolerance is None else tolerance
        dim = pieces.shape[1] // 2
        extent = _extent(pieces)
        reaches = [kernel_reach(k, dim, tolerance, extent) for k in kernels.values()]
        return max(reaches, default=np.inf)

    def _make_expert(self):
        if self.expert is None:
            return _default_expert()
        params = self.expert.get_params() if hasattr(self.expert, "get_params") else {}
        if "kernel" in params and params["kernel"] is None:
            # An expert given for its other settings keeps the integral kernel: its own
            # default would read a beam's [start, end] columns as one point.
            return clone(self.expert).set_params(kernel=_default_kernel())
        return self.expert

    def _similarity_length_scale(self, expert, dim):
        kernel = expert.get_params().get("kernel") if hasattr(expert, "get_params") else None
        return np.asarray(1.0) if kernel is None else _similarity_length_scale(kernel, dim)

    def _cluster_and_assign(self, X, occupied, expert, rng):
        d = X.shape[1] // 2
        hits = X[occupied, :d]
        if self.clusterer is None:
            from .cluster import DPGMMClusterer

            clusterer = DPGMMClusterer()
        else:
            clusterer = clone(self.clusterer)
        if "random_state" in clusterer.get_params():
            clusterer.set_params(random_state=rng.randint(np.iinfo(np.int32).max))
        sample = None
        if self.max_cluster_samples is not None and hits.shape[0] > self.max_cluster_samples:
            sample = np.sort(rng.choice(hits.shape[0], self.max_cluster_samples, replace=False))
        _log(
            self.verbose,
            f"clustering {hits.shape[0] if sample is None else sample.size} of "
            f"{hits.shape[0]} hit point(s)",
        )
        self.clusterer_ = clusterer.fit(hits if sample is None else hits[sample])
        raw = getattr(self.clusterer_, "labels_", None) if sample is None else None
        if raw is None or len(raw) != hits.shape[0]:
            raw = self.clusterer_.predict(hits)
        self.cluster_ids_, hit_labels = np.unique(np.asarray(raw), return_inverse=True)

        # Every row follows an anchor hit: a hit itself, a return beam its hit, a no-return
        # beam the hit of its most similar return beam (its pieces may then join other
        # hits, see piece_assignment). Clusters and their pieces are sets of hits.
        hit_rows = np.flatnonzero(occupied)
        # Free points follow the return-beam rule without a distance limit.
        radius = np.inf if self.layout == "points" else self.return_radius
        kinds, anchor = _observation_kinds(
            X, occupied, radius, workers=_query_workers(self.n_jobs)
        )
        self.observation_kind_ = kinds
        is_ret = kinds == RETURN
        is_nr = kinds == NO_RETURN
        if np.any(is_nr):
            if np.any(is_ret):
                anchor[is_nr] = _assign_no_return(
                    X[is_nr],
                    X[is_ret],
                    anchor[is_ret],
                    self._similarity_length_scale(expert, d),
                    max_references=_NO_RETURN_REFERENCES,
                    random_state=rng,
                    n_jobs=self.n_jobs,
                )
            else:
                # No return beams to compare with: the hit nearest to the beam's midpoint.
                anchor[is_nr] = hit_rows[_hit_tree(hits).query(_midpoints(X[is_nr]))[1]]
        # Position of each hit row among the hits, to look up its cluster.
        hit_pos = np.cumsum(occupied) - 1
        labels = hit_labels[hit_pos[anchor]]
        self.cluster_merge_ = _merge_small(labels, hits, hit_labels, self.min_expert_size)
        self.n_clusters_ = int(self.cluster_merge_.max() + 1)
        return self.cluster_merge_[labels], anchor

    def _split_clusters(self, hits, hit_cluster, pieces, piece_hit):
        """Split clusters above ``max_expert_size`` (:func:`_split_hits`); gate the parts.

        Returns the expert of each hit. Each split cluster's experts are gated by
        Gaussians fitted to their pieces' midpoints.
        """
        hit_expert, self.expert_cluster_ = _split_hits(
            hits, hit_cluster, self.n_clusters_, piece_hit, self.max_expert_size
        )
        self._piece_gates = _piece_gates(
            self.expert_cluster_, self.n_clusters_, pieces, hit_expert[piece_hit]
        )
        self._first_expert = np.searchsorted(self.expert_cluster_, np.arange(self.n_clusters_))
        if self.expert_cluster_.size > self.n_clusters_:
            _log(
                self.verbose,
                f"split big clusters into {self.expert_cluster_.size} pieces of at "
                f"most {self.max_expert_size} observations",
            )
        return hit_expert

    def _hyperparameter_groups(self, expert_rows):
        """Groups of pieces whose summed evidence learns the shared hyperparameters.

        The experts' own (``expert_rows``) with ``piece_assignment="beam"``. With
        ``"nearest_hit"``, the experts the paper's rule would make (every piece with its
        beam's hit, clusters split alike): an expert of local pieces holds walls with the
        free space just around them, and its evidence prefers a length scale that
        extrapolates less than the map's beams support (on the tuning log, ACES, learned on
        the local experts it was 0.54 m and held-out AUC 0.913, against 1.05 m and 0.959;
        ``benchmarks/bench_tuning.py``, seed 100).
        """
        if self.piece_assignment == "beam":
            return expert_rows
        return self._hit_groups(self._piece_beam_hit)

    def _hit_groups(self, beam_hit):
        """Pieces grouped by the expert of their beam's hit, the clusters split to
        ``max_expert_size`` by these pieces (the experts of the paper's rule)."""
        hit_group, group_cluster = _split_hits(
            self._hits,
            self.expert_cluster_[self._hit_expert],
            self.n_clusters_,
            beam_hit,
            self.max_expert_size,
        )
        return _groups(hit_group[beam_hit], group_cluster.size)

    def _fit_experts(self, X, y, labels, expert, rng):
        n_experts = self.expert_cluster_.size
        # Seeds drawn up front so that results do not depend on n_jobs or on the order in
        # which workers finish.
        seeds = rng.randint(np.iinfo(np.int32).max, size=n_experts)
        has_seed = "random_state" in expert.get_params()
        rows = _groups(labels, n_experts)

        def prepared(k, base):
            est = clone(base)
            if has_seed:
                est.set_params(random_state=int(seeds[k]))
            return est

        self.shared_kernel_ = None
        base = expert
        if self.share_hyperparameters:
            base = self._learn_shared(rows, expert, rng)

        self._expert_base = base
        _log(self.verbose, f"fitting {n_experts} expert(s) with n_jobs={self.n_jobs}")
        # Kernel matrices kept for later partial_fit calls: of the last experts, as many as
        # the cache holds, so that no more than its budget is ever returned by the workers.
        packed_bytes = np.array([8 * r.size * (r.size + 1) // 2 for r in rows])
        from_end = np.cumsum(packed_bytes[::-1])[::-1]
        keep = from_end <= self.kernel_cache_size * 2**20
        results = Parallel(n_jobs=self.n_jobs, verbose=max(self.verbose - 1, 0))(
            delayed(_fit_expert)(
                prepared(k, base), X[rows[k]], y[rows[k]], keep_kernel=bool(keep[k])
            )
            for k in range(n_experts)
        )
        _warn_once_each([expert_warnings for _, expert_warnings, _ in results], n_experts)
        experts = [est for est, _, _ in results]
        self._cache_kernels(experts, [lower for _, _, lower in results], experts)
        return experts

    def _cuts_own_learning_pieces(self, expert):
        """Whether the shared kernel is learned on pieces of its own cut
        (``hyperparameter_beam_length`` differs from ``max_beam_length``)."""
        if not self.share_hyperparameters or self.hyperparameter_beam_length is None:
            return False
        if self.hyperparameter_beam_length == self.max_beam_length:
            return False
        return _learns_kernel(expert)

    def _learning_pieces(self, X, kinds, y_enc, row_hit, transient, rng, kept=None):
        """Rows ``X`` cut at ``hyperparameter_beam_length`` and thinned as the experts'
        pieces are: ``(pieces, labels, beam hit of each piece)``. ``kept``: free learning
        pieces of earlier batches, for the thinning's count."""
        pieces, source = _beam_pieces(
            X, kinds, self.hyperparameter_beam_length, self.beam_end_length
        )
        pieces, source = self._thinned(pieces, source, y_enc, rng, transient, kept=kept)
        return pieces, y_enc[source], row_hit[source]

    def _learning_groups(self, rows):
        """Groups (the paper's rule) of the pieces the shared kernel is learned on."""
        if self._learning is None:
            return self._hyperparameter_groups(rows)
        return self._hit_groups(self._learning[2])

    def _learn_shared(self, rows, expert, rng):
        """The expert with the shared kernel, fixed (or ``expert`` if no piece can learn)."""
        X, y = (self._pieces, self._piece_y) if self._learning is None else self._learning[:2]
        params = expert.get_params()
        if "kernel" not in params or "optimizer" not in params:
            raise ValueError(
                "share_hyperparameters=True needs an expert with 'kernel' and 'optimizer' "
                f"parameters; {type(expert).__name__} lacks them."
            )
        if self.hyperparameter_window is None:
            # Experts' pieces (as the paper's rule groups them), a random subset of them:
            # each term is one expert's fit, so a few dozen fix a handful of
            # hyperparameters at a bounded cost however large the map.
            groups = self._learning_groups(rows)
            two_class = [r for r in groups if 0 < y[r].sum() < r.size]
            chosen = rng.choice(len(two_class), min(len(two_class), _SHARED_PIECES), replace=False)
            windows = [two_class[k] for k in np.sort(chosen)]
        else:
            windows = window_pieces(
                _midpoints(X),
                y,
                radius=self.hyperparameter_window,
                max_rows=self.max_expert_size or _SHARED_WINDOW_ROWS,
                n_pieces=_SHARED_PIECES,
                random_state=rng,
            )
        if not windows:
            # Each expert learns its own kernel: no shared one (a re-learn must not leave
            # the previous one, which prediction would take for every expert's prior).
            self.shared_kernel_ = None
            return expert
        _log(self.verbose, f"learning shared hyperparameters on {len(windows)} piece(s)")
        learner = clone(expert)
        if "random_state" in learner.get_params():
            learner.set_params(random_state=rng.randint(np.iinfo(np.int32).max))
        self.shared_kernel_ = learn_shared_kernel(
            learner, [(X[piece], y[piece]) for piece in windows], n_jobs=self.n_jobs
        )
        if params["optimizer"] is not None:
            warn_at_bounds(self.shared_kernel_, "shared kernel")
            warn_beyond_extent(self.shared_kernel_, _extent(X), "shared kernel")
        return clone(expert).set_params(kernel=self.shared_kernel_, optimizer=None)

    def _fit_gpc_gate(self, X, labels, rng):
        """GP classifier over the expert labels of the observations' midpoints.

        Hyperparameters are fixed rather than learned (learning them for a one-vs-rest GP
        per expert took minutes on the paper's data): a signal variance of 4 lets the gate
        become confident, and the length scale is the mean spread of the pieces.
        """
        if self.n_experts_ == 1:
            return None
        from sklearn.gaussian_process import GaussianProcessClassifier
        from sklearn.gaussian_process.kernels import RBF, ConstantKernel

        mids = _midpoints(X)
        groups = _groups(labels, self.n_experts_)
        # Stratified sample, so that every expert keeps some training points.
        per = max(_GATING_GPC_MAX_SAMPLES // self.n_experts_, 1)
        idx = np.concatenate([rng.permutation(g)[:per] for g in groups])
        spread = np.mean([np.sqrt(np.mean(np.var(mids[g], axis=0))) for g in groups])
        length_scale = float(spread) if spread > 0 else 1.0
        gate = GaussianProcessClassifier(
            kernel=ConstantKernel(4.0, "fixed") * RBF(length_scale, "fixed"),
            optimizer=None,
            random_state=rng.randint(np.iinfo(np.int32).max),
        )
        _log(self.verbose, f"fitting the gpc gate on {idx.size} point(s)")
        return gate.fit(mids[idx], labels[idx])

    # -- gating ----------------------------------------------------------------------

    def _cluster_weights(self, mids):
        """Gate of the merged clusters: sums of the clusterer's responsibilities."""
        if self.n_clusters_ == 1:
            return np.ones((mids.shape[0], 1))
        raw = self._clusterer_weights(mids)
        weights = np.zeros((mids.shape[0], self.n_clusters_))
        for c in range(self.n_clusters_):
            weights[:, c] = raw[:, self.cluster_merge_ == c].sum(axis=1)
        return weights

    def _clusterer_weights(self, mids):
        """Responsibilities of the clusterer's clusters that received hits."""
        n_clusters = self.cluster_ids_.size
        soft = hasattr(self.clusterer_, "predict_proba") and (
            np.issubdtype(self.cluster_ids_.dtype, np.integer) and self.cluster_ids_.min() >= 0
        )
        if soft:
            proba = np.asarray(self.clusterer_.predict_proba(mids), dtype=np.float64)
            soft = self.cluster_ids_.max() < proba.shape[1]
        if soft:
            # Columns are the clusterer's labels 0..n-1; keep those that received hits.
            weights = proba[:, self.cluster_ids_.astype(np.intp)]
            total = weights.sum(axis=1, keepdims=True)
            empty = total[:, 0] <= 0
            weights = weights / np.where(empty[:, None], 1.0, total)
        else:
            weights = np.zeros((mids.shape[0], n_clusters))
            empty = np.ones(mids.shape[0], dtype=bool)
        if np.any(empty):
            # Hard assignment where the clusterer gives no soft weights.
            pred = np.asarray(self.clusterer_.predict(mids[empty]))
            pos = np.searchsorted(self.cluster_ids_, pred).clip(0, n_clusters - 1)
            found = self.cluster_ids_[pos] == pred
            sub = np.full((pred.size, n_clusters), 1.0 / n_clusters)
            sub[found] = 0.0
            sub[np.flatnonzero(found), pos[found]] = 1.0
            weights[empty] = sub
        return weights

    def _pair_gates(self, mids, query, expert):
        """``p(expert | x)`` of each candidate (query, expert) pair, before the threshold."""
        if self.n_experts_ == 1:
            return np.ones(query.size)
        if self.gating == "gpc":
            # The GP classifier's softmax over experts is dense by nature.
            proba = self.gating_.predict_proba(mids)
            column = np.full(self.n_experts_, -1)
            column[self.gating_.classes_] = np.arange(self.gating_.classes_.size)
            col = column[expert]
            return np.where(col >= 0, proba[query, np.maximum(col, 0)], 0.0)
        cluster = self.expert_cluster_[expert]
        weights = self._cluster_weights(mids)[query, cluster]
        # Split clusters: the piece's share of its cluster, at the queries that ask for it.
        order = np.argsort(cluster, kind="stable")
        bounds = np.searchsorted(cluster[order], np.arange(self.n_clusters_ + 1))
        for c, gate in enumerate(self._piece_gates):
            if gate is None or bounds[c] == bounds[c + 1]:
                continue
            pairs = order[bounds[c] : bounds[c + 1]]
            asked, pos = np.unique(query[pairs], return_inverse=True)
            share = gate.predict_proba(mids[asked])
            weights[pairs] *= share[pos.ravel(), expert[pairs] - self._first_expert[c]]
        return weights

    def _gate(self):
        """The gate in use: ``gating``, but the clusterer's where an infinite reach
        leaves the coverage gate without cells."""
        if self.gating == "coverage" and not np.isfinite(self._reach_index.reach):
            return "clusterer"
        return self.gating

    def _gating_threshold(self):
        if self.gating_threshold != "auto":
            return self.gating_threshold
        return _AUTO_GATING_THRESHOLD[self._gate()]

    def _coverage_gates(self, Xc, query, expert, return_covered=False):
        """``gating="coverage"``: each candidate's share of the coverage of the query
        (:meth:`ExpertReach.coverage` with width ``coverage_width_``); equal weights where
        no candidate covers it. ``return_covered``: also whether each pair's coverage is
        positive (its expert has cells within the coverage's cut of the query)."""
        cover = self._reach_index.coverage(
            Xc, query, expert, self.coverage_width_, n_jobs=self.n_jobs
        )
        total = np.bincount(query, weights=cover, minlength=Xc.shape[0])[query]
        weights = np.where(total > 0, cover / np.where(total > 0, total, 1.0), 1.0)
        return (weights, cover > 0) if return_covered else weights

    def _consulted(self, Xc):
        """The experts each query consults: (query, expert, weight) sorted by expert.

        The index's table gives each query its candidate experts (a superset of those
        with data within ``reach_``). Those whose gate weight is at least
        ``gating_threshold`` (times the query's largest weight, with the coverage gate),
        and the one with the largest weight, are kept if they have
        data within reach of the query (see :meth:`ExpertReach.within_reach`). A query
        that keeps none falls back to its best-weighted expert within reach, and to no
        expert (the prior) when none is. The coverage gate with a positive threshold
        finds the same pairs from those of positive coverage
        (:meth:`_consulted_by_coverage`), without the candidates' coverage, once that pays.
        """
        index = self._reach_index
        coverage = self._gate() == "coverage"
        if coverage and self._gating_threshold() > 0.0 and index.prefers_covering(len(Xc)):
            return self._consulted_by_coverage(Xc)
        query, expert = index.candidates(Xc)
        if query.size == 0:
            return query, expert, np.empty(0)
        # Pairs known to be within reach without a search: those the coverage gate covers
        # (it counts only midpoint cells whose data lie within reach of the query).
        if coverage:
            weights, covered = self._coverage_gates(Xc, query, expert, return_covered=True)
        else:
            weights = self._pair_gates(_midpoints(Xc), query, expert)
            covered = np.zeros(query.size, dtype=bool)
        largest = _query_max(query, weights)
        # The coverage gate's threshold is relative to the best-covered expert: where
        # dozens of experts overlap, each holds a small share, and all of them hold data.
        bound = self._gating_threshold() * (largest if coverage else 1.0)
        keep = (weights == largest) | (weights >= bound)
        near = keep & covered
        search = keep & ~near
        near[search] = index.within_reach(Xc, query[search], expert[search])
        lost = np.ones(Xc.shape[0], dtype=bool)
        lost[query[near]] = False
        retry = lost[query]
        if np.any(retry):
            # Their kept experts were all out of reach: the best of those in reach.
            rows = np.flatnonzero(retry)
            rows = rows[index.within_reach(Xc, query[rows], expert[rows])]
            near[rows[_best(query[rows], weights[rows])]] = True
        # A query whose weights all vanish still has its best expert, with positive weight.
        weights = np.maximum(weights, np.finfo(np.float64).tiny)
        query, expert, weights = query[near], expert[near], weights[near]
        order = np.argsort(expert, kind="stable")
        return query[order], expert[order], weights[order]

    def _consulted_by_coverage(self, Xc):
        """:meth:`_consulted` with the coverage gate and a positive threshold, from the
        pairs of positive coverage (``ExpertReach.covering``) instead of every candidate's.

        The same pairs and weights: with a positive threshold a query that some expert
        covers keeps only covering experts (which hold data within reach), and one that
        none covers keeps every candidate within reach, all of equal weight.
        """
        index = self._reach_index
        query, expert, cover = index.covering(Xc, self.coverage_width_)
        total = np.bincount(query, weights=cover, minlength=Xc.shape[0])
        weights = cover / total[query]
        largest = _query_max(query, weights)
        keep = (weights == largest) | (weights >= self._gating_threshold() * largest)
        parts = [(query[keep], expert[keep], weights[keep])]
        bare = np.flatnonzero(total == 0.0)
        if bare.size:
            q, e = index.candidates(Xc[bare])
            near = index.within_reach(Xc[bare], q, e)
            parts.append((bare[q[near]], e[near], np.ones(np.count_nonzero(near))))
        query, expert, weights = (np.concatenate(part) for part in zip(*parts, strict=True))
        order = np.lexsort((query, expert))
        return query[order], expert[order], weights[order]

    # -- prediction ------------------------------------------------------------------

    def _check_fitted_with(self):
        """``layout``, and a ``"gpc"`` gate, shape what fit builds: set since, they would
        be read against a model built without them."""
        fitted = getattr(self, "_fitted_with", self.get_params())  # older pickles: unchecked
        if self.layout != fitted["layout"]:
            name = "layout"
        elif self.gating == "gpc" and fitted["gating"] != "gpc":
            name = "gating"
        else:
            return
        raise ValueError(
            f"{name}={getattr(self, name)!r} was set after the model was fitted with "
            f"{name}={fitted[name]!r}; call fit again (combiner, gating_threshold and a "
            "gating of 'coverage' or 'clusterer' may change between predictions)."
        )

    def _validate_queries(self, X):
        check_is_fitted(self)
        self._check_fitted_with()
        return _as_segment_rows(validate_queries(self, X), self.layout)

    def _merged(self, X):
        """Merged prediction (proba, mean, variance), query chunk by query chunk.

        Queries are taken in the order of the index's blocks, so that a chunk is a compact
        region and each expert predicts its queries of a chunk in one call.
        """
        X = self._validate_queries(X)
        if X.shape[0] == 0:
            return np.empty(0), np.empty(0), np.empty(0)
        order = self._reach_index.spatial_order(X)
        # Bounded pair arrays: each query consults at most the experts near its block.
        pair_bytes = 8 * 8 * max(self._reach_index.max_candidates, 1)
        chunk = int(get_config()["working_memory"] * 2**20 // pair_bytes)
        chunk = min(max(chunk, 64), max(X.shape[0], 1))
        out = [np.empty(X.shape[0]) for _ in range(3)]
        batches = list(gen_batches(X.shape[0], chunk))
        for b, batch in enumerate(batches):
            rows = order[batch]
            for arr, part in zip(out, self._merge_chunk(X[rows]), strict=True):
                arr[rows] = part
            if self.verbose > 1:
                _log(self.verbose, f"predicted chunk {b + 1} of {len(batches)}")
        return tuple(out)

    def _merge_chunk(self, Xc):
        query, expert, weights = self._consulted(Xc)
        needs_prior = self.combiner in ("bcm", "rbcm")
        means = np.empty(query.size)
        variances = np.empty(query.size)
        prior = np.empty(query.size) if needs_prior else None
        bounds = np.searchsorted(expert, np.arange(self.n_experts_ + 1))
        # One kernel for every expert: its prior variance at the chunk's queries, once.
        shared_prior = None
        if self.shared_kernel_ is not None:
            shared_prior = np.asarray(self.shared_kernel_.diag(Xc), dtype=np.float64)

        def predict_expert(k, cross=None):
            # Each task writes its own slice of the pairs: results do not depend on n_jobs.
            part = slice(bounds[k], bounds[k + 1])
            rows = Xc[query[part]]
            model = self.experts_[k]
            k_diag = None if shared_prior is None else shared_prior[query[part]]
            if _is_binary_ep(model):
                # The mixture validated the queries: the expert's own checks only cost.
                means[part], variances[part] = model._latent(rows, k_diag, cross)
            else:
                means[part], variances[part] = model.latent_mean_and_variance(rows)
            if needs_prior:
                prior[part] = _prior_variance(model, rows) if k_diag is None else k_diag

        # Threads, not processes: shipping all experts to workers per chunk costs more than
        # the kernels, which spend their time in numpy calls that release the GIL.
        consulted = np.flatnonzero(np.diff(bounds))
        if threads_pay(query.size, consulted.size):
            Parallel(n_jobs=self.n_jobs, require="sharedmem")(
                delayed(predict_expert)(k) for k in consulted
            )
        else:
            # Without joblib: its bookkeeping per task (configuration, warning filters)
            # cost a few-query prediction as much as the experts' own work.
            for k, cross in self._cross_covariances(Xc, query, bounds, consulted):
                predict_expert(k, cross)
        proba = np.full(Xc.shape[0], 0.5)
        mean = np.zeros(Xc.shape[0])
        variance = np.empty(Xc.shape[0])
        reached, pair_query = np.unique(query, return_inverse=True)
        merged = combine_pairs(
            pair_query.ravel(),
            means,
            variances,
            weights,
            n_queries=reached.size,
            method=self.combiner,
            prior_variance=prior,
        )
        proba[reached], mean[reached], variance[reached] = merged
        # Beyond the reach of every expert: the prior.
        alone = np.ones(Xc.shape[0], dtype=bool)
        alone[reached] = False
        if np.any(alone):
            variance[alone] = (
                shared_prior[alone]
                if shared_prior is not None
                else self._unreached_prior_variance(Xc[alone])
            )
        return proba, mean, variance

    def _cross_covariances(self, Xc, query, bounds, consulted):
        """``(k, K_star)`` for each consulted expert: its cross-covariances at its queries,
        evaluated for groups of experts at once, or None (then the expert computes them).

        A few queries give each expert one or two rows, and an integral kernel call of
        that size is mostly fixed costs. Where the experts share an integral kernel (the
        default) and the queries are points, :func:`point_row_pairs` evaluates groups of
        experts' (query, training row) pairs, ``_POINT_CHUNK`` pairs at a time, with the
        values of the experts' own calls to the bit (every binary EP expert holds the
        shared kernel: ``fit`` and every re-learn refit them all with it).
        """
        parts = None if self.shared_kernel_ is None else _integral_parts(self.shared_kernel_)
        d = Xc.shape[1] // 2
        if parts is None or not np.array_equal(Xc[:, :d], Xc[:, d:]):
            yield from ((k, None) for k in consulted)
            return
        constant, integral = parts
        length_scale = integral._checked_length_scale(d)
        group, n_pairs = [], 0
        for position, k in enumerate(consulted):
            model = self.experts_[k]
            if _is_binary_ep(model):
                group.append(k)
                n_pairs += (bounds[k + 1] - bounds[k]) * model.X_train_.shape[0]
            else:
                yield k, None
            if group and (n_pairs >= _POINT_CHUNK or position == consulted.size - 1):
                yield from self._group_cross(
                    Xc[:, :d], query, bounds, group, length_scale, constant
                )
                group, n_pairs = [], 0

    def _group_cross(self, points, query, bounds, group, length_scale, constant):
        train = [self.experts_[k].X_train_ for k in group]
        group = np.asarray(group)
        n_queries = bounds[group + 1] - bounds[group]
        n_rows = np.array([t.shape[0] for t in train])
        size = n_queries * n_rows
        ends = np.cumsum(size)
        # Pair p of expert e: its query within // n_rows, its row within % n_rows.
        owner = np.repeat(np.arange(group.size), size)
        within = np.arange(ends[-1]) - (ends - size)[owner]
        point = query[bounds[group][owner] + within // n_rows[owner]]
        row = (np.cumsum(n_rows) - n_rows)[owner] + within % n_rows[owner]
        values = point_row_pairs(
            points, np.concatenate(train), point, row, length_scale=length_scale
        )
        if constant is not None:
            # The product kernel's entries: the constant times the integral, exactly.
            values *= constant.constant_value
        for e, block in enumerate(np.split(values, ends[:-1])):
            yield int(group[e]), block.reshape(n_queries[e], n_rows[e])

    def _unreached_prior_variance(self, X):
        """Prior latent variance where no expert reaches, without shared hyperparameters
        (with them every expert has the shared kernel's prior): the experts' mean prior
        precision, averaged over up to 16 experts spread over the list.
        """
        chosen = np.unique(np.linspace(0, self.n_experts_ - 1, 16).astype(int))
        precision = np.mean([1.0 / _prior_variance(self.experts_[k], X) for k in chosen], axis=0)
        return 1.0 / precision

    def prior_variance(self, X):
        """Prior latent variance at the query segments: what :meth:`predict_var` gives
        where no expert reaches, the reference for "unknown" on a map.

        Parameters
        ----------
        X : array-like of shape (n_queries, 2 * D)
            Query segments; a map cell is a zero-length segment.

        Returns
        -------
        variance : ndarray of shape (n_queries,)

        Examples
        --------
        >>> from skoccmap import MixtureGPOccupancyMap
        >>> from skoccmap.datasets import make_paper_scans
        >>> data = make_paper_scans(random_state=0)
        >>> model = MixtureGPOccupancyMap(random_state=0).fit(data.X, data.y)
        >>> far = [[1e3, 1e3, 1e3, 1e3]]
        >>> bool(model.predict_var(far)[0] == model.prior_variance(far)[0] == 1e3)
        True
        """
        X = self._validate_queries(X)
        if X.shape[0] == 0:
            return np.empty(0)
        if self.shared_kernel_ is not None:
            return np.asarray(self.shared_kernel_.diag(X), dtype=np.float64)
        return self._unreached_prior_variance(X)

    def predict_proba(self, X):
        """Probability of each class at the query segments.

        A segment's probability is that of the map's latent function averaged along it
        (the integral kernel), not of its most occupied point: a segment that crosses a
        thin wall reads freer the longer it is (on the simulated office, a 4 m segment
        centred on a wall read 0.28, its points up to 1.0). To ask whether a path is
        free, query points along it, e.g.
        ``as_segments(a + np.linspace(0, 1, n)[:, None] * (b - a))`` at the map's
        resolution, and take the largest probability.

        Parameters
        ----------
        X : array-like of shape (n_queries, 2 * D)
            Query segments; a map cell is a zero-length segment.

        Returns
        -------
        proba : ndarray of shape (n_queries, 2)
            Column 1 is the probability of ``classes_[1]`` (occupied).
        """
        p = self._merged(X)[0]
        return np.column_stack([1.0 - p, p])

    def predict(self, X):
        """Most probable class at the query segments.

        Parameters
        ----------
        X : array-like of shape (n_queries, 2 * D)
            Query segments.

        Returns
        -------
        y : ndarray of shape (n_queries,)
            Labels from ``classes_``.
        """
        proba = self.predict_proba(X)
        return self.classes_[np.argmax(proba, axis=1)]

    def latent_mean_and_variance(self, X):
        """Merged latent mean and variance at the query segments.

        Parameters
        ----------
        X : array-like of shape (n_queries, 2 * D)
            Query segments.

        Returns
        -------
        mean : ndarray of shape (n_queries,)
            Merged latent mean.
        variance : ndarray of shape (n_queries,)
            Merged latent variance (for ``"moe"`` the variance of the mixture).
        """
        _, mean, variance = self._merged(X)
        return mean, variance

    def _predict_proba_and_var(self, X):
        """P(occupied) and merged latent variance from one pass over the experts.

        :meth:`skoccmap.OccupancyGrid.from_estimator` uses it when present, so that a map
        needs every expert's kernel rows once rather than once for ``predict_proba`` and
        again for ``predict_var``.
        """
        proba, _, variance = self._merged(X)
        return proba, variance

    def predict_var(self, X):
        """Merged latent variance at the query segments.

        A segment's is the variance of the latent function averaged along it (see
        :meth:`predict_proba`).

        Parameters
        ----------
        X : array-like of shape (n_queries, 2 * D)
            Query segments.

        Returns
        -------
        variance : ndarray of shape (n_queries,)
            Merged latent variance, strictly positive.
        """
        return self._merged(X)[2]
