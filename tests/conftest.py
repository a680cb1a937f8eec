import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")  # no silent broadcasting

# Workaround, tests only: in ~40 % of runs of test_integrate + test_transforms +
# test_amplification in one process (1 in 8 full runs), every dG(1) amplification matrix of
# one compiled function came out as cG(1)'s, consistently within that process. Keeping every
# jnp.asarray result alive made 5 of 5 such runs pass, which points at JAX (0.10) taking a
# freed temporary's id for a new constant during tracing (DynamicJaxprTrace.new_const keys
# constants by id()). The cause is not pinned down; see the README's known issues.
import jax.numpy as _jnp  # noqa: E402

_KEPT = []
_asarray = _jnp.asarray


def _asarray_kept(*args, **kwargs):
    out = _asarray(*args, **kwargs)
    _KEPT.append(out)
    return out


_jnp.asarray = _asarray_kept
