"""The peers every benchmark compares with: diffrax, SciPy ``solve_ivp``, and integrators written
directly in JAX (velocity Verlet and Gauss collocation by fixed-point iteration, each composable).

A peer of ``bench_peers`` is a factory ``make(H, T, knob) -> run`` with ``run(z0) -> (z1,
status)``: ``z0`` and ``z1`` are the state ``z = (q, p)`` of shape ``(2d,)`` at t = 0 and t = T,
status 0 on success; ``knob`` is the number of steps of ``T / knob`` (fixed steps) or ``rtol =
atol`` (adaptive). The steps themselves (``diffrax_solve``, ``verlet_step``, ``gauss_step``) serve
the other benchmarks' own loops. A JAX ``run`` is jitted by the caller; a SciPy ``run`` is plain
Python (``run.is_python``). The library never imports this.
"""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import scipy.integrate

# Gauss collocation's tables, Hairer-Lubich-Wanner Table II.1.2: s = 1 is the implicit midpoint rule
_R = np.sqrt(15.0)
GAUSS = {
    1: (np.array([[0.5]]), np.array([1.0])),
    3: (np.array([[5 / 36, 2 / 9 - _R / 15, 5 / 36 - _R / 30], [5 / 36 + _R / 24, 2 / 9, 5 / 36 - _R / 24],
                  [5 / 36 + _R / 30, 2 / 9 + _R / 15, 5 / 36]]), np.array([5 / 18, 4 / 9, 5 / 18])),
}
# Yoshida's fourth-order triple jump [Yoshida 1990]: the weights of a composition of a symmetric step
TRIPLE_JUMP = (1 / (2 - 2 ** (1 / 3)), -(2 ** (1 / 3)) / (2 - 2 ** (1 / 3)), 1 / (2 - 2 ** (1 / 3)))


def hamiltonian_field(H):
    """``f(z) = J DH(z)`` for ``z = (q, p)`` stacked: ``(dH/dp, -dH/dq)``."""
    dH = jax.grad(H, argnums=(0, 1))

    def f(z):
        d = z.shape[-1] // 2
        dq, dp = dH(z[:d], z[d:])
        return jnp.concatenate([dp, -dq])

    return f


def diffrax_solve(H, T, z0, solver, dt0, controller, max_steps):
    """diffrax from 0 to T on ``z = (q, p)``: ``(z1, status, accepted, rejected)``."""
    solution = diffrax.diffeqsolve(
        diffrax.ODETerm(lambda t, z, args: hamiltonian_field(H)(z)), solver, 0.0, T, dt0, z0,
        saveat=diffrax.SaveAt(t1=True), stepsize_controller=controller, max_steps=max_steps, throw=False,
    )
    status = jnp.where(solution.result == diffrax.RESULTS.successful, 0, 1)
    return solution.ys[-1], status, solution.stats["num_accepted_steps"], solution.stats["num_rejected_steps"]


def diffrax_peer(solver, pid=False, max_steps=1_000_000):
    """diffrax ``solver`` as a peer: ``n`` constant steps of ``T / n`` (the knob n; a few spare
    steps: the last is clipped to T) or, with ``pid``, a PID controller (the knob rtol = atol,
    the first step diffrax's)."""

    def make(H, T, knob):
        if pid:
            return lambda z0: diffrax_solve(H, T, z0, solver, None, diffrax.PIDController(rtol=knob, atol=knob),
                                            max_steps)[:2]
        return lambda z0: diffrax_solve(H, T, z0, solver, T / knob, diffrax.ConstantStepSize(), knob + 4)[:2]

    return make


def kvaerno5(tol=1e-13):
    """Kvaerno5 (ESDIRK, order 5) at fixed steps with ``optimistix.Newton(tol, tol)``: diffrax's
    default root finder (a chord method whose tolerances come from a step-size controller)
    diverges at constant steps."""
    return diffrax.Kvaerno5(root_finder=optx.Newton(rtol=tol, atol=tol))


