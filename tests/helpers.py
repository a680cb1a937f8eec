"""Problems with exact or independent reference solutions, and order fitting."""

import jax
import jax.numpy as jnp
import numpy as np

import galerkin_jax as gj

# The paper's isotropic oscillator [GBS, Figs. 4.1-4.5]: m = 2, c = -0.25, H = 0.25.
OSC_M, OSC_C = 2.0, -0.25


def oscillator(m=OSC_M, c=OSC_C):
    """H = |p|^2 / (2m) - c |q|^2 / 2 [GBS, eq. (43)] and a 3-D state with H = 0.25, L != 0."""
    H = lambda q, p: p @ p / (2 * m) - 0.5 * c * (q @ q)
    omega = np.sqrt(-c / m)
    # H = 0.25: q0 = (1, 0, 0) gives V = 0.125, |p0|^2 / (2m) = 0.125.
    q0 = jnp.array([1.0, 0.0, 0.0])
    p0 = jnp.array([0.0, np.sqrt(0.5) * 0.8, np.sqrt(0.5) * 0.6])
    return H, q0, p0, omega


def quartic(m=2.0, c=1000.0):
    """V = c (r^2 - 1)^2 / 2 [GBS, Figs. 4.6-4.7], a 3-D state with H = 6000."""
    V = lambda q: 0.5 * c * (q @ q - 1.0) ** 2
    H = lambda q, p: p @ p / (2 * m) + V(q)
    q0 = jnp.array([2.0, 0.0, 0.0])  # V = 4500
    p0 = jnp.array([0.0, np.sqrt(2 * m * 1500.0), 0.0])  # T = 1500
    return H, V, q0, p0


def kepler(e=0.5):
    """H = |p|^2 / 2 - 1 / |q|, starting at perihelion; period 2 pi."""
    H = lambda q, p: 0.5 * (p @ p) - 1.0 / jnp.sqrt(q @ q)
    q0 = jnp.array([1.0 - e, 0.0])
    p0 = jnp.array([0.0, np.sqrt((1.0 + e) / (1.0 - e))])
    return H, q0, p0


def kepler_exact(t, e=0.5):
    """Exact Kepler orbit (semi-major axis 1) from Kepler's equation E - e sin E = t, in NumPy."""
    E = t
    for _ in range(50):
        E = E - (E - e * np.sin(E) - t) / (1.0 - e * np.cos(E))
    q = np.array([np.cos(E) - e, np.sqrt(1 - e**2) * np.sin(E)])
    dE = 1.0 / (1.0 - e * np.cos(E))
    p = np.array([-np.sin(E) * dE, np.sqrt(1 - e**2) * np.cos(E) * dE])
    return q, p


def angular_momentum(q, p):
    return jnp.cross(q, p)


def fitted_order(hs, errs, floor=1e-12):
    """Slope of log(err) against log(h), over the points whose error is above ``floor``."""
    hs, errs = np.asarray(hs), np.asarray(errs)
    keep = errs > floor
    if keep.sum() < 2:
        raise AssertionError(f"fewer than two errors above the floor {floor}: {errs}")
    return np.polyfit(np.log(hs[keep]), np.log(errs[keep]), 1)[0]


def pendulum():
    H = lambda q, p: 0.5 * (p @ p) - jnp.cos(q[0])
    return H, jnp.array([1.2]), jnp.array([0.3])


def non_separable():
    """A coupled, non-separable H (no Lagrangian of the form T(qdot) - U(q))."""
    H = lambda q, p: 0.5 * (1 + 0.3 * q[0] ** 2) * p[0] ** 2 + 0.5 * p[1] ** 2 + 0.25 * p[0] * p[1] * q[1] + 0.25 * q[0] ** 4 + 0.5 * q[1] ** 2
    return H, jnp.array([0.8, -0.4]), jnp.array([0.2, 0.5])


def symplecticity_defect(A):
    """max |A^T J A - J| for a one-step Jacobian in the ordering z = (q, p)."""
    d = A.shape[0] // 2
    J = np.block([[np.zeros((d, d)), np.eye(d)], [-np.eye(d), np.zeros((d, d))]])
    A = np.asarray(A)
    return np.abs(A.T @ J @ A - J).max()


def collocation_tableau(nodes):
    """The collocation Runge-Kutta tableau on ``nodes`` (Gauss points: Gauss; right Radau
    points: Radau IIA): a_ij = int_0^{c_i} l_j, b_j = int_0^1 l_j for the Lagrange basis l_j."""
    s = len(nodes)
    a, b = np.zeros((s, s)), np.zeros(s)
    for j in range(s):
        others = np.delete(nodes, j)
        l_j = np.polynomial.Polynomial.fromroots(others) if len(others) else np.polynomial.Polynomial([1.0])
        l_j = l_j / l_j(nodes[j])
        antiderivative = l_j.integ()
        a[:, j] = antiderivative(nodes) - antiderivative(0.0)
        b[j] = antiderivative(1.0) - antiderivative(0.0)
    return a, b


