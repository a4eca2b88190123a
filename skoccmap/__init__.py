"""Continuous occupancy maps from laser scans with a mixture of Gaussian-process experts.

The method is that of S. Kim and J. Kim, "Building occupancy maps with a mixture of Gaussian
processes", ICRA 2012.

The public estimators follow scikit-learn's API:

- :class:`DPGMMClusterer` -- Dirichlet-process Gaussian mixture, collapsed Gibbs sampling.
- :class:`IntegralKernel` -- squared-exponential kernel averaged along segments (laser beams).
- :class:`EPGaussianProcessClassifier` -- GP classification by Expectation Propagation; two
  classes by EP, more by one-vs-rest or one-vs-one, as scikit-learn's
  ``GaussianProcessClassifier``.
- :class:`MixtureGPOccupancyMap` -- one GP expert per cluster, merged into one occupancy map.

Observations are plain float arrays of segment rows ``[start_1..start_D, end_1..end_D]``; a
point is a zero-length segment (see :func:`skoccmap.observations.as_segments`).
"""

import importlib

__version__ = "0.1.0.dev0"

# Public name -> defining module. Submodules are imported on first access so that
# ``import skoccmap`` stays cheap and optional pieces (plotting) never load matplotlib early.
_LAZY = {
    "DPGMMClusterer": "cluster",
    "IntegralKernel": "kernels",
    "EPGaussianProcessClassifier": "classifier",
    "MixtureGPOccupancyMap": "mixture",
    "OccupancyGrid": "grid",
    "OccupancyGridMap": "baselines",
    "FrequencyGridMap": "baselines",
    "HilbertMap": "baselines",
    "scans_to_observations": "observations",
    "as_segments": "observations",
    "Scans": "observations",
}

__all__ = sorted(_LAZY) + ["__version__"]


def __getattr__(name):
    if name in _LAZY:
        module = importlib.import_module(f".{_LAZY[name]}", __name__)
        return getattr(module, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return __all__
