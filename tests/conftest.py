import os
import pathlib
import subprocess
import sys

import jax
import pytest

# The suite's time is mostly XLA's CPU compiler. Two options of it (fusion emitters off, LLVM's
# expensive passes off) make it compile in about two thirds of the time. They change no
# operation, only how a reduction may be rounded (the order of its sum): the runs that
# tests/test_compile_flags.py compares come out the same bit for bit; others, as on another CPU,
# may not, and the suite's claims hold with margins that such rounding keeps. The notebooks, whose
# committed outputs are compared digit by digit, run with the user's flags (``user_xla_flags``).
# What was measured: notes/performance-studies.md, "Compile time". Set here, before the backend starts,
# and inherited by pytest-xdist's workers and every subprocess. A jaxlib that does not know an
# option would abort at its first computation: probes in subprocesses keep those it knows, once,
# in the process that starts the workers, and record the verdict in GALERKIN_JAX_TEST_FLAGS; set
# that to "off" beforehand to run the suite without them.
COMPILE_FLAGS = ("--xla_llvm_disable_expensive_passes=true", "--xla_cpu_use_fusion_emitters=false")


def user_xla_flags():
    """``XLA_FLAGS`` as the suite found it, without its compile options."""
    return os.environ.get("GALERKIN_JAX_USER_XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))


def _known(flags):
    probe = subprocess.run([sys.executable, "-c", "import jax.numpy as jnp; jnp.zeros(1).block_until_ready()"],
                           env=dict(os.environ, XLA_FLAGS=" ".join(flags)), capture_output=True, timeout=120)
    return probe.returncode == 0


def _with_compile_flags():
    flags = os.environ.get("XLA_FLAGS", "")
    if os.environ.get("GALERKIN_JAX_TEST_FLAGS") is not None:
        return
    chosen = [flags, *COMPILE_FLAGS]
    if not _known(chosen):  # one at a time: keep those this jaxlib knows
        chosen = [flags]
        for flag in COMPILE_FLAGS:
            chosen += [flag] if _known(chosen + [flag]) else []
    os.environ["GALERKIN_JAX_TEST_FLAGS"] = "on" if len(chosen) > 1 else "off"
    os.environ["GALERKIN_JAX_USER_XLA_FLAGS"] = flags
    os.environ["XLA_FLAGS"] = " ".join(chosen).strip()


_with_compile_flags()
# The suite keeps no compiled program on disk: the README's tour, run by tests/test_docs.py,
# calls gj.use_compilation_cache(), which would otherwise write every later program of that
# worker into the user's cache folder and load programs of earlier runs from it.
os.environ["GALERKIN_JAX_CACHE"] = ""
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")  # no silent broadcasting


# The suite's two tiers. The default one covers every line and branch of galerkin_jax that the
# whole suite covers (.ci/check_coverage.py checks it in CI); the slow tier holds the other tests,
# those listed in slow.txt (.ci/tiers.py chose them from a measured run of the whole suite).
SLOW = {line.strip() for line in pathlib.Path(__file__).with_name("slow.txt").read_text().splitlines()
        if line.strip() and not line.startswith("#")}


def pytest_addoption(parser):
    parser.addoption("--tier", choices=("default", "slow", "all"), default="default",
                     help="default: the tests that cover the library (minutes); slow: the others "
                          "(tests/slow.txt); all: both")


def _named(config):
    """The tests named on the command line (``FILE::TEST``): they run whatever their tier."""
    named = []
    for arg in config.args:
        path, sep, test = arg.partition("::")
        if sep:
            named.append(f"{os.path.relpath(os.path.abspath(path), config.rootpath)}::{test}")
    return tuple(named)


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    tier = config.getoption("tier")
    for item in items:
        if item.nodeid in SLOW:
            item.add_marker(pytest.mark.slow)
    if tier == "all":
        return
    named = _named(config)
    chosen = [(item.nodeid in SLOW) == (tier == "slow") or item.nodeid.startswith(named) for item in items]
    config.hook.pytest_deselected(items=[item for item, keep in zip(items, chosen) if not keep])
    items[:] = [item for item, keep in zip(items, chosen) if keep]


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
