import os
import subprocess
import sys

import jax
import pytest

# The suite's time is mostly XLA's CPU compiler. These two of its options make it compile in
# about two thirds of the time. The integrator's runs come out the same, bit for bit
# (tests/test_compile_flags.py checks one that takes every phase of the root finder against a
# subprocess without them); the fusion emitters' option can round a reduction differently, which
# an optimisation over many Adam steps amplifies (notebooks/05_tuning.ipynb: a loss reduced 8.2x
# instead of 7.0x), so the notebooks, whose committed outputs are compared digit by digit, run
# with the user's flags (``user_xla_flags``). The claims the suite tests hold with margins that
# any such rounding keeps. Set here, before the backend starts, and inherited by pytest-xdist's
# workers and every subprocess. A jaxlib that no longer knows one of them would abort at its
# first computation: a probe in a subprocess decides, once, in the process that starts the
# workers, and records its verdict in GALERKIN_JAX_TEST_FLAGS; set that to "off" beforehand to
# run the suite without them.
COMPILE_FLAGS = ("--xla_llvm_disable_expensive_passes=true", "--xla_cpu_use_fusion_emitters=false")


def user_xla_flags():
    """``XLA_FLAGS`` as the suite found it, without its compile options."""
    return os.environ.get("GALERKIN_JAX_USER_XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))


def _with_compile_flags():
    flags = os.environ.get("XLA_FLAGS", "")
    if os.environ.get("GALERKIN_JAX_TEST_FLAGS") is not None or all(f in flags for f in COMPILE_FLAGS):
        return
    candidate = " ".join([flags, *COMPILE_FLAGS]).strip()
    probe = subprocess.run([sys.executable, "-c", "import jax.numpy as jnp; jnp.zeros(1).block_until_ready()"],
                           env=dict(os.environ, XLA_FLAGS=candidate), capture_output=True, timeout=120)
    os.environ["GALERKIN_JAX_TEST_FLAGS"] = "on" if probe.returncode == 0 else "off"
    os.environ["GALERKIN_JAX_USER_XLA_FLAGS"] = flags
    if probe.returncode == 0:
        os.environ["XLA_FLAGS"] = candidate


_with_compile_flags()
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")  # no silent broadcasting


@pytest.fixture(scope="module", autouse=True)
def _free_compiled_programs():
    """Drop JAX's compiled programs after each test module. XLA's CPU backend maps a few
    hundred memory regions per compiled program (measured ~400 for one integrate), so a
    worker that keeps a few hundred programs reaches the kernel's vm.max_map_count (65530 by
    default) and crashes inside the next compilation."""
    yield
    import gc

    jax.clear_caches()
    gc.collect()
