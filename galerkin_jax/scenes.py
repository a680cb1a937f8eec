"""Built-in scenes: a Hamiltonian, an initial state, a default step, and what to watch.

One place for the problems that the command line tool, the notebooks and the benchmarks
share. States are NumPy arrays (float64), so a scene never creates a JAX array on import
and takes the dtype the caller asks for.
"""

import dataclasses
from typing import Callable, Optional

import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class Scene:
    """A Hamiltonian system with its initial state.

    Attributes:
        name: the name ``get`` takes.
        description: one line, with the paper's reference where there is one.
        H: ``H(q, p) -> scalar``.
        q0, p0: shape ``(d,)``, NumPy float64.
        h, n_steps: a step size and run length that show the scene's behaviour.
        invariants: ``{name: I(q, p)}`` conserved by the exact flow besides H.
        exact: ``t -> (q, p)`` (NumPy) where the exact solution is known, else None.
        center: the position of a fixed central body (the Sun of the Kepler problem), drawn
            in the orbit plot; None where the scene has none.
    """

    name: str
    description: str
    H: Callable
    q0: np.ndarray
    p0: np.ndarray
    h: float
    n_steps: int
    invariants: dict = dataclasses.field(default_factory=dict)
    exact: Optional[Callable] = None
    center: Optional[tuple] = None


def _angular_momentum(q, p):
    """|q x p| in 2-D or 3-D (the scalar q1 p2 - q2 p1 in 2-D)."""
    if q.shape[-1] == 2:
        return q[0] * p[1] - q[1] * p[0]
    return jnp.linalg.norm(jnp.cross(q, p))


def oscillator(m=2.0, c=-0.25):
    """The isotropic oscillator of [GBS, Figs. 4.1-4.5]: H = |p|^2 / 2m - c |q|^2 / 2, H = 0.25."""
    omega = np.sqrt(-c / m)
    q0 = np.array([1.0, 0.0, 0.0])  # V = 0.125
    p0 = np.array([0.0, np.sqrt(0.5) * 0.8, np.sqrt(0.5) * 0.6])  # T = 0.125

    def exact(t):
        t = np.asarray(t, dtype=float)[..., None]
        q = q0 * np.cos(omega * t) + p0 / (m * omega) * np.sin(omega * t)
        p = p0 * np.cos(omega * t) - m * omega * q0 * np.sin(omega * t)
        return q, p

    return Scene(
        name="oscillator",
        description=f"isotropic harmonic oscillator, m = {m:g}, c = {c:g}, H = 0.25 [GBS, Figs. 4.1-4.5]",
        H=lambda q, p: p @ p / (2 * m) - 0.5 * c * (q @ q),
        q0=q0, p0=p0, h=0.1, n_steps=1000,
        invariants={"L": _angular_momentum}, exact=exact,
    )


def quartic(m=2.0, c=1000.0):
    """The quartic central force of [GBS, Figs. 4.6-4.7]: V = c (|q|^2 - 1)^2 / 2, H = 6000."""
    q0 = np.array([2.0, 0.0, 0.0])  # V = 4500
    p0 = np.array([0.0, np.sqrt(2 * m * 1500.0), 0.0])  # T = 1500
    return Scene(
        name="quartic",
        description=f"central force V = c (r^2 - 1)^2 / 2, m = {m:g}, c = {c:g}, H = 6000 [GBS, Figs. 4.6-4.7]",
        H=lambda q, p: p @ p / (2 * m) + 0.5 * c * (q @ q - 1.0) ** 2,
        q0=q0, p0=p0, h=0.01, n_steps=1000,
        invariants={"L": _angular_momentum},
    )


def kepler_orbit(t, e):
    """The exact Kepler orbit (a = 1, period 2 pi) from perihelion, by Newton on E - e sin E = t."""
    t = np.asarray(t, dtype=float)
    E = t.copy()
    for _ in range(60):
        E = E - (E - e * np.sin(E) - t) / (1.0 - e * np.cos(E))
    dE = 1.0 / (1.0 - e * np.cos(E))
    q = np.stack([np.cos(E) - e, np.sqrt(1 - e**2) * np.sin(E)], axis=-1)
    p = np.stack([-np.sin(E) * dE, np.sqrt(1 - e**2) * np.cos(E) * dE], axis=-1)
    return q, p