def first_derivatives(f, tangent, cotangent):
    """One compiled program ``args -> (f(*args), J tangent, J^T cotangent)``: the value, the
    forward-mode product and the reverse-mode products (one per argument; the transpose of the
    same linearization, as ``jax.vjp`` computes it). Difference quotients of the value come
    from the same program."""

    @jax.jit
    def derivatives(args):
        value, linear = jax.linearize(f, *args)
        return value, linear(*tangent), jax.linear_transpose(linear, *args)(cotangent)

    return derivatives


def jacobians(f, x):
    """``(f(x), forward, reverse)`` for a 1-D x: the Jacobian by forward mode (its columns, the
    linearization on the basis vectors, as ``jax.jacfwd`` takes them) and by reverse mode (its
    rows, the transpose of the same linearization on the basis vectors, as ``jax.jacrev``); one
    linearization, so inside ``jit`` one program, and outside it the inputs' values stay known
    while the run is traced (as under ``jax.jacfwd``)."""
    value, linear = jax.linearize(f, x)
    forward = jax.vmap(linear, out_axes=-1)(jnp.eye(x.size, dtype=x.dtype))
    reverse = jax.vmap(jax.linear_transpose(linear, x))(jnp.eye(value.size, dtype=value.dtype))[0]
    return value, forward, reverse


def _products(f, args, eps, seed):
    """For random t and c: ``(J t, <J^T c, t>, D, c)``, D the central difference
    (f(x + eps t) - f(x - eps t)) / (2 eps), all from one compiled program (``first_derivatives``)."""
    rng = np.random.RandomState(seed)
    args = tuple(jnp.asarray(x, jnp.asarray(x).dtype) for x in args)  # not weakly typed, as x + eps t
    tangent = tuple(jnp.asarray(rng.standard_normal(x.shape), x.dtype) for x in args)
    out = jax.eval_shape(f, *args)
    cotangent = jnp.asarray(rng.standard_normal(out.shape), out.dtype)
    derivatives = first_derivatives(f, tangent, cotangent)
    _, forward, reverse = derivatives(args)
    shifted = lambda sign: derivatives(tuple(x + sign * eps * t for x, t in zip(args, tangent)))[0]
    numerical = (shifted(1.0) - shifted(-1.0)) / (2 * eps)
    projected = sum(jnp.vdot(c, t) for c, t in zip(reverse, tangent))
    return np.asarray(forward), float(projected), np.asarray(numerical), np.asarray(cotangent)


def check_first_derivatives(f, args, *, eps, atol, rtol, seed=0):
    """``jax.test_util.check_grads(f, args, order=1, modes=("fwd", "rev"))`` with one compiled
    program (``first_derivatives``) for random t and c: J t must equal the central difference
    (f(x + eps t) - f(x - eps t)) / (2 eps), and <J^T c, t> must equal <c, that difference>."""
    forward, projected, numerical, cotangent = _products(f, args, eps, seed)
    np.testing.assert_allclose(forward, numerical, atol=atol, rtol=rtol, err_msg="forward mode")
    np.testing.assert_allclose(projected, np.vdot(cotangent, numerical), atol=atol, rtol=rtol, err_msg="reverse mode")


def cg_element(k, H, z0, h, sweeps=100):
    """cG(k) + Gauss k on one element from z0: ``(z1, W)``, its fixed point by plain sweeps
    (a smaller program than the run's root finder; the same element to round-off)."""
    method = gj.CG(k, gj.gauss_legendre(k))
    q, p = jnp.split(z0, 2)
    C = jax.lax.fori_loop(0, sweeps, lambda _, C: C - method.residual(H, q, p, C, h), method.initial_guess(q, p))
    return z0 + C[0], method.polynomial(H, q, p, C, h)


def first_derivative_errors(f, args, *, eps, seed=0):
    """The disagreement ``check_first_derivatives`` bounds, measured: ``(forward, reverse)``, for
    the same random t and c, the central difference D = (f(x + eps t) - f(x - eps t)) / (2 eps):
    forward = max |J t - D| / max |D|, reverse = |<J^T c, t> - <c, D>| / sum |c D| (the size of
    the terms of the dot product, which a cancelling sum could not make small)."""
    forward, projected, numerical, c = _products(f, args, eps, seed)
    forward_error = float(np.max(np.abs(forward - numerical)) / np.max(np.abs(numerical)))
    reverse_error = abs(projected - float(np.vdot(c, numerical))) / float(np.sum(np.abs(c * numerical)))
    return forward_error, reverse_error


def check_first_derivatives_within(f, args, *, eps, forward, reverse, seed=0):
    """``first_derivative_errors`` below the bounds ``forward`` and ``reverse``; returns the
    measured pair (to print where a bound is being set)."""
    errors = first_derivative_errors(f, args, eps=eps, seed=seed)
    assert errors[0] <= forward, f"forward mode: J t is {errors[0]:.2e} from the central difference (bound {forward:.1e})"
    assert errors[1] <= reverse, f"reverse mode: <J^T c, t> is {errors[1]:.2e} from <c, D> (bound {reverse:.1e})"
    return errors
