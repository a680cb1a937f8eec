"""The main job: ``python -m galerkin_jax.demo`` is ``galerkin-jax run`` (Kepler, cG(3)).

Kept so that older instructions still work; extra arguments go to ``run``, e.g.
``python -m galerkin_jax.demo quartic --method mm``. See ``galerkin-jax --help``.
"""

import sys

from .cli import console

if __name__ == "__main__":
    sys.exit(console(["run", *sys.argv[1:]]))
