"""The systems of ``bench_moderate.py``: untuned moderate Hamiltonian systems with initial states
chosen as a user of each field would choose them. Reduced units throughout, float64.

* Pair-potential clusters in 3-D (``lennard_jones``, ``morse``): the Mackay icosahedron of 13
  or 55 atoms relaxed to its minimum (the global minimum of LJ13 and LJ55 [Wales and Doye
  1997] and of the Morse cluster M13 at rho = 6 [Doye and Wales 1997]), with
  Maxwell-Boltzmann velocities at a reduced temperature, zero total momentum and zero angular
  momentum, the usual start of a microcanonical cluster run.
* Gravitational N-body (``plummer``): a Plummer sphere sampled as Aarseth, Henon and Wielen
  (1974) do, in Henon units (G = M = 1, virial radius 1), Plummer softening, rescaled to
  virial equilibrium of the softened potential.
* A non-separable chain (``pendulum_chain``): the planar N-link pendulum in its joint angles,
  H = p^T M(q)^-1 p / 2 + V(q) with the links' mass matrix.

Each factory returns a ``System``; ``V`` is given for separable systems (H = sum p^2 / 2m +
V(q)), where the explicit peers apply. The library never imports this.
"""

import dataclasses
from typing import Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize

from galerkin_jax import scenes


@dataclasses.dataclass(frozen=True)
class System:
    """A Hamiltonian system with its initial state and span.

    Attributes:
        name: short label (``--only`` takes it).
        description: one line: the potential, the size, the start, with the seed.
        H: ``H(q, p)`` on flat arrays of shape ``(d,)``.
        q0, p0: NumPy float64, shape ``(d,)``.
        T: the span.
        V: ``V(q)`` for a separable H (``H = p^2 / 2m + V``), else None.
        facts: what the start is, in numbers (its energy, temperature, ...), for the results file.
    """

    name: str
    description: str
    H: Callable
    q0: np.ndarray
    p0: np.ndarray
    T: float
    V: Optional[Callable] = None
    facts: dict = dataclasses.field(default_factory=dict)


def separable(V, masses):
    """H(q, p) = sum p^2 / 2m + V(q)."""
    inverse = jnp.asarray(1.0 / masses)
    return lambda q, p: 0.5 * jnp.sum(inverse * p * p) + V(q)


def pair_potential(phi):
    """V(q) = sum_{i < j} phi(|x_i - x_j|^2) over the atoms of q = (x_1, y_1, z_1, x_2, ...),
    written as a user of JAX would: the full matrix of squared distances, its diagonal masked
    (faster than a gather of the N (N - 1) / 2 pairs for 55 atoms on this CPU: 19 against 34
    us a gradient)."""

    def V(q):
        x = q.reshape(-1, 3)
        n = x.shape[0]
        d = x[:, None, :] - x[None, :, :]
        eye = jnp.eye(n, dtype=bool)
        r2 = jnp.sum(d * d, axis=-1) + eye  # 1 on the diagonal: no 0 / 0 in phi or its gradient
        return 0.5 * jnp.sum(jnp.where(eye, 0.0, phi(r2)))

    return V


def lj_pair(r2):
    """Lennard-Jones, epsilon = sigma = 1: 4 (r^-12 - r^-6)."""
    inv6 = (1.0 / r2) ** 3
    return 4.0 * (inv6 * inv6 - inv6)


def morse_pair(rho):
    """Morse, epsilon = r0 = 1: e^(rho (1 - r)) (e^(rho (1 - r)) - 2); rho = 6 is close to
    Lennard-Jones's well width."""

    def phi(r2):
        e = jnp.exp(rho * (1.0 - jnp.sqrt(r2)))
        return e * (e - 2.0)

    return phi


def icosahedron(shells):
    """The Mackay icosahedron of ``shells`` shells around a central atom (13, 55, 147, ...
    atoms) with unit nearest-neighbour distance along the radius: each shell s holds the 12
    vertices at radius s, s - 1 atoms on each of the 30 edges and the triangular lattice
    inside each of the 20 faces."""
    g = (1 + 5**0.5) / 2
    base = np.array([[0.0, a, b * g] for a in (-1, 1) for b in (-1, 1)])
    v = np.concatenate([np.roll(base, k, axis=1) for k in range(3)])
    v /= np.linalg.norm(v[0])
    near = lambda a, b: np.isclose(np.linalg.norm(v[a] - v[b]), np.linalg.norm(v[0] - v[8]))  # edge length
    edges = [(a, b) for a in range(12) for b in range(a + 1, 12) if near(a, b)]
    faces = [(a, b, c) for a, b in edges for c in range(b + 1, 12) if near(a, c) and near(b, c)]
    assert len(edges) == 30 and len(faces) == 20
    points = [np.zeros(3)]
    for s in range(1, shells + 1):
        points += [s * v[a] for a in range(12)]
        points += [s * (v[a] + (v[b] - v[a]) * t / s) for a, b in edges for t in range(1, s)]
        points += [s * (v[a] + (v[b] - v[a]) * i / s + (v[c] - v[a]) * j / s)
                   for a, b, c in faces for i in range(1, s) for j in range(1, s - i)]
    return np.array(points)


