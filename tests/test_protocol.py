"""The method protocol (``gj.AbstractMethod``): a method written outside the library runs
through every entry point, and a class that does not implement it is rejected before tracing."""

import pathlib
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
import helpers

DOCS = pathlib.Path(__file__).resolve().parents[1] / "docs" / "methods_protocol.md"


@gj.pytree_dataclass
class ImplicitMidpoint(gj.AbstractMethod):
    """z1 = z0 + h J DH((z0 + z1) / 2); unknowns: dz = z1 - z0, shape (1, 2d)."""

    fixed_point = True  # R = dz - h J DH(z0 + dz / 2): dR/d(dz) = I at h = 0
    partition_axis = -1  # dz = (dq | dp)

    def initial_guess(self, q0, p0, previous=None):
        if previous is None:
            return jnp.zeros((1, 2 * q0.shape[0]), q0.dtype)
        return previous[2]

    def residual(self, H, q0, p0, Z, h, part=None):
        dq, dp = jnp.split(Z[0], 2)
        dHdq, dHdp = jax.grad(H, argnums=(0, 1))(q0 + 0.5 * dq, p0 + 0.5 * dp)
        r_q, r_p = dq - h * dHdp, dp + h * dHdq
        return {None: jnp.concatenate([r_q, r_p]), "q": r_q, "p": r_p}[part][None, :]

    def increment(self, H, q0, p0, Z, h):
        return tuple(jnp.split(Z[0], 2))

    def polynomial(self, H, q0, p0, Z, h):
        return jnp.concatenate([0.5 * Z, 0.5 * Z])  # alpha dz = (P_0 + P_1) dz / 2


def chain(d=12):
    """A nonlinear chain of d masses, fixed ends: d > 8 takes the Gauss-Seidel sweep."""

    def H(q, p):
        stretch = jnp.diff(jnp.concatenate([jnp.zeros(1), q, jnp.zeros(1)]))
        return 0.5 * p @ p + 0.5 * stretch @ stretch + 0.25 * jnp.sum(stretch**4)

    return H, jnp.asarray(0.3 * np.sin(np.linspace(0.0, 3.0, d))), jnp.asarray(0.2 * np.cos(np.arange(d)))


SCENES = {"kepler": (*helpers.kepler(0.5), 0.01, 4000), "chain": (*chain(), 0.05, 1000)}


@pytest.mark.parametrize("scene", SCENES)
def test_implicit_midpoint_method_equals_cg1_midpoint_through_integrate(scene):
    """The same equations as cG(1) with the midpoint rule [GBS, eq. (16), k = 1], in another
    basis: states, error estimates and dense output agree to round-off over thousands of steps."""
    H, q0, p0, h, n = SCENES[scene]
    mine = gj.integrate(H, q0, p0, method=ImplicitMidpoint(), h=h, n_steps=n, save_every=10, dense=True)
    builtin = gj.integrate(H, q0, p0, method=gj.CG(1, gj.midpoint()), h=h, n_steps=n, save_every=10, dense=True)
    assert int(mine.status) == int(builtin.status) == 0
    scale = float(jnp.abs(jnp.concatenate([builtin.q, builtin.p])).max())
    difference = max(float(jnp.abs(mine.q - builtin.q).max()), float(jnp.abs(mine.p - builtin.p).max()))
    # measured 0 (bitwise, with equal iteration counts) on both scenes; allowed: the random
    # walk of a few eps per step that a rounding difference in either residual would start
    assert difference <= 10 * np.sqrt(n) * np.finfo(np.float64).eps * scale
    # the inherited estimate is the built-in one, from the same polynomial (measured: bitwise)
    np.testing.assert_allclose(mine.error_estimate, builtin.error_estimate, rtol=1e-12)
    t = jnp.linspace(0.0, n * h, 37)
    np.testing.assert_allclose(jnp.concatenate(mine.evaluate(t)), jnp.concatenate(builtin.evaluate(t)),
                               atol=100 * np.finfo(np.float64).eps * scale)  # measured: 0


