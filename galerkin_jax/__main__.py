"""``python -m galerkin_jax``: the ``galerkin-jax`` command line tool (``cli.main``)."""

import sys

from .cli import main

sys.exit(main())
