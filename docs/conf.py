"""Sphinx configuration for the skoccmap documentation."""

import os
import socket
import threading
from urllib.parse import urlsplit

from docutils import nodes

import skoccmap

project = "skoccmap"
author = "skoccmap developers"
copyright = "2026, skoccmap developers"
version = release = skoccmap.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.intersphinx",
    "sphinx.ext.mathjax",
    "numpydoc",
    "sphinx_gallery.gen_gallery",
]

autosummary_generate = True
# Class pages document the methods defined in the class and module pages their functions
# (autosummary's own templates list them in tables that link nowhere).
templates_path = ["_templates"]
numpydoc_show_class_members = False
exclude_patterns = ["_build", "auto_examples/*.ipynb"]
html_theme = "pydata_sphinx_theme"

SKLEARN_DOCS = "https://scikit-learn.org/stable/"
_INVENTORIES = {
    "python": ("https://docs.python.org/3", None),
    "numpy": ("https://numpy.org/doc/stable/", None),
    "scipy": ("https://docs.scipy.org/doc/scipy/", None),
    "sklearn": (SKLEARN_DOCS, None),
}


def _reachable(url, timeout=3.0):
    """Whether a TCP connection to the URL's host opens within ``timeout`` seconds.

    Runs in a daemon thread so that a hanging name lookup cannot stall the build either.
    """
    parts = urlsplit(url)
    port = parts.port or (443 if parts.scheme == "https" else 80)
    result = []

    def probe():
        try:
            socket.create_connection((parts.hostname, port), timeout=timeout).close()
            result.append(True)
        except OSError:
            result.append(False)

    thread = threading.Thread(target=probe, daemon=True)
    thread.start()
    thread.join(timeout)
    return bool(result and result[0])


# Cross-links to Python, NumPy, SciPy and scikit-learn need their inventories from the web.
# Offline (or with SKOCCMAP_DOCS_OFFLINE=1) they are left out, so that ``sphinx-build -W``
# builds without a network: references to those projects then render as plain text.
if os.environ.get("SKOCCMAP_DOCS_OFFLINE", "") not in ("", "0"):
    intersphinx_mapping = {}
else:
    intersphinx_mapping = {
        name: target for name, target in _INVENTORIES.items() if _reachable(target[0])
    }

# Labels of scikit-learn's documentation that inherited docstrings refer to with :ref:
# (``ClassifierMixin.score`` links its "accuracy" to ``accuracy_score``). Without the
# scikit-learn inventory they resolve to these pages directly.
_SKLEARN_LABELS = {
    "accuracy_score": "modules/model_evaluation.html#accuracy-score",
}


def _sklearn_label(app, env, node, contnode):
    target = node.get("reftarget")
    if node.get("refdomain") != "std" or target not in _SKLEARN_LABELS:
        return None
    link = nodes.reference("", "", internal=False, refuri=SKLEARN_DOCS + _SKLEARN_LABELS[target])
    link.append(contnode)
    return link


def _skip_member(app, what, name, obj, skip, options):
    # scikit-learn adds set_{method}_request to every estimator: its metadata routing,
    # documented there, not ours. A named tuple's fields are its docstring's Attributes.
    if name.startswith("set_") and name.endswith("_request"):
        return True
    if (getattr(obj, "__doc__", None) or "").startswith("Alias for field number"):
        return True
    return None


def setup(app):
    app.connect("autodoc-skip-member", _skip_member)
    # After intersphinx (priority 500): its inventory answers first when it was loaded.
    app.connect("missing-reference", _sklearn_label, priority=900)


sphinx_gallery_conf = {
    "examples_dirs": "../examples",
    "gallery_dirs": "auto_examples",
    "filename_pattern": r"/plot_",
    "reference_url": {"skoccmap": None},
}
