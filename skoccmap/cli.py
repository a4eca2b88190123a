"""The ``skoccmap`` command.

Each subcommand lives in its own module ``skoccmap._cmd_<name>`` exposing
``add_arguments(parser)`` and ``run(args) -> int``; heavy imports happen inside ``run``.
"""

import argparse
import importlib
import sys
import warnings

SUBCOMMANDS = {
    "demo": "reproduce the paper's simulation experiment (tables, figures, maps)",
    "map": "build an occupancy map from a CARMEN laser log or a ROS bag",
    "evaluate": "score a map on held-out scans of a CARMEN log or a ROS bag against "
    "counting grids",
}


def build_parser():
    from skoccmap import __version__

    parser = argparse.ArgumentParser(
        prog="skoccmap",
        description="Occupancy maps from laser scans with a mixture of Gaussian-process experts.",
    )
    parser.add_argument("--version", action="version", version=f"skoccmap {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, help_text in SUBCOMMANDS.items():
        module = importlib.import_module(f"skoccmap._cmd_{name}")
        command = sub.add_parser(name, help=help_text, description=help_text)
        module.add_arguments(command)
        command.set_defaults(_run=module.run)
    return parser


def main(argv=None):
    args = build_parser().parse_args(argv)
    return args._run(args)


def _print_warning(message, category, filename, lineno, file=None, line=None):
    print(f"skoccmap: {category.__name__}: {message}", file=sys.stderr if file is None else file)


def console_main(argv=None):
    """:func:`main` for the installed command and ``python -m skoccmap``: warnings print as
    ``skoccmap: UserWarning: ...``, not with the line of the launcher script that the
    library's warnings would otherwise point at."""
    warnings.showwarning = _print_warning
    return main(argv)


if __name__ == "__main__":
    sys.exit(console_main())
