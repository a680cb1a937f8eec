"""The suite compiles with two options of XLA's CPU compiler that it sets for speed
(``conftest.COMPILE_FLAGS``): they must not change the integrator's numbers, or the suite would
test something other than what a user runs. One program that takes every phase of the root finder (Newton in
a small system's first element, then the fixed point), the step controller and a batch (a
vmapped controlled run), compared bit for bit with the same program in a subprocess compiled
without the options."""

import hashlib
import os
import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
from conftest import user_xla_flags

HERE = pathlib.Path(__file__).parent


def fingerprint():
    """A digest of the states and counts of two controlled Kepler runs (e = 0.6 and 0.7), vmapped,
    and their error estimates. The estimates (about 1e-15, round-off themselves: the largest local
    error of a run at rtol 1e-8 is at the floor) are a reduction, which the options may round
    differently; they are compared to eps."""
    H = lambda q, p: 0.5 * (p @ p) - 1.0 / jnp.sqrt(q @ q)
    q0 = jnp.array([[0.4, 0.0], [0.3, 0.0]])
    p0 = jnp.array([[0.0, 2.0], [0.0, np.sqrt(1.7 / 0.3)]])
    run = lambda q0, p0: gj.integrate(H, q0, p0, method=gj.CG(4, gj.gauss_legendre(4)), h=0.01, t1=7.0,
                                      controller=gj.PIDController(1e-8, 1e-8))
    sol = jax.vmap(run)(q0, p0)
    arrays = [sol.q, sol.p, *jax.tree.leaves(sol.stats)]
    digest = hashlib.sha256(b"".join(np.asarray(a).tobytes() for a in arrays)).hexdigest()
    return digest + " " + " ".join(repr(float(e)) for e in sol.error_estimate)


def test_the_suites_compile_options_change_no_number():
    if os.environ.get("GALERKIN_JAX_TEST_FLAGS") != "on":
        pytest.skip("the suite runs without the compile options (GALERKIN_JAX_TEST_FLAGS)")
    env = dict(os.environ, XLA_FLAGS=user_xla_flags(), GALERKIN_JAX_TEST_FLAGS="off", PYTHONPATH=os.pathsep.join(
        [str(HERE), str(HERE.parent), os.environ.get("PYTHONPATH", "")]))
    code = ("import jax; jax.config.update('jax_enable_x64', True); "
            "import test_compile_flags as t; print(t.fingerprint())")
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    theirs, ours = done.stdout.splitlines()[-1].split(), fingerprint().split()
    assert theirs[0] == ours[0]
    np.testing.assert_allclose(np.array(theirs[1:], float), np.array(ours[1:], float), rtol=0,
                               atol=np.finfo(float).eps)
