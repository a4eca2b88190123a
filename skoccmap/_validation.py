"""Input checks shared by the kernel, the estimators and the observation helpers."""

import contextlib
import functools
import os
import re
import sys
import warnings
from numbers import Real

import joblib
import numpy as np
import sklearn
from scipy import sparse

# Code whose frames a warning skips to name the line that called into it (see
# caller_stacklevel).
_LIBRARY_DIRS = tuple(
    os.path.dirname(module.__file__) + os.sep
    for module in (sys.modules[__package__], sklearn, joblib)
)


def caller_stacklevel():
    """``stacklevel`` for ``warnings.warn`` that names the first frame outside this package,
    scikit-learn and joblib: the user's line, however many wrappers, decorators and
    meta-estimators (``OneVsRestClassifier``, ``Pipeline``) lie between.

    Call it from the function that calls ``warnings.warn``."""
    return _caller(sys._getframe(2))[1]


def _caller(frame):
    """The first frame from ``frame`` outwards outside this package, scikit-learn and
    joblib (None if none is), and its ``stacklevel`` counted from ``frame`` as 2."""
    level = 2
    while frame is not None and (
        frame.f_code.co_filename.startswith(_LIBRARY_DIRS) or _generated_init(frame.f_code)
    ):
        frame, level = frame.f_back, level + 1
    return frame, level


# Numbers in a warning's text (a count, a residual).
_NUMBER = re.compile(r"[-+]?\d[\d.e+-]*")
# The kinds of warning shown under the filters held (see _repeated).
_SHOWN = {"filters": None, "snapshot": None, "kinds": set()}


def warn(message, category=UserWarning):
    """``warnings.warn`` at the caller's line (:func:`caller_stacklevel`), each kind of
    warning once per line where the filters show a warning once.

    Python's ``"default"`` action shows a warning once per line and text, but every
    ``catch_warnings`` resets its record of what it showed, and the mixture's expert fits
    run in one: a warning that every ``partial_fit`` of a loop gives would reach the log
    once per update. Where the filter that applies says ``"default"``, ``"module"`` or
    ``"once"``, a warning of a kind already shown there (the same text, numbers aside) is
    left out here, until the filters change; under ``"always"`` or ``"error"`` every one
    is raised.
    """
    frame, level = _caller(sys._getframe(1))
    if frame is None or not _repeated(str(message), category, frame):
        warnings.warn(message, category, stacklevel=level)


def warning_kind(text):
    """A warning's text with its numbers blanked: messages that differ only in their
    numbers (a count, a residual) are one kind of warning."""
    return _NUMBER.sub("#", text)


def _filter_action(text, category, module, lineno):
    """The action of the first filter that matches, as ``warnings.warn`` finds it."""
    for action, msg, cat, mod, line in warnings.filters:
        if (
            (msg is None or msg.match(text))
            and issubclass(category, cat)
            and (mod is None or mod.match(module))
            and (line == 0 or line == lineno)
        ):
            return action
    return warnings.defaultaction


def _repeated(text, category, frame):
    """Whether a warning of this kind was shown at ``frame``'s line (its module, or
    anywhere, for ``"module"`` and ``"once"``) under the filters held now; records it."""
    module = frame.f_globals.get("__name__", "<string>")
    filename, lineno = frame.f_code.co_filename, frame.f_lineno
    action = _filter_action(text, category, module, lineno)
    if action not in ("default", "module", "once"):
        return False
    filters = warnings.filters
    if _SHOWN["filters"] is not filters or _SHOWN["snapshot"] != filters:
        # New filters (the caller's catch_warnings, simplefilter): start over, as Python does.
        _SHOWN.update(filters=filters, snapshot=list(filters), kinds=set())
    kind = (category, warning_kind(text))
    kind += {"once": (), "module": (filename,), "default": (filename, lineno)}[action]
    if kind in _SHOWN["kinds"]:
        return True
    _SHOWN["kinds"].add(kind)
    return False


def _generated_init(code):
    # The __init__ that dataclasses writes (Scans'), between __post_init__ and the caller.
    return code.co_filename == "<string>" and code.co_name == "__init__"


@contextlib.contextmanager
def queries_of_our_own():
    """Around predictions on arrays this package builds in the estimator's own column
    order (cell centres, held-out points): scikit-learn's warning that such an array has
    no feature names, for an estimator fitted on a DataFrame, would only puzzle the user.
    """
    with warnings.catch_warnings():
        warnings.filterwarnings(
            "ignore", message="X does not have valid feature names", category=UserWarning
        )
        yield