def relax(V, x):
    """The local minimum of V nearest ``x`` (flattened): the best uniform scale of x first,
    then L-BFGS on V with its JAX gradient, then five Newton steps (least squares on the
    Hessian, whose six rigid-body modes are zero) to a gradient at round-off."""
    value_and_grad, hessian = jax.jit(jax.value_and_grad(V)), jax.jit(jax.hessian(V))
    scales = np.linspace(0.8, 1.4, 61)
    scale = scales[np.argmin([float(value_and_grad(jnp.asarray(s * x))[0]) for s in scales])]
    fun = lambda q: tuple(np.asarray(a) for a in value_and_grad(jnp.asarray(q)))
    q = scipy.optimize.minimize(fun, scale * x, jac=True, method="L-BFGS-B",
                                options=dict(gtol=1e-10, ftol=1e-16, maxiter=20_000)).x
    for _ in range(5):
        q = q - np.linalg.lstsq(np.asarray(hessian(jnp.asarray(q))), fun(q)[1], rcond=1e-10)[0]
    energy, gradient = fun(q)
    return q, float(energy), float(np.max(np.abs(gradient)))


def thermal_velocities(x, temperature, rng):
    """Maxwell-Boltzmann velocities (unit masses) at ``temperature`` (k_B = 1) for atoms at
    ``x`` (shape (N, 3)): normal draws, the centre-of-mass velocity and the rigid rotation
    (omega = I^-1 L about the centre of mass) removed, then scaled so that the kinetic energy
    is (3N - 6) T / 2, the equipartition share of the 3N - 6 internal degrees of freedom."""
    n = x.shape[0]
    v = rng.normal(scale=np.sqrt(temperature), size=(n, 3))
    v -= v.mean(axis=0)
    r = x - x.mean(axis=0)
    L = np.sum(np.cross(r, v), axis=0)
    inertia = np.sum(r * r) * np.eye(3) - r.T @ r
    v -= np.cross(np.linalg.solve(inertia, L), r)
    kinetic = 0.5 * np.sum(v * v)
    return v * np.sqrt((3 * n - 6) * temperature / 2 / kinetic)


def cluster(kind, n, temperature, T, seed, rho=6.0):
    """A cluster of ``n`` (13 or 55) unit-mass atoms, ``kind`` "lj" or "morse": the relaxed
    Mackay icosahedron with thermal velocities (``thermal_velocities``, ``seed``)."""
    shells = {13: 1, 55: 2, 147: 3}[n]
    phi, label = (lj_pair, "Lennard-Jones") if kind == "lj" else (morse_pair(rho), f"Morse rho = {rho:g}")
    V = pair_potential(phi)
    x, energy, gradient = relax(V, icosahedron(shells).ravel())
    v = thermal_velocities(x.reshape(-1, 3), temperature, np.random.default_rng(seed))
    masses = np.ones(3 * n)
    name = f"{'LJ' if kind == 'lj' else 'Morse'}{n}"
    description = (f"{label} cluster of {n} atoms: relaxed Mackay icosahedron (V = {energy:.6f}), Maxwell-Boltzmann "
                   f"velocities at T* = {temperature:g} (seed {seed}), zero momentum and angular momentum, span {T:g}")
    facts = dict(minimum_energy=energy, minimum_gradient=gradient, temperature=temperature, seed=seed, atoms=n)
    return System(name, description, separable(V, masses), x, v.ravel(), T, V=V, facts=facts)


def lennard_jones(n, temperature=0.3, T=50.0, seed=0):
    """A Lennard-Jones cluster (``cluster``): LJ13's minimum -44.326801, LJ55's -279.248470
    (the Cambridge Cluster Database's values)."""
    return cluster("lj", n, temperature, T, seed)


def morse(n, temperature=0.3, T=50.0, seed=0, rho=6.0):
    """A Morse cluster at rho = 6 (``cluster``): M13's minimum -42.439863 (Doye and Wales 1997)."""
    return cluster("morse", n, temperature, T, seed, rho)