def scipy_ivp(method):
    """``scipy.integrate.solve_ivp(method)`` with ``rtol = atol = tol`` (the knob). The right-hand
    side (and, for implicit methods, the Jacobian) is a compiled JAX function called from
    Python, so each call pays JAX's dispatch (a few microseconds)."""

    def make(H, T, tol):
        f = hamiltonian_field(H)
        fun = jax.jit(lambda z: f(z))
        jac = jax.jit(jax.jacfwd(f)) if method in ("Radau", "BDF", "LSODA") else None
        options = {} if jac is None else {"jac": lambda t, z: np.asarray(jac(z))}

        def run(z0):
            solution = scipy.integrate.solve_ivp(lambda t, z: np.asarray(fun(z)), (0.0, T), np.asarray(z0),
                                                 method=method, rtol=tol, atol=tol, **options)
            return solution.y[:, -1], 0 if solution.success else 1

        run.is_python = True
        return run

    return make


def verlet_step(H, h, weights=(1.0,)):
    """Velocity Verlet (kick-drift-kick) for separable H, composed with ``weights`` (one
    substep each): ``step((q, p, force)) -> (q, p, force)``, force = dH/dq at q carried from
    the substep before, so one gradient of V per substep (dH/dq is taken at the half-step
    momentum, which it does not depend on)."""
    dHq, dHp = jax.grad(H, argnums=0), jax.grad(H, argnums=1)

    def step(carry):
        q, p, force = carry
        for w in weights:
            p = p - 0.5 * w * h * force
            q = q + w * h * dHp(q, p)
            force = dHq(q, p)
            p = p - 0.5 * w * h * force
        return q, p, force

    return step


def leapfrog(H, T, n, weights=(1.0,)):
    """``verlet_step`` as a peer: n steps of T / n in a ``lax.scan``."""
    step = verlet_step(H, T / n, weights)

    def run(z0):
        q, p = jnp.split(z0, 2)
        (q, p, _), _ = jax.lax.scan(lambda c, _: (step(c), None), (q, p, jax.grad(H)(q, p)), None, length=n)
        return jnp.concatenate([q, p]), jnp.zeros((), jnp.int32)

    return run


def gauss_step(H, h, stages=3, weights=(1.0,), max_iterations=50):
    """Gauss collocation of ``stages`` stages (order 2s; s = 1: the implicit midpoint rule),
    composed with ``weights``, by fixed-point iteration on the stage increments Z_i = h sum_j
    a_ij f(z0 + Z_j), the usual choice for non-stiff problems [Hairer, Lubich, Wanner, Sect.
    VIII.6]: each substep's iteration starts from its own increments of the step before and
    stops at the round-off floor; z1 = z0 + b^T A^-1 Z (no further field evaluation).
    ``step((z, Zs, status, updates))``: Zs of shape (len(weights), s, 2d), status 1 once a
    substep took ``max_iterations``, updates counted (each ``stages`` field evaluations)."""
    f = hamiltonian_field(H)
    A, b = GAUSS[stages]
    A, d = jnp.asarray(A), jnp.asarray(np.linalg.solve(A.T, b))

    def substep(z, Z, w):
        tol = 10 * jnp.finfo(z.dtype).eps * (1 + jnp.max(jnp.abs(z)))

        def iterate(c):
            Z, _, i = c
            Z1 = w * h * A @ jax.vmap(f)(z[None] + Z)
            return Z1, jnp.max(jnp.abs(Z1 - Z)), i + 1

        Z, _, i = jax.lax.while_loop(lambda c: (c[1] > tol) & (c[2] < max_iterations), iterate, (Z, jnp.inf, 0))
        return z + d @ Z, Z, i

    def step(carry):
        z, Zs, status, updates = carry
        new = []
        for j, w in enumerate(weights):
            z, Z, i = substep(z, Zs[j], w)
            new.append(Z)
            status, updates = jnp.where(i >= max_iterations, 1, status), updates + i
        return z, jnp.stack(new), status, updates

    return step


def gauss_rk(H, T, n, stages=3):
    """``gauss_step`` as a peer: n steps of T / n in a ``lax.scan``."""
    step = gauss_step(H, T / n, stages)

    def run(z0):
        carry = (z0, jnp.zeros((1, stages, z0.size), z0.dtype), jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32))
        (z1, _, status, _), _ = jax.lax.scan(lambda c, _: (step(c), None), carry, None, length=n)
        return z1, status

    return run