def queries_at(estimator, points):
    """``points`` (an array of shape (n, D)) as the rows ``estimator`` predicts on: the
    points themselves for an estimator fitted on ``D`` columns (``layout="points"``, or
    any classifier fitted on points), zero-length segments ``[p, p]`` otherwise.

    The helpers that query an estimator at points of their own (cell centres, held-out
    points) call it: segments alone reached an estimator fitted on points as
    "X has 4 features, but ... is expecting 2"."""
    points = np.asarray(points, dtype=np.float64)
    if getattr(estimator, "n_features_in_", None) == points.shape[1]:
        return points
    return np.concatenate([points, points], axis=1)


def check_known_labels(y, classes):
    """ValueError where ``y`` holds labels outside ``classes`` (those of the first
    ``partial_fit`` call)."""
    unknown = ~np.isin(y, classes)
    if np.any(unknown):
        raise ValueError(
            f"y holds label(s) {np.unique(y[unknown]).tolist()} not in classes "
            f"{np.asarray(classes).tolist()}; pass every label on the first call "
            "(classes=...)."
        )


@contextlib.contextmanager
def non_finite_explained(what):
    """Around ``validate_data`` of a map estimator: scikit-learn's NaN and infinity errors
    (whose advice is to impute) say instead what to do with observations or queries."""
    try:
        yield
    except ValueError as exc:
        text = str(exc)
        if not text.startswith("Input") or not any(
            word in text for word in ("contains NaN", "contains infinity")
        ):
            raise
        first = text.split("\n")[0].split(" or a value too large")[0].rstrip(".")
        advice = {
            "observations": "Observations must be finite: drop those rows (range readings "
            "of NaN or inf given to skoccmap.scans_to_observations become no-return beams).",
            "queries": "Query points must be finite.",
        }[what]
        raise ValueError(f"{first}. {advice}") from None


