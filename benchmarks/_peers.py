"""The peers of ``bench_peers.py``: diffrax, SciPy ``solve_ivp``, and two integrators written
directly in JAX (leapfrog, 3-stage Gauss Runge-Kutta).

Every peer is a factory ``make(H, T, knob) -> run`` with ``run(z0) -> (z1, status)``: ``z0``
and ``z1`` are the state ``z = (q, p)`` of shape ``(2d,)`` at t = 0 and t = T, and status is
0 on success. ``knob`` is the number of steps of size ``T / knob`` (fixed-step peers) or the
tolerance ``rtol = atol`` (adaptive peers). A JAX ``run`` is jitted by the caller; a SciPy
``run`` is plain Python (``is_python`` tells them apart). The library never imports this.
"""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import scipy.integrate

# The 3-stage Gauss method (order 6), Hairer-Lubich-Wanner, Table II.1.2.
_R = np.sqrt(15.0)
GAUSS3_A = np.array([
    [5 / 36, 2 / 9 - _R / 15, 5 / 36 - _R / 30],
    [5 / 36 + _R / 24, 2 / 9, 5 / 36 - _R / 24],
    [5 / 36 + _R / 30, 2 / 9 + _R / 15, 5 / 36],
])
GAUSS3_B = np.array([5 / 18, 4 / 9, 5 / 18])


def hamiltonian_field(H):
    """``f(z) = J DH(z)`` for ``z = (q, p)`` stacked: ``(dH/dp, -dH/dq)``."""
    dH = jax.grad(H, argnums=(0, 1))

    def f(z):
        d = z.shape[-1] // 2
        dq, dp = dH(z[:d], z[d:])
        return jnp.concatenate([dp, -dq])

    return f


def _diffrax_solve(H, T, z0, solver, dt0, controller, max_steps):
    solution = diffrax.diffeqsolve(
        diffrax.ODETerm(lambda t, z, args: hamiltonian_field(H)(z)), solver, 0.0, T, dt0, z0,
        saveat=diffrax.SaveAt(t1=True), stepsize_controller=controller, max_steps=max_steps, throw=False,
    )
    return solution.ys[-1], jnp.where(solution.result == diffrax.RESULTS.successful, 0, 1)


def diffrax_fixed(solver):
    """diffrax ``solver`` with ``n`` constant steps ``h = T / n`` (the knob is n)."""

    def make(H, T, n):
        # a few spare steps: the last step is clipped to T, rounding may add one
        return lambda z0: _diffrax_solve(H, T, z0, solver, T / n, diffrax.ConstantStepSize(), n + 4)

    return make


def diffrax_pid(solver, max_steps=1_000_000):
    """diffrax ``solver`` with a PID controller, ``rtol = atol = tol`` (the knob), the initial
    step chosen by diffrax."""

    def make(H, T, tol):
        controller = diffrax.PIDController(rtol=tol, atol=tol)
        return lambda z0: _diffrax_solve(H, T, z0, solver, None, controller, max_steps)

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


def leapfrog(H, T, n):
    """Stormer-Verlet (kick-drift-kick, one force evaluation per step) for separable H:
    dH/dq is evaluated at the half-step momentum, which it does not depend on."""
    h = T / n
    dHq, dHp = jax.grad(H, argnums=0), jax.grad(H, argnums=1)

    def step(carry, _):
        q, p, force = carry
        p_half = p - 0.5 * h * force
        q1 = q + h * dHp(q, p_half)
        force1 = dHq(q1, p_half)
        return (q1, p_half - 0.5 * h * force1, force1), None

    def run(z0):
        q, p = jnp.split(z0, 2)
        (q, p, _), _ = jax.lax.scan(step, (q, p, dHq(q, p)), None, length=n)
        return jnp.concatenate([q, p]), jnp.zeros((), jnp.int32)

    return run


def gauss_rk3(H, T, n, max_iterations=50):
    """The 3-stage Gauss Runge-Kutta method (Gauss collocation, order 6) with fixed-point
    iteration on the stage increments Z_i = h sum_j a_ij f(z0 + Z_j), the usual choice for
    non-stiff problems [Hairer, Lubich, Wanner, Sect. VIII.6]: predictor the previous step's
    increments, stop at the round-off floor (on a non-stiff problem a fixed-point update is far
    cheaper than a Newton update with a dense Jacobian). ``lax.scan`` over steps; status 1 if
    some step took ``max_iterations``."""
    h, f = T / n, hamiltonian_field(H)
    A, b = jnp.asarray(GAUSS3_A), jnp.asarray(GAUSS3_B)

    def step(carry, _):
        z0, Z, status = carry
        tol = 10 * jnp.finfo(z0.dtype).eps * (1 + jnp.max(jnp.abs(z0)))

        def iterate(c):
            Z, _, i = c
            Z1 = h * A @ jax.vmap(f)(z0 + Z)
            return Z1, jnp.max(jnp.abs(Z1 - Z)), i + 1

        Z, _, i = jax.lax.while_loop(lambda c: (c[1] > tol) & (c[2] < max_iterations), iterate, (Z, jnp.inf, 0))
        z1 = z0 + h * b @ jax.vmap(f)(z0 + Z)
        return (z1, Z, jnp.where(i >= max_iterations, 1, status)), None

    def run(z0):
        (z1, _, status), _ = jax.lax.scan(step, (z0, jnp.zeros((3, z0.size), z0.dtype), 0), None, length=n)
        return z1, status

    return run


def is_python(run):
    return getattr(run, "is_python", False)


def diffrax_pid_counted(solver, max_steps=1_000_000):
    """diffrax ``solver`` with a PID controller (``rtol = atol = tol``, the initial step chosen by
    diffrax) as ``run(z0, T, tol) -> (z1, status, accepted, rejected)``: the span and the
    tolerance are arguments, so one compilation serves a whole tolerance sweep (``bench_adaptive``)."""

    def make(H):
        field = hamiltonian_field(H)

        def run(z0, T, tol):
            solution = diffrax.diffeqsolve(
                diffrax.ODETerm(lambda t, z, args: field(z)), solver, 0.0, T, None, z0,
                saveat=diffrax.SaveAt(t1=True), stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
                max_steps=max_steps, throw=False,
            )
            status = jnp.where(solution.result == diffrax.RESULTS.successful, 0, 1)
            return solution.ys[-1], status, solution.stats["num_accepted_steps"], solution.stats["num_rejected_steps"]

        return run

    return make


def versions():
    """The versions of the peers and of NumPy, and whether JAX runs in float64 (a result file's record)."""
    return {"diffrax": diffrax.__version__, "optimistix": optx.__version__, "scipy": scipy.__version__,
            "numpy": np.__version__, "jax_enable_x64": bool(jax.config.jax_enable_x64)}