def kepler(e=0.6):
    """H = |p|^2 / 2 - 1 / |q| from perihelion, eccentricity e, period 2 pi."""
    q0, p0 = (x[0] for x in kepler_orbit(np.zeros(1), e))
    return Scene(
        name="kepler",
        description=f"Kepler problem, eccentricity {e:g}, period 2 pi",
        H=lambda q, p: 0.5 * (p @ p) - 1.0 / jnp.sqrt(q @ q),
        q0=q0, p0=p0, h=0.05, n_steps=1000,
        invariants={"L": _angular_momentum},
        exact=lambda t: kepler_orbit(t, e), center=(0.0, 0.0),
    )


def pendulum():
    """H = p^2 / 2 - cos q, started at q = 1.2, p = 0.3."""
    return Scene(
        name="pendulum",
        description="mathematical pendulum H = p^2 / 2 - cos q",
        H=lambda q, p: 0.5 * (p @ p) - jnp.sum(jnp.cos(q)),
        q0=np.array([1.2]), p0=np.array([0.3]), h=0.1, n_steps=1000,
    )


def fput(n=64, beta=1.0, excitation="thermal", seed=0):
    """The beta Fermi-Pasta-Ulam-Tsingou chain of n unit masses with fixed ends:

        H = |p|^2 / 2 + sum_{i=0}^{n} [(q_{i+1} - q_i)^2 / 2 + beta (q_{i+1} - q_i)^4 / 4],  q_0 = q_{n+1} = 0.

    ``excitation="thermal"``: q = 0 and standard normal momenta (every mode moves; the
    highest linear frequency is 2). ``"mode"``: the lowest normal mode with amplitude 1, the
    classic recurrence experiment.
    """
    if excitation == "thermal":
        q0, p0 = np.zeros(n), np.random.default_rng(seed).normal(size=n)
    elif excitation == "mode":
        q0, p0 = np.sin(np.pi * np.arange(1, n + 1) / (n + 1)), np.zeros(n)
    else:
        raise ValueError(f"fput: excitation must be 'thermal' or 'mode', got {excitation!r}.")

    def H(q, p):
        zero = jnp.zeros(1, q.dtype)
        strain = jnp.diff(jnp.concatenate([zero, q, zero]))
        return 0.5 * (p @ p) + jnp.sum(0.5 * strain**2 + 0.25 * beta * strain**4)

    return Scene(
        name="fput",
        description=f"beta-FPUT chain, {n} masses, beta = {beta:g}, {excitation} start",
        H=H, q0=q0, p0=p0, h=0.05, n_steps=2000,
    )


def pendulum_chain(n=10, angle=0.5, momenta=0.0, seed=0):
    """The planar n-link pendulum: unit point masses on massless rods of unit length, g = 1, in
    the links' angles q_j from the downward vertical:

        H = p^T M(q)^-1 p / 2 + sum_j (n - j) (1 - cos q_j),  M_jk = (n - max(j, k)) cos(q_j - q_k)

    (0-based j, k: the masses at or below link max(j, k)). H is not separable (M depends on q),
    so no splitting applies, and each of its partial gradients runs through the solve with M.
    The start: each angle drawn uniformly from [-angle, angle], the momenta normal with standard
    deviation ``momenta`` (0: at rest), both from one generator (seed). A problem of the
    benchmarks and tests, not among the command line's ``SCENES``: its motion is chaotic, and
    the command's verdict on the energy error (oscillating or drifting) is not made for that.
    """
    below = n - np.arange(n)
    weight = np.minimum.outer(below, below).astype(float)

    def H(q, p):
        M = jnp.asarray(weight, q.dtype) * jnp.cos(q[:, None] - q[None, :])
        return 0.5 * p @ jnp.linalg.solve(M, p) + jnp.sum(jnp.asarray(below, q.dtype) * (1.0 - jnp.cos(q)))

    rng = np.random.default_rng(seed)
    q0 = rng.uniform(-angle, angle, n)
    p0 = momenta * rng.normal(size=n) if momenta else np.zeros(n)
    return Scene(
        name="pendulum_chain",
        description=f"planar {n}-link pendulum (unit masses and rods, g = 1), non-separable",
        H=H, q0=q0, p0=p0, h=0.05, n_steps=400,
    )


SCENES = {"oscillator": oscillator, "quartic": quartic, "kepler": kepler, "pendulum": pendulum, "fput": fput}


def get(name, **parameters):
    """The scene called ``name`` (one of ``SCENES``), with its parameters overridden."""
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; the built-in scenes are {', '.join(SCENES)}.")
    return SCENES[name](**parameters)