def test_a_user_method_steps_sweeps_vmaps_and_differentiates():
    """``step``, ``sweep``, and ``vmap`` over h of ``grad`` through the run (implicit function
    theorem), against cG(1) with the midpoint rule."""
    H, q0, p0 = helpers.kepler(0.5)
    method, cg1 = ImplicitMidpoint(), gj.CG(1, gj.midpoint())
    np.testing.assert_array_equal(jnp.concatenate(gj.step(H, q0, p0, method=method, h=0.1)),
                                  jnp.concatenate(gj.step(H, q0, p0, method=cg1, h=0.1)))  # measured: bitwise
    swept = [gj.sweep(H, gj.grid(method=m, h=[0.01, 0.02], state=(q0, p0)), n_steps=50) for m in (method, cg1)]
    np.testing.assert_array_equal(swept[0].status, [0, 0])
    np.testing.assert_array_equal(swept[0].q, swept[1].q)  # measured: bitwise

    def energy(h, m):
        sol = gj.integrate(H, q0, p0, method=m, h=h, n_steps=20, save_every=20)
        return H(sol.q[-1], sol.p[-1])

    hs = jnp.array([0.01, 0.02])
    mine, builtin = (jax.jit(jax.vmap(jax.value_and_grad(lambda h: energy(h, m))))(hs) for m in (method, cg1))
    assert np.all(np.abs(np.asarray(mine[1])) > 1e-6)  # dE/dh of a symplectic one-step map: small, not zero
    np.testing.assert_array_equal(mine[0], builtin[0])  # measured: bitwise (the same iterates)
    # the tangents solve with Jacobians of two differently written residuals, which round
    # differently: measured 4.9e-14 relative; 1e-12 is 20 times that
    np.testing.assert_allclose(mine[1], builtin[1], rtol=1e-12)


class Counting:
    """H that counts its calls: a trace calls it, a check before tracing does not."""

    def __init__(self, H):
        self.H, self.calls = H, 0

    def __call__(self, q, p):
        self.calls += 1
        return self.H(q, p)


@gj.pytree_dataclass
class DuckTyped:
    """Written to the protocol without its base class, and missing ``increment``."""

    fixed_point = True
    initial_guess, residual = ImplicitMidpoint.initial_guess, ImplicitMidpoint.residual
    polynomial, local_error = ImplicitMidpoint.polynomial, gj.AbstractMethod.local_error


class Unregistered(gj.AbstractMethod):
    """Every member, but not a pytree."""

    initial_guess, residual, increment, polynomial = (ImplicitMidpoint.initial_guess, ImplicitMidpoint.residual,
                                                      ImplicitMidpoint.increment, ImplicitMidpoint.polynomial)


@gj.pytree_dataclass
class PartitionWithoutPart(ImplicitMidpoint):
    def residual(self, H, q0, p0, Z, h):
        return ImplicitMidpoint.residual(self, H, q0, p0, Z, h)


@gj.pytree_dataclass
class TracedFixedPoint(ImplicitMidpoint):
    fixed_point = np.float64(1.0)


BAD = [
    (DuckTyped(), r"method must be a galerkin_jax method .* gj.AbstractMethod; DuckTyped lacks increment\."),
    (Unregistered(), r"Unregistered must be a pytree .* @gj.pytree_dataclass"),
    (PartitionWithoutPart(), r"has a partition_axis, so its residual must take part="),
    (TracedFixedPoint(), r"TracedFixedPoint.fixed_point must be a Python bool"),
    (object(), r"object lacks initial_guess, residual, increment, polynomial, local_error, fixed_point\."),
]


@pytest.mark.parametrize("method, match", BAD, ids=[type(m).__name__ for m, _ in BAD])
@pytest.mark.parametrize("entry", ["integrate", "step", "grid"])
def test_a_method_that_breaks_the_protocol_is_rejected_before_tracing(method, match, entry):
    H, q0, p0 = helpers.kepler(0.5)
    counted = Counting(H)
    calls = {"integrate": lambda: gj.integrate(counted, q0, p0, method=method, h=0.1, n_steps=2),
             "step": lambda: gj.step(counted, q0, p0, method=method, h=0.1),
             "grid": lambda: gj.grid(method=[method], h=0.1, state=(q0, p0))}
    with pytest.raises(TypeError, match=match):
        calls[entry]()
    assert counted.calls == 0


def test_an_abstract_member_left_out_fails_at_construction():
    class NoResidual(gj.AbstractMethod):
        initial_guess, increment, polynomial = (ImplicitMidpoint.initial_guess, ImplicitMidpoint.increment,
                                                ImplicitMidpoint.polynomial)

    with pytest.raises(TypeError, match="abstract method.*residual"):
        gj.pytree_dataclass(NoResidual)()


def test_the_walkthrough_on_the_docs_page_runs_and_agrees():
    """docs/methods_protocol.md's code blocks, run in order: the page cannot go stale."""
    blocks = re.findall(r"```python\n(.*?)```", DOCS.read_text(), flags=re.S)
    namespace = {}
    exec(compile("\n".join(blocks), str(DOCS), "exec"), namespace)
    mine, builtin = namespace["mine"], namespace["builtin"]
    assert int(mine.status) == 0
    np.testing.assert_allclose(mine.q, builtin.q, rtol=0, atol=1e-13)
