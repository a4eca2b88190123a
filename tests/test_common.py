"""scikit-learn's estimator checks for every public estimator.

Each estimator joins ``ESTIMATORS`` as it lands. Expected failures, if any, go in
``EXPECTED_FAILED_CHECKS`` with the reason next to each entry.
"""

import warnings

import numpy as np
import pytest
import sklearn
from sklearn.exceptions import NotFittedError
from sklearn.utils.estimator_checks import check_param_validation, parametrize_with_checks

from skoccmap._validation import warn_unless_metres
from skoccmap.baselines import FrequencyGridMap, HilbertMap, OccupancyGridMap
from skoccmap.classifier import EPGaussianProcessClassifier
from skoccmap.cluster import DPGMMClusterer
from skoccmap.datasets import make_paper_scans
from skoccmap.mixture import MixtureGPOccupancyMap

ESTIMATORS = [
    OccupancyGridMap(),
    FrequencyGridMap(),
    HilbertMap(),
    EPGaussianProcessClassifier(),
    DPGMMClusterer(),
]
# Points layout: every column count is valid (segments: tests/test_mixture.py).
ESTIMATORS.append(MixtureGPOccupancyMap(layout="points"))

# {estimator class name: {check name: reason}}
EXPECTED_FAILED_CHECKS = {}


def _expected_failed_checks(estimator):
    return EXPECTED_FAILED_CHECKS.get(type(estimator).__name__, {})


@parametrize_with_checks(ESTIMATORS, expected_failed_checks=_expected_failed_checks)
def test_sklearn_compatible_estimator(estimator, check):
    check(estimator)


@pytest.mark.parametrize("estimator", ESTIMATORS, ids=lambda est: type(est).__name__)
def test_param_validation(estimator):
    # Not part of check_estimator: invalid constructor parameters must be rejected in fit.
    check_param_validation(type(estimator).__name__, estimator)


@pytest.mark.parametrize(
    "estimator",
    [
        OccupancyGridMap(),
        FrequencyGridMap(),
        HilbertMap(random_state=0),
        EPGaussianProcessClassifier(),
        DPGMMClusterer(random_state=0),
        MixtureGPOccupancyMap(random_state=0),
    ],
    ids=lambda est: type(est).__name__,
)
def test_a_fit_that_raises_leaves_the_estimator_unfitted(estimator):
    # Neither the earlier fit nor half of the new one beside half of the old.
    data = make_paper_scans(random_state=0)
    X, y = data.X[::3], data.y[::3]
    estimator.fit(X, y)
    bad = X.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError):
        estimator.fit(bad, y)
    with pytest.raises(NotFittedError):
        estimator.predict(X)
    # A parameter refused by the validation before the fit, too.
    estimator.fit(X, y)
    name = next(iter(estimator.get_params()))
    estimator.set_params(**{name: object()})
    with pytest.raises(ValueError):
        estimator.fit(X, y)
    with pytest.raises(NotFittedError):
        estimator.predict(X)


def test_a_failed_fit_keeps_the_metadata_requests():
    with sklearn.config_context(enable_metadata_routing=True):
        grid = OccupancyGridMap(l_min=0.0, l_max=0.0).set_fit_request(scan_index=True)
        with pytest.raises(ValueError, match="l_min"):
            grid.fit(*_paper_xy())
        assert grid.get_metadata_routing().fit.requests == {"scan_index": True}


def _paper_xy():
    data = make_paper_scans(random_state=0)
    return data.X[::3], data.y[::3]


def test_a_fit_failing_after_its_first_attributes_predicts_nothing():
    data = make_paper_scans(random_state=0)
    X, y = data.X[::3], data.y[::3]
    # HilbertMap set its new centre before finding no usable free row, then predicted
    # from the old classifier around it.
    hilbert = HilbertMap(random_state=0).fit(X, y)
    far = [[100, 100, 150, 100], [150.1, 100, 150.1, 100], [151, 100, 151, 100]]
    with pytest.raises(ValueError, match="max_free_length"):
        hilbert.fit(far, [0, 1, 1])
    with pytest.raises(NotFittedError):
        hilbert.predict_proba(X)
    # The mixture took the failed fit's classes, and labelled the old experts' output.
    mixture = MixtureGPOccupancyMap(random_state=0).fit(X, y)
    one_hit = np.r_[np.flatnonzero(y == 1)[:1], np.flatnonzero(y == 0)[:4]]
    with pytest.raises(ValueError, match="2"):
        mixture.fit(X[one_hit], np.where(y[one_hit] == 1, "occ", "free"))
    with pytest.raises(NotFittedError):
        mixture.predict(X)
    # A fresh grid whose fit failed on its own parameters said AttributeError.
    grid = OccupancyGridMap(l_min=0.0, l_max=0.0)
    with pytest.raises(ValueError, match="l_min"):
        grid.fit(X, y)
    with pytest.raises(NotFittedError):
        grid.predict(X)


@pytest.mark.parametrize(
    "estimator",
    [OccupancyGridMap(), FrequencyGridMap(), HilbertMap(), MixtureGPOccupancyMap()],
    ids=lambda est: type(est).__name__,
)
def test_coordinates_in_millimetres_warn_before_the_fit(estimator):
    # The mixture's fit took 53 s instead of 3 on the paper's scans in mm, without a word.
    X, y = _paper_xy()
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        with pytest.raises(UserWarning, match="Divide X by 1000"):
            estimator.fit(1000 * X, y)
        estimator.fit(X, y)  # metres: no warning


def test_the_metres_check_reads_the_median_beam_and_skips_hits():
    starts = np.zeros((5, 2))
    ends = np.c_[[0, 0, 0, 400, 450], np.zeros(5)]  # three hits, median beam 425
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_unless_metres(starts, ends)
        warn_unless_metres(starts[:3], ends[:3])  # no beam
    ends[3:, 0] = [400, 600]  # median 500: the bound itself
    warn_unless_metres(starts, ends)
    ends[4, 0] = 620
    with pytest.warns(UserWarning, match="median length is 510"):
        warn_unless_metres(starts, ends)


def test_an_interrupted_fit_leaves_the_estimator_unfitted(monkeypatch):
    # Ctrl-C in a long fit is no Exception: the half-fitted model must not predict either.
    from skoccmap import baselines

    X, y = _paper_xy()
    grid = OccupancyGridMap().fit(X, y)

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(baselines, "warn_unless_metres", interrupt)
    with pytest.raises(KeyboardInterrupt):
        grid.fit(X, y)
    with pytest.raises(NotFittedError):
        grid.predict(X)
    assert grid.get_params() == OccupancyGridMap().get_params()


def test_the_metres_check_keeps_quiet_at_its_bound():
    # A median beam of exactly 500 m is within the bound: no warning.
    starts = np.zeros((3, 2))
    ends = np.c_[[400, 500, 600], np.zeros(3)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_unless_metres(starts, ends)
