"""The suite compiles with two options of XLA's CPU compiler that it sets for speed
(``conftest.COMPILE_FLAGS``): they must not change a number, or the suite would test something
other than what a user runs. Three runs that cover the root finder's phases (fixed point,
Newton, a batch) and the step controller, compared bit for bit with the same runs in a
subprocess compiled without the options."""

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
from conftest import COMPILE_FLAGS

HERE = pathlib.Path(__file__).parent


def fingerprint():
    """A digest of the states and iteration counts of three runs on Kepler e = 0.6."""
    H = lambda q, p: 0.5 * (p @ p) - 1.0 / jnp.sqrt(q @ q)
    q0, p0 = jnp.array([0.4, 0.0]), jnp.array([0.0, 2.0])
    adaptive = gj.integrate(H, q0, p0, method=gj.CG(4, gj.gauss_legendre(4)), h=0.01, t1=7.0,
                            controller=gj.PIDController(1e-8, 1e-8))
    newton = gj.integrate(H, q0, p0, method=gj.DG(1, gj.gauss_legendre(2)), h=0.02, n_steps=300, save_every=30)
    batch = gj.sweep(H, gj.grid(method=gj.CG(2, gj.gauss_legendre(2)), h=[0.01, 0.02], state=[(q0, p0)]),
                     n_steps=300)
    arrays = [adaptive.q, adaptive.p, newton.q, newton.p, *jax.tree.leaves(batch)]
    arrays += [v for sol in (adaptive, newton) for v in jax.tree.leaves(sol.stats)]
    return hashlib.sha256(b"".join(np.asarray(a).tobytes() for a in arrays)).hexdigest()


def test_the_suites_compile_options_change_no_number():
    if os.environ.get("GALERKIN_JAX_TEST_FLAGS") != "on":
        pytest.skip("the suite runs without the compile options (GALERKIN_JAX_TEST_FLAGS)")
    plain = " ".join(f for f in os.environ.get("XLA_FLAGS", "").split() if f not in COMPILE_FLAGS)
    env = dict(os.environ, XLA_FLAGS=plain, GALERKIN_JAX_TEST_FLAGS="off", PYTHONPATH=os.pathsep.join(
        [str(HERE), str(HERE.parent), os.environ.get("PYTHONPATH", "")]))
    code = ("import jax; jax.config.update('jax_enable_x64', True); "
            "import test_compile_flags as t; print(t.fingerprint())")
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split()[-1] == fingerprint()