def validate_queries(estimator, X, y=None):
    """``validate_data(estimator, X, reset=False)`` of a fitted estimator's queries (or, with
    ``y``, of a later batch of observations), with a hint where they are points while the
    estimator takes segment rows."""
    from sklearn.utils.validation import validate_data

    what = "queries" if y is None else "observations"
    data = (X,) if y is None else (X, y)
    try:
        with non_finite_explained(what):
            return validate_data(
                estimator, *data, reset=False, dtype=np.float64, ensure_min_samples=0
            )
    except ValueError as exc:
        n_features = getattr(estimator, "n_features_in_", None)
        try:
            shape = np.shape(X)
        except ValueError:  # rows of different lengths, which the error above names
            shape = None
        segments = getattr(estimator, "layout", "segments") != "points"
        hint = segments and n_features and n_features % 2 == 0 and shape is not None
        if hint and shape[1:] == (n_features // 2,):
            raise ValueError(
                f"{exc} The {what} look like points of {n_features // 2} coordinates; the "
                "estimator takes segment rows [start, end] (a point is a zero-length "
                "segment): pass skoccmap.as_segments(points)."
            ) from None
        raise


# No laser's beams have a median length this long (metres); coordinates in millimetres give
# thousands.
_LONGEST_MEDIAN_BEAM = 500.0


def warn_unless_metres(starts, ends):
    """Warn where the beams' median length says the coordinates are not in metres.

    Every length default of the package (beam pieces, cells, length scales) is in metres;
    millimetres make a fit thousands of times slower and its map meaningless, silently.
    """
    lengths = np.linalg.norm(ends - starts, axis=1)
    lengths = lengths[lengths > 0]
    if lengths.size and np.median(lengths) > _LONGEST_MEDIAN_BEAM:
        warn(
            f"The beams' median length is {np.median(lengths):.4g}: as metres, beyond any "
            "laser's range. skoccmap reads coordinates in metres (its beam pieces, cells and "
            "length scales are in metres); were these millimetres? Divide X by 1000.",
            UserWarning,
        )


# Coarsest float32 step (metres) at which a warning is not needed: 2**-7 m, that of
# coordinates below 131 072 m; UTM northings (4e6 m) step by 0.25 or 0.5 m.
_FINEST_FLOAT32_STEP = 2.0**-7


def warn_if_coarse_float32(X_in, X):
    """Warn where ``X_in`` held float32 coordinates whose steps, at the size of ``X`` (its
    float64 copy), are more than ``_FINEST_FLOAT32_STEP``: the map cannot be finer than
    the data's rounding, which no later cast undoes."""
    dtypes = getattr(X_in, "dtypes", None)  # a DataFrame's columns
    dtype = np.result_type(*dtypes) if dtypes is not None else getattr(X_in, "dtype", None)
    if dtype != np.float32 or not X.size:
        return
    largest = np.float32(max(np.max(X), -np.min(X)))
    step = float(np.spacing(largest))
    if step > _FINEST_FLOAT32_STEP:
        warn(
            f"X is float32 and holds coordinates up to {largest:.3g}, where float32 steps "
            f"are {step:.3g} m: the map cannot be finer than that. Pass float64 "
            "coordinates, or subtract an origin (such as the first pose) first.",
            UserWarning,
        )


def is_number(value):
    """Whether ``value`` is a real number (Python or numpy scalar), not a bool: ``True``
    would read as 1, and text is no number however ``float`` reads it."""
    return isinstance(value, Real) and not isinstance(value, bool)


# Coordinates beyond this overflow in squared sums over many points (float max ~1.8e308).
MAX_COORDINATE = 1e100


def check_magnitude(X, name="X"):
    """``X``, or a ValueError for coordinates whose squares (squared distances and lengths,
    the Normal-Wishart statistics) would overflow to inf and the results to NaN."""
    # Largest and smallest apart: no array of absolute values the size of X (every kernel
    # call and every fit checks its segments).
    largest = max(np.max(X), -np.min(X)) if X.size else 0.0
    if largest > MAX_COORDINATE:
        raise ValueError(
            f"{name} holds coordinates up to {largest:.3g} in absolute value; beyond "
            f"{MAX_COORDINATE:g} their squares overflow. Rescale or shift the data."
        )
    return X


def check_segments(X, *, name="X", allow_empty=False):
    """Return ``X`` as a float array of segment rows ``[start, end]``.

    Parameters
    ----------
    X : array-like of shape (n_samples, 2 * n_dims)
        Segment rows; a point is a zero-length segment.
    name : str, default="X"
        Argument name used in error messages.
    allow_empty : bool, default=False
        Whether zero rows are accepted.

    Returns
    -------
    X : ndarray of shape (n_samples, 2 * n_dims), dtype float64

    Raises
    ------
    ValueError
        If ``X`` is not 2-D, has an odd number of columns, holds NaN or inf, or holds
        coordinates beyond 1e100 in absolute value (their squares overflow).
    TypeError
        If ``X`` is a sparse matrix.
    """
    if sparse.issparse(X):
        raise TypeError(
            f"{name} is a sparse matrix; segment rows must be dense: pass {name}.toarray()."
        )
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2:
        raise ValueError(
            f"{name} must be a 2-D array of segment rows [start, end], got {X.ndim} dimension(s)."
        )
    if X.shape[1] == 0 or X.shape[1] % 2:
        raise ValueError(
            f"{name} has {X.shape[1]} column(s); segment rows [start_1..start_D, end_1..end_D] "
            "need an even number of columns (2*D). Turn points into zero-length segments "
            "with skoccmap.observations.as_segments."
        )
    if not allow_empty and X.shape[0] == 0:
        raise ValueError(f"{name} has no rows.")
    if not np.all(np.isfinite(X)):
        raise ValueError(f"{name} contains NaN or infinite values; segments must be finite.")
    return check_magnitude(X, name)


def segment_dim(X):
    """Spatial dimension D of segment rows with 2*D columns."""
    return X.shape[1] // 2


@contextlib.contextmanager
def unfitted_on_error(estimator):
    """A fit that raises inside this block leaves ``estimator`` unfitted.

    The attributes a fit sets before its error would otherwise sit beside those of an
    earlier fit, and the estimator would predict from a mixture of the two without a word.
    Everything but the constructor's parameters and the metadata requests is removed.
    Outside scikit-learn's ``_fit_context``, so that a parameter refused there does so too.
    """
    try:
        yield
    except BaseException:
        # Constructor parameters stay, and so do metadata requests (set_fit_request...).
        kept = set(estimator.get_params(deep=False)) | {"_metadata_request"}
        for name in [name for name in vars(estimator) if name not in kept]:
            delattr(estimator, name)
        raise


def fit_or_unfitted(fit):
    """Decorate a ``fit`` method with :func:`unfitted_on_error`."""

    @functools.wraps(fit)
    def wrapper(self, *args, **kwargs):
        with unfitted_on_error(self):
            return fit(self, *args, **kwargs)

    return wrapper
