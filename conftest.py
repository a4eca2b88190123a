"""Doctests of optional features skip, rather than fail, where their extra is not installed.

``pytest --doctest-modules skoccmap`` then passes with ``pip install ".[test]"`` (which has
every extra, so CI runs them all) and with a bare install alike.
"""

import importlib.util

import pytest

# Doctests (module path, then object) that need a package of an extra.
_NEEDS = {
    "skoccmap.datasets._rosbag.": "rosbags",
    "skoccmap.grid.OccupancyGrid.to_ros_message": "rosbags",
    "skoccmap.grid.OccupancyGrid.write_rosbag": "rosbags",
}


def pytest_collection_modifyitems(config, items):
    for item in items:
        if getattr(item, "dtest", None) is None:  # not a doctest
            continue
        for prefix, package in _NEEDS.items():
            if item.name.startswith(prefix) and importlib.util.find_spec(package) is None:
                item.add_marker(
                    pytest.mark.skip(reason=f"needs {package} (pip install 'skoccmap[ros]')")
                )
