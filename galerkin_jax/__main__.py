"""``python -m galerkin_jax``: the ``galerkin-jax`` command line tool (``cli.console``)."""

import sys

from .cli import console

sys.exit(console())
