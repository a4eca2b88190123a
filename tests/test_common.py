"""scikit-learn's estimator checks for every public estimator.

Each estimator joins ``ESTIMATORS`` as it lands. Expected failures, if any, go in
``EXPECTED_FAILED_CHECKS`` with the reason next to each entry.
"""

import pytest
from sklearn.utils.estimator_checks import check_param_validation, parametrize_with_checks

from skoccmap.baselines import OccupancyGridMap
from skoccmap.classifier import EPGaussianProcessClassifier
from skoccmap.cluster import DPGMMClusterer
from skoccmap.mixture import MixtureGPOccupancyMap

ESTIMATORS = [OccupancyGridMap(), EPGaussianProcessClassifier(), DPGMMClusterer()]
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
