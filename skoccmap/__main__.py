"""``python -m skoccmap``: the ``skoccmap`` command."""

import sys

from .cli import main

sys.exit(main())
