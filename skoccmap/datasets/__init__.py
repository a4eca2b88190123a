"""Data sets: a laser simulator, the paper's simulated environment, an office, a 3-D room;
readers for CARMEN logs and ROS bags."""

from ._carmen import flaser_angles, load_carmen
from ._office import make_office_environment, make_office_scans
from ._paper import make_paper_environment, make_paper_scans
from ._room3d import Room3D, make_room3d_environment, make_room3d_scans, scanner_directions
from ._rosbag import load_rosbag, write_rosbag
from ._simulator import Environment2D, simulate_scans

__all__ = [
    "Environment2D",
    "Room3D",
    "flaser_angles",
    "load_carmen",
    "load_rosbag",
    "make_office_environment",
    "make_office_scans",
    "make_paper_environment",
    "make_paper_scans",
    "make_room3d_environment",
    "make_room3d_scans",
    "scanner_directions",
    "simulate_scans",
    "write_rosbag",
]
