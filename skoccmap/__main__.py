"""``python -m skoccmap``: the ``skoccmap`` command."""

import sys

from .cli import console_main

# Guarded as in cli.py: importing the module (documentation tools, package walkers) must
# not run the command and exit the interpreter.
if __name__ == "__main__":
    sys.exit(console_main())
