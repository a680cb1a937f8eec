"""The element Jacobian dR/dZ of cG(k) and dG(k) from the field's Jacobians at the quadrature
points (``_galerkin.galerkin_jacobian``), which the root finder's Newton matrices and the
implicit function theorem's dense tangents take in place of one tangent of R per unknown.

The scene: the planar pendulum chain (``scenes.pendulum_chain``), whose H is not separable (the
mass matrix depends on q), so that every term of the Jacobian's coupling is there.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import galerkin_jax as gj
from galerkin_jax import _galerkin, scenes

CHAIN = scenes.pendulum_chain(4, angle=1.0, momenta=1.0, seed=1)
METHODS = {
    "cG(1) + Gauss 1": gj.CG(1, gj.gauss_legendre(1)),
    "cG(3) + Gauss 3": gj.CG(3, gj.gauss_legendre(3)),
    "cG(3) + Lobatto 5": gj.CG(3, gj.gauss_lobatto(5)),
    "dG(0) + Radau 1": gj.DG(0, gj.gauss_radau(1)),
    "dG(2) + Radau 3": gj.DG(2, gj.gauss_radau(3)),
    "dG(1) + Gauss 3": gj.DG(1, gj.gauss_legendre(3)),
}


@pytest.mark.parametrize("name", METHODS)
def test_the_jacobian_from_the_points_equals_the_residuals_own(name):
    """At unknowns away from the root and h = 0.7: the largest difference from ``jax.jacfwd`` of
    the residual, measured 1.1e-16 to 2.2e-16 of entries up to about 5 (a rounding of the
    coupling's sum), below 1e-14: room for another order of summation, and far below any
    wrong term (each is h times a field derivative, of order 0.1 to 1)."""
    method, h = METHODS[name], 0.7
    q0, p0 = jnp.asarray(CHAIN.q0), jnp.asarray(CHAIN.p0)
    Z = 0.2 * jax.random.normal(jax.random.PRNGKey(0), method.initial_guess(q0, p0).shape)
    own = jax.jit(jax.jacfwd(lambda Z: method.residual(CHAIN.H, q0, p0, Z, h).reshape(-1)))(Z).reshape(Z.size, Z.size)
    np.testing.assert_allclose(jax.jit(lambda Z: method.jacobian(CHAIN.H, q0, p0, Z, h))(Z), own, rtol=0, atol=1e-14)


def test_runs_and_gradients_with_either_jacobian_agree(monkeypatch):
    """Long elements (h = 0.5 and 0.25, Newton matrices in most elements) of cG(4) and dG(1): with and without
    the method's ``jacobian``, the same updates and statuses, end states within 1e-13 and
    gradients (the dense tangent) within 1e-11 relative. The two matrices differ by round-off
    alone, which the stopping rule and the tangent's solve leave at round-off: measured equal to
    the bit; the margins allow another CPU's rounding of the matrices."""
    methods = ((gj.CG(4, gj.gauss_legendre(4)), 0.5), (gj.DG(1, gj.gauss_radau(2)), 0.25))

    def outputs():
        results = []
        for method, h in methods:
            def run(q0):
                sol = gj.integrate(CHAIN.H, q0, jnp.asarray(CHAIN.p0), method=method, h=h, n_steps=12,
                                   save_every=12, error_estimate=False)
                return sol.q[-1] @ sol.q[-1] + sol.p[-1] @ sol.p[-1], sol

            (_, sol), gradient = jax.value_and_grad(run, has_aux=True)(jnp.asarray(CHAIN.q0))
            results.append((int(sol.status), int(sol.stats["num_newton_iterations"]), np.asarray(sol.q[-1]),
                            np.asarray(gradient)))
        return results

    structured = outputs()
    for cls in (_galerkin.CG, _galerkin.DG):
        monkeypatch.delattr(cls, "jacobian")
    by_tangents = outputs()
    for (status, updates, q, g), (status_b, updates_b, q_b, g_b) in zip(structured, by_tangents):
        assert status == status_b == 0 and updates == updates_b
        np.testing.assert_allclose(q, q_b, rtol=0, atol=1e-13)
        np.testing.assert_allclose(g, g_b, rtol=1e-11)


def test_a_subclass_that_redefines_the_residual_alone_takes_its_tangents():
    """A subclass of CG whose residual is 2 R: its inherited ``jacobian`` (that of R) is not its
    own, so Newton and the tangent take 2R's tangents: the same root and gradient as CG's (within
    1e-12: the two solves' round-off). With R's Jacobian against 2R's equations the tangent
    would be twice the true one."""

    @gj.pytree_dataclass
    class Doubled(gj.CG):
        def residual(self, H, q0, p0, C, h, part=None):
            return 2.0 * super().residual(H, q0, p0, C, h, part)

    def gradient(method):
        return jax.grad(lambda q0: gj.integrate(CHAIN.H, q0, jnp.asarray(CHAIN.p0), method=method, h=0.5, n_steps=4,
                                                save_every=4).q[-1] @ jnp.ones(4))(jnp.asarray(CHAIN.q0))

    rule = gj.gauss_legendre(3)
    np.testing.assert_allclose(gradient(Doubled(3, rule)), gradient(gj.CG(3, rule)), rtol=1e-12)
