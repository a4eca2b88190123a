import warnings

import numpy as np
import pytest
from scipy import integrate
from scipy.special import ndtr

from skoccmap.uncertainty import probability_std


@pytest.mark.parametrize(
    "mu, var", [(0.3, 2.0), (-1.5, 0.5), (2.0, 10.0), (0.0, 100.0), (4.0, 1e-3)]
)
def test_probability_std_against_quadrature(mu, var):
    sd = np.sqrt(var)

    def moment(k):
        def integrand(f):
            return ndtr(f) ** k * np.exp(-0.5 * ((f - mu) / sd) ** 2) / (sd * np.sqrt(2 * np.pi))

        return integrate.quad(integrand, mu - 12 * sd, mu + 12 * sd, epsabs=1e-13, limit=200)[0]

    mean = moment(1)
    expected = np.sqrt(moment(2) - mean**2)
    np.testing.assert_allclose(mean, ndtr(mu / np.sqrt(1 + var)), atol=1e-10)
    np.testing.assert_allclose(probability_std(mean, var), expected, rtol=1e-6, atol=1e-9)


def test_probability_std_limits():
    # No latent uncertainty: Phi(f) is a constant; a uniform Phi(f) at mu = 0, var = 1.
    # (E[Phi^2] - E[Phi]^2 cancels to rounding, ~1e-16, whose square root is ~1e-8.)
    np.testing.assert_allclose(probability_std([0.1, 0.5, 0.0, 1.0], 0.0), 0.0, atol=1e-7)
    np.testing.assert_allclose(probability_std(0.5, 1.0), 1 / np.sqrt(12))
    # Huge variance: Phi(f) is 0 or 1, a coin flip at p = 1/2.
    np.testing.assert_allclose(probability_std(0.5, 1e12), 0.5, atol=1e-5)
    # Infinite variance: Phi(f) is 0 or 1 with probability 1 - p and p.
    np.testing.assert_allclose(probability_std([0.5, 0.7], np.inf), np.sqrt([0.25, 0.21]))
    # Near the largest float, 1 + 2 var overflows to its limit, with no warning about it.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_allclose(probability_std([0.5, 0.7], 1e308), np.sqrt([0.25, 0.21]))
    std = probability_std(np.linspace(0, 1, 11)[:, None], np.logspace(-3, 3, 7)[None, :])
    assert std.shape == (11, 7) and np.all((std >= 0) & (std <= 0.5))


@pytest.mark.parametrize(
    "proba, var, match",
    [
        (np.nan, 1.0, "proba"),
        (1.5, 1.0, "proba"),
        (-0.1, 1.0, "proba"),
        (0.5, -1.0, "latent_variance"),
        (0.5, np.nan, "latent_variance"),
    ],
)
def test_probability_std_rejects_bad_input(proba, var, match):
    with pytest.raises(ValueError, match=match):
        probability_std(proba, var)


def test_probability_std_of_mismatched_shapes_is_a_clear_error():
    with pytest.raises(ValueError, match=r"must broadcast together, got shapes \(2,\) and \(3,\)"):
        probability_std([0.5, 0.5], [1.0, 1.0, 1.0])


@pytest.mark.parametrize("n_rows", [2, 5])
def test_probability_std_refuses_both_columns_of_predict_proba(n_rows):
    # With two rows predict_proba's (2, 2) broadcast against predict_var's (2,) and gave
    # a (2, 2) result, row 0's probabilities with row 1's variance among them; with more
    # rows the error did not say which column to pass.
    p_occupied = np.linspace(0.2, 0.9, n_rows)
    both_columns = np.column_stack([1 - p_occupied, p_occupied])
    variance = np.linspace(0.5, 3.0, n_rows)
    with pytest.raises(ValueError, match=r"predict_proba\(X\)\[:, 1\]"):
        probability_std(both_columns, variance)
    std = probability_std(both_columns[:, 1], variance)
    assert std.shape == (n_rows,)
    # Each row's std is that of its own probability and variance.
    for p, v, s in zip(p_occupied, variance, std, strict=True):
        np.testing.assert_allclose(s, probability_std(p, v))