def plummer(n, softening=None, T=10.0, seed=0):
    """A Plummer sphere of ``n`` equal masses, G = 1, total mass 1, Henon units (virial radius 1,
    so the Plummer scale is a = 3 pi / 16; crossing time 2 sqrt(2)). Radii and speeds are drawn
    as in Aarseth, Henon and Wielen (1974): r = a (X^(-2/3) - 1)^(-1/2), the speed by von
    Neumann rejection from g(s) = s^2 (1 - s^2)^(7/2) times the local escape speed; isotropic
    directions; the centre of mass put at rest at the origin; the velocities scaled to virial
    equilibrium 2K + W = 0 of the softened potential. Plummer softening eps (default 4 / n,
    Aarseth's choice of eps ~ 4 r_V / N): V = -sum_{i<j} m_i m_j / sqrt(r_ij^2 + eps^2)."""
    eps = 4.0 / n if softening is None else softening
    rng = np.random.default_rng(seed)
    a, m = 3 * np.pi / 16, 1.0 / n
    radius = a / np.sqrt(rng.uniform(0.0, 1.0, n) ** (-2.0 / 3.0) - 1.0)
    speeds = []
    while len(speeds) < n:
        s, y = rng.uniform(0.0, 1.0, 2)
        if 0.1 * y < s * s * (1 - s * s) ** 3.5:
            speeds.append(s)
    escape = np.sqrt(2.0 / np.sqrt(radius**2 + a**2))  # the Plummer potential's escape speed, G = M = 1
    x = radius[:, None] * _directions(rng, n)
    v = (np.array(speeds) * escape)[:, None] * _directions(rng, n)
    x -= x.mean(axis=0)
    v -= v.mean(axis=0)
    masses = np.full(3 * n, m)

    def V(q):
        y = q.reshape(-1, 3)
        d = y[:, None, :] - y[None, :, :]
        inv = 1.0 / jnp.sqrt(jnp.sum(d * d, axis=-1) + eps * eps)
        return -0.5 * m * m * (jnp.sum(inv) - n / eps)  # the diagonal's n / eps taken out

    W = float(V(jnp.asarray(x.ravel())))
    K = 0.5 * m * np.sum(v * v)
    v *= np.sqrt(-W / (2 * K))
    description = (f"Plummer sphere of {n} equal masses, G = M = 1, Henon units, softening {eps:g} "
                   f"(seed {seed}), virial equilibrium of the softened potential, span {T:g}")
    facts = dict(bodies=n, softening=eps, seed=seed, potential=W, kinetic=-W / 2, energy=W / 2)
    return System(f"Plummer{n}", description, separable(V, masses), x.ravel(), (m * v).ravel(), T, V=V, facts=facts)


def _directions(rng, n):
    """``n`` isotropic unit vectors."""
    u = rng.normal(size=(n, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def pendulum_chain(n, angle=0.5, T=20.0, seed=0):
    """The planar ``n``-link pendulum (``scenes.pendulum_chain``), at rest with each link at an
    angle drawn uniformly from [-angle, angle] (seed). Its H, the energy above the hanging rest
    state, is > 0, and is not separable (M depends on q), so no explicit symplectic splitting
    applies."""
    scene = scenes.pendulum_chain(n, angle=angle, seed=seed)
    energy = float(scene.H(jnp.asarray(scene.q0), jnp.asarray(scene.p0)))
    description = (f"planar {n}-link pendulum (unit masses and lengths, g = 1), non-separable, at rest with angles "
                   f"uniform in [-{angle:g}, {angle:g}] (seed {seed}), H = {energy:.4f} above rest, span {T:g}")
    return System(f"Chain{n}", description, scene.H, scene.q0, scene.p0, T,
                  facts=dict(links=n, angle=angle, seed=seed, energy=energy))


def learned(width=32, dim=2, scale=0.3, T=20.0, seed=0):
    """A Hamiltonian as a network learns one: H(q, p) = |p|^2 / 2 + |q|^2 / 2 + scale N(q, p),
    N a two-layer tanh network (``width`` units) on the joined state with weights drawn from
    N(0, 1 / fan-in) (seed): non-separable (the network reads q and p together), smooth, with
    an expensive field (two matrix products per gradient). The start: q0 = (1, 0, ...), p0 = 0."""
    rng = np.random.default_rng(seed)
    W1 = jnp.asarray(rng.normal(size=(width, 2 * dim)) / np.sqrt(2 * dim))
    b1 = jnp.asarray(rng.normal(size=width) * 0.1)
    w2 = jnp.asarray(rng.normal(size=width) / np.sqrt(width))

    def H(q, p):
        z = jnp.concatenate([q, p])
        return 0.5 * p @ p + 0.5 * q @ q + scale * w2 @ jnp.tanh(W1 @ z + b1)

    q0 = np.zeros(dim)
    q0[0] = 1.0
    p0 = np.zeros(dim)
    energy = float(H(jnp.asarray(q0), jnp.asarray(p0)))
    description = (f"a learned-network H on {dim} degrees of freedom (|p|^2/2 + |q|^2/2 + {scale:g} w2 tanh(W1 z + b1), "
                   f"{width} units, seed {seed}), non-separable, from q0 = e1 at rest, H = {energy:.4f}, span {T:g}")
    return System(f"Learned{dim}", description, H, q0, p0, T, facts=dict(width=width, scale=scale, seed=seed,
                                                                          energy=energy))
