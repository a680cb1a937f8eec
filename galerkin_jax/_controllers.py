"""Step-size controllers and events: what ``integrate(..., controller=, events=)`` takes.

* ``PIDController``: error-per-step control of h with diffrax's option names and meanings,
  driven by the element's embedded estimate (``embedded_error``).
* ``TimeTransform``: variable steps that keep the structure. The run integrates the
  Poincare-transformed Hamiltonian

      K(q, t, p, p_t) = s(q, p) (H(q, p) + p_t),   p_t(0) = -H(q0, p0),

  in a fictive time tau with the constant step h. K is a Hamiltonian on the extended phase
  space (q, t | p, p_t), so a symplectic method stays symplectic and a symmetric one
  symmetric; on K = 0 its flow is H's flow with dt/dtau = s (Hairer, Lubich, Wanner,
  Geometric Numerical Integration, Sec. VIII.2). The method conserves K near 0, so the
  energy error H - H0 = K / s stays bounded over long runs, which error-per-step control does
  not give.
* ``Event``: a scalar g(t, q, p) whose sign changes are located on the element polynomial.
"""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from ._basis import legendre_derivatives, legendre_values
from ._defect import hamilton_field, symplectic_field
from ._pytree import pytree_dataclass


@pytree_dataclass
class PIDController:
    """Error-per-step control of the step size h [diffrax's ``PIDController``].

    A step's error is ``err = rms(e / (atol + rtol max(|z0|, |z1|)))``, e the element's embedded
    estimate (``embedded_error``, of order q = degree + 1 of the element polynomial); the step is
    accepted when ``err <= 1`` and its implicit solve converged to a finite state, and the next
    h is ``h clip(safety err^(-b1/q) err_prev^(-b2/q) err_prev2^(-b3/q), factormin, factormax)``
    with b1 = pcoeff + icoeff + dcoeff, b2 = -(pcoeff + 2 dcoeff), b3 = dcoeff (a rejected step
    never grows h; a failed solve multiplies it by ``max(failfactor, factormin)``). With ``predictive`` (the
    default), after an accepted step the factor is at most Gustafsson's predictive one,
    ``safety (h / h_prev) err^(-2/q) max(err_prev, 0.01)^(1/q)`` (h_prev, err_prev: the last
    accepted step before this one), as in Hairer and Wanner's Radau5 (Solving ODEs II, Sec.
    IV.8): where the time scale shrinks from step to step, as on the way into a pericentre,
    it carries the trend of h on, where the I controller grows h after every accepted step
    and has the next one rejected. The numeric fields are pytree leaves, so a sweep can vmap
    over tolerances.

    Args:
        rtol: relative tolerance on the embedded estimate, > 0 (required). The true local error
            of a superconvergent method (cG(k): order 2k + 1) lies below it.
        atol: absolute tolerance on the embedded estimate, > 0 (required).
        pcoeff: proportional coefficient; default 0 (with the defaults below: I control).
        icoeff: integral coefficient; default 1.
        dcoeff: derivative coefficient; default 0.
        dtmin: smallest step; default 0 (the run ends where h falls to the round-off of t). A step
            rejected at dtmin ends the run with status DTMIN, unless ``force_dtmin``.
        dtmax: largest step; default inf.
        safety: factor < 1 on the predicted optimal h; default 0.9.
        factormin: least factor by which h changes per step; default 0.2.
        factormax: largest factor by which h changes per step; default 10.
        failfactor: the factor on h after a failed solve; default 0.5 (at least ``factormin``):
            it halves h, as Radau5 does after a Newton failure (Hairer and Wanner, Sec. IV.8); diffrax cuts by
            ``factormin``. A failed solve says the step was too long for the solve, not by how
            much: a cut by 0.2 leaves the estimate so small that the controller grows h about
            four times and fails again.
        predictive: bound the factor by Gustafsson's predictive controller (above); default
            True. False (with ``failfactor=factormin``) gives diffrax's controller. Static.
        force_dtmin: accept a step of h <= dtmin whose error exceeds the tolerance and go on at
            dtmin, as diffrax's ``force_dtmin=True`` does; default False (such a step ends the run,
            DTMIN). The status stays SUCCESS, and ``error_estimate`` shows the error such steps
            made; a failed solve is not accepted (status DTMIN there). Static.

    Raises:
        ValueError: at construction, for a concrete value out of its range (``BOUNDS``: rtol,
            atol > 0; 0 < safety <= 1; 0 < factormin < 1 < factormax; 0 < failfactor < 1;
            0 <= dtmin < dtmax; finite PID coefficients), each entry of an array of values (a
            sweep's) included. Traced values are not read; ``integrate`` and ``sweep`` check
            the shapes. The check runs where you construct the controller, not where JAX
            rebuilds it (``jax.tree.map``, ``vmap``'s axis specs, cotangents), so build axis
            specs with ``jax.tree.map``.
        TypeError: ``predictive`` or ``force_dtmin`` not a bool.
    """

    rtol: float
    atol: float
    pcoeff: float = 0.0
    icoeff: float = 1.0
    dcoeff: float = 0.0
    dtmin: float = 0.0
    dtmax: float = float("inf")
    safety: float = 0.9
    factormin: float = 0.2
    factormax: float = 10.0
    failfactor: float = 0.5
    predictive: bool = dataclasses.field(default=True, metadata=dict(static=True))
    force_dtmin: bool = dataclasses.field(default=False, metadata=dict(static=True))

    def _check_on_construction(self):
        for name in ("predictive", "force_dtmin"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"PIDController: {name} must be a bool, got {getattr(self, name)!r}.")
        check_values(concrete_values(self), "PIDController: ")

    def next_factor(self, err, err_prev, err_prev2, order, accepted, h_ratio):
        """The factor on h after a step with scaled error ``err`` (inf for a failed solve);
        ``err_prev``, ``err_prev2``: the last two accepted steps' errors; ``h_ratio``: this
        step's h over the last accepted one's (NaN before one was accepted; read only with
        ``predictive``)."""
        b1 = self.pcoeff + self.icoeff + self.dcoeff
        b2 = -(self.pcoeff + 2 * self.dcoeff)
        b3 = self.dcoeff
        tiny = jnp.finfo(jnp.result_type(err)).tiny
        inverse = lambda e: 1.0 / jnp.maximum(e, tiny)
        factor = self.safety * inverse(err) ** (b1 / order) * inverse(err_prev) ** (b2 / order) \
            * inverse(err_prev2) ** (b3 / order)
        if self.predictive:
            trend = self.safety * h_ratio * (jnp.maximum(err_prev, 1e-2) * inverse(err) ** 2) ** (1 / order)
            factor = jnp.where(accepted & jnp.isfinite(trend), jnp.minimum(factor, trend), factor)
        factor = jnp.where(jnp.isfinite(err), factor, self.failfactor)  # the clip below keeps factormin
        upper = jnp.where(accepted, self.factormax, 1.0)
        return jnp.clip(factor, self.factormin, upper)


# the range of each numeric field of a PIDController: (test on a float array, in words)
BOUNDS = {
    "rtol": (lambda v: v > 0, "> 0"),
    "atol": (lambda v: v > 0, "> 0"),
    "pcoeff": (np.isfinite, "finite"),
    "icoeff": (np.isfinite, "finite"),
    "dcoeff": (np.isfinite, "finite"),
    "dtmin": (lambda v: v >= 0, ">= 0"),
    "dtmax": (lambda v: v > 0, "> 0"),
    "safety": (lambda v: (v > 0) & (v <= 1), "in (0, 1]"),
    "factormin": (lambda v: (v > 0) & (v < 1), "in (0, 1)"),
    "factormax": (lambda v: v > 1, "> 1"),
    "failfactor": (lambda v: (v > 0) & (v < 1), "in (0, 1)"),
}


def concrete_values(controller):
    """``{field: float array}`` of the PIDController's numeric fields whose values are concrete
    (numbers, NumPy arrays, JAX arrays outside a trace); tracers and other objects are left out."""
    values = {}
    for field in dataclasses.fields(controller):
        x = getattr(controller, field.name)
        if field.name not in BOUNDS or isinstance(x, (bool, np.bool_, jax.core.Tracer)):
            continue
        if not isinstance(x, (int, float, np.number, np.ndarray, jax.Array)):
            continue
        try:
            v = np.asarray(x)
        except Exception:  # e.g. an array not fully addressable from this process
            continue
        if v.dtype.kind in "iuf":
            values[field.name] = v.astype(float)
    return values


def _shown(v, bad):
    """``v`` (a scalar), or its first bad entry and where, for an array of values."""
    if v.ndim == 0:
        return f"{float(v)!r}"
    index = tuple(int(i) for i in np.argwhere(bad)[0])
    where = index[0] if len(index) == 1 else index
    return f"{float(v[index])!r} (entry {where} of {v.shape[0] if v.ndim == 1 else v.shape})"


def check_values(values, prefix):
    """Raise ``ValueError`` for a value of ``values`` (``concrete_values``) outside ``BOUNDS``,
    or dtmin >= dtmax; ``prefix`` names the controller, e.g. ``"PIDController: "``."""
    for name, (ok, words) in BOUNDS.items():
        if name in values:
            with np.errstate(invalid="ignore"):
                bad = ~ok(values[name])
            if np.any(bad):
                raise ValueError(f"{prefix}{name} must be {words}, got {_shown(values[name], bad)}.")
    if "dtmin" in values and "dtmax" in values:
        dtmin, dtmax = np.broadcast_arrays(values["dtmin"], values["dtmax"])
        bad = ~(dtmin < dtmax)
        if np.any(bad):
            raise ValueError(f"{prefix}dtmin must be < dtmax, got dtmin = {_shown(dtmin, bad)} and "
                             f"dtmax = {_shown(dtmax, bad)}.")


S_MAX = 3.0  # the default density's largest value: docs/adaptive.md, "Where Hamilton's field vanishes"


def default_step_density(H, u, s_max=S_MAX):
    """The default s(q, p) of ``TimeTransform``: ``((1 + k^2) / (u |F(z)|^2 + k^2))^(3/8)`` with
    F = J DH Hamilton's field, |.| its Euclidean norm, ``u`` = 1 / |F(z0)|^2 (``field_scale``) and
    k^2 = 1 / (s_max^(8/3) - 1); s = 1 everywhere where ``u`` is 0 (a start at an equilibrium).

    That is ``(|F(z0)| / |F(z)|)^(3/4)`` with |F| floored smoothly at k |F(z0)|: where |F| is
    well above the floor, as on an eccentric orbit's way into its pericentre, the density is
    (|F(z0)| / |F(z)|)^(3/4) to within a factor (1 + k^2)^(3/8) (1.02 for s_max = 3); where F
    vanishes, s rises to ``s_max`` and stays finite; s(z0) = 1, so h is the first step's length
    in t.

    Why |F|^(-3/4): where one term of F dominates near a singularity, as the force 1/r^2 of a
    close encounter, |F|^(-3/4) ~ r^(3/2), the dynamical time scale sqrt(r^3 / (G M)) over
    which the orbit turns (Kepler's third law), so the steps follow the orbit's own time scale.

    Why the cap: where F vanishes the unbounded density fails. At rest it is 0 / 0; near an
    equilibrium the motion is slow but its time scale, that of the linearised flow, is not (a
    pendulum's saddle: 1), and s makes steps many of these long (near the separatrix: steps 5.4
    long in t, the run 0.63 rad off). The cap is relative to the first step because nothing the
    start shows (|F(z0)|, 0 at rest; H's Hessian there; h) tells a saddle ahead from an
    apocentre ahead, where |F| / |F(z0)| is as small (0.0032 on the pendulum's way from the
    bottom to near its saddle, 0.0036 on Kepler e = 0.9's from pericentre to apocentre); a cap
    from the linearised rate at every state tells them apart but costs 1.6-3x the time per step
    (third derivatives of H in the residual). 3 by measurement: near the separatrix the largest
    error is 6.9e-7 against 2.4 unbounded and 9.3e-4 with s = 1 at the same number of steps (at
    5 and more it falls behind s = 1 at p0 = 1.99), and from apocentre Kepler takes 1.7-1.9 %
    fewer steps with energy errors within their noise. The price falls on a run started at its
    fastest point with a slow region to follow: Kepler from pericentre takes 7.1x the steps at
    e = 0.9, 167x at e = 0.99; ``TimeTransform(s_max=inf)`` is the unbounded density
    (docs/adaptive.md, "Where Hamilton's field vanishes").

    Where it is weak: where |F|, which mixes the units of q' and p', does not measure how fast
    the state turns (pass your own s there); and on an eccentric orbit near apocentre, where
    |dH/dp| is small and changes fast, its share of |F| makes s vary within a long step; the
    error of the transformed Hamiltonian made there is divided by the small s of every
    pericentre. A density of the position alone (Kepler: r^(3/2)) avoids that; the default
    keeps |dH/dp| so that s stays finite where the force vanishes (docs/adaptive.md, "The
    default step density and your own").
    """
    k2 = _floor_share(s_max)

    return lambda q, p: _density(u, field_norm2(H, q, p), k2)[0]


def _density(u, norm2, k2):
    """``(s, u |F|^2 + k^2)`` of ``default_step_density`` from |F|^2 = ``norm2`` (s = 1 and the
    denominator 1 where u = 0), for the density and for K's closed-form gradient alike."""
    active = u > 0
    denominator = jnp.where(active, u * norm2 + k2, 1.0)
    return (jnp.where(active, 1.0 + k2, 1.0) / denominator) ** 0.375, denominator


def _floor_share(s_max):
    """k^2 of ``default_step_density``: s = ((1 + k^2) / k^2)^(3/8) = s_max where F = 0."""
    if not s_max > 1:
        raise ValueError(f"TimeTransform: s_max must be > 1, got {s_max!r}.")
    return 0.0 if np.isinf(s_max) else 1.0 / (s_max ** (8 / 3) - 1.0)


def field_scale(H, q0, p0):
    """``u`` of ``default_step_density``: 1 / |F(z0)|^2, or 0 where the start is an equilibrium,
    |F(z0)| at most 16 eps |D^2H(z0) z0|, the change of F from rounding z0 to the precision
    (a pendulum at q0 = pi: |F(z0)| = |sin(pi)| = 1.2e-16, 16 eps pi = 1.1e-14): the run then has no
    field to scale by, and s = 1 (steps h in t)."""
    grad = jax.grad(H, argnums=(0, 1))
    dH, hessian_z0 = jax.jvp(grad, (q0, p0), (q0, p0))
    w0 = sum(jnp.sum(g * g) for g in dH)
    eps = jnp.finfo(w0.dtype).eps
    roundoff = jnp.maximum((16 * eps) ** 2 * sum(jnp.sum(g * g) for g in hessian_z0), jnp.finfo(w0.dtype).tiny)
    still = w0 <= roundoff
    return jnp.where(still, 0.0, 1.0 / jnp.where(still, 1.0, w0))


def field_norm2(H, q, p):
    """|J DH(q, p)|^2 = |DH(q, p)|^2, the squared Euclidean norm of Hamilton's field."""
    return sum(jnp.sum(g * g) for g in jax.grad(H, argnums=(0, 1))(q, p))


def field_norm(H, q, p):
    """|J DH(q, p)|, the Euclidean norm of Hamilton's field."""
    return jnp.sqrt(sum(jnp.sum(f * f) for f in hamilton_field(H)(q, p)))


@pytree_dataclass
class TimeTransform:
    """Variable steps that keep symplecticity and symmetry: the Poincare transformation
    (module docstring) with dt/dtau = s(q, p) and the constant step h in tau.

    Args:
        s: the step density ``s(q, p) -> scalar > 0``, small where the motion is fast; default
            None (``default_step_density``). Called with q and p in the state's own shape, or as
            ``s(q, p, args)`` when ``args`` is passed. A non-positive or non-finite s inside a run
            ends it with status TIME_TRANSFORM.
        s_max: the default density's largest value, > 1; default None (3): steps in t at most
            ``s_max`` h where Hamilton's field vanishes (``float("inf")``: unbounded, the density
            (|F(z0)| / |F(z)|)^(3/4), which fails where F vanishes). With the default s only.
            Static.

    Raises:
        TypeError: ``s`` neither None nor callable.
        ValueError: ``s_max`` not > 1, or given with an ``s`` of your own.
    """

    s: object = dataclasses.field(default=None, metadata=dict(static=True))
    s_max: object = dataclasses.field(default=None, metadata=dict(static=True))

    def __post_init__(self):  # static fields: the user's objects, also where JAX rebuilds the node
        if self.s is not None and not callable(self.s):
            raise TypeError(f"TimeTransform: s must be a callable s(q, p), got {type(self.s).__name__}.")
        if self.s_max is not None:
            if self.s is not None:
                raise ValueError("TimeTransform: s_max bounds the default density; an s of your own bounds itself.")
            if isinstance(self.s_max, bool) or not isinstance(self.s_max, (int, float, np.integer, np.floating)):
                raise ValueError(f"TimeTransform: s_max must be a number > 1, got {self.s_max!r}.")
            _floor_share(float(self.s_max))


@pytree_dataclass
class Event:
    """A sign change of ``g(t, q, p)`` (a scalar) to locate, passed as ``integrate(..., events=)``.

    Each crossing is located on the element polynomial and reported in ``Solution.events``.

    Args:
        g: the event function ``g(t, q, p)``, returning a scalar; required. q and p arrive in the
            state's own shape.
        direction: which crossings count; default 0, any. +1 counts only upward ones (g from
            < 0 to >= 0), -1 only downward ones, in the run's order: in a run backwards
            (t1 < t0) upward as t decreases.
        terminal: end the run at the first crossing; default False. Its time and state are then
            the run's last.
        capacity: the number of events stored, an integer >= 1; default 64. Later events are
            counted, not stored: raise it when ``Events.count`` exceeds it.

    Raises:
        TypeError: ``g`` not callable, ``direction`` or ``capacity`` not an integer, ``terminal``
            not a bool.
        ValueError: ``direction`` not -1, 0 or 1; ``capacity`` < 1.
    """

    g: object = dataclasses.field(metadata=dict(static=True))
    direction: int = dataclasses.field(default=0, metadata=dict(static=True))
    terminal: bool = dataclasses.field(default=False, metadata=dict(static=True))
    capacity: int = dataclasses.field(default=64, metadata=dict(static=True))

    def __post_init__(self):  # static fields: the user's objects, also where JAX rebuilds the node
        check_event_fields(self.g, self.direction, self.terminal, self.capacity)


def event_value(g, t, q, p, args):
    """An event's g at (t, q, p): ``g(t, q, p)``, or ``g(t, q, p, args)`` with H's args where g
    reads them (``reads_args``: a g whose closed-over values travel in args, ``_inputs.EventG``)."""
    return g(t, q, p, args) if getattr(g, "reads_args", False) else g(t, q, p)


def user_args(args, clock, sigma):
    """H's args as the user's functions take them, from the args~ of the problem a loop solves:
    a time transformation's ``(args, u)`` (``poincare``; ``clock`` not None), then a traced
    direction's ``(sigma, args)`` (``_march.in_direction``; ``sigma`` not a Python int)."""
    if clock is not None:
        args = args[0]
    if not isinstance(sigma, int):
        args = args[1] if len(args) > 1 else None
    return args


def _integer(x):
    """An int or NumPy integer, not a bool."""
    return isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_))


def check_event_fields(g, direction, terminal, capacity):
    """Raise ``TypeError`` or ``ValueError``, naming the field, for an ``Event`` field of the wrong
    kind: ``g`` callable, ``direction`` in {-1, 0, 1}, ``terminal`` a bool, ``capacity`` an
    integer >= 1."""
    if not callable(g):
        raise TypeError(f"Event: g must be a callable g(t, q, p), got {type(g).__name__}.")
    if not _integer(direction):
        raise TypeError(f"Event: direction must be the integer -1, 0 or 1, got {direction!r}.")
    if direction not in (-1, 0, 1):
        raise ValueError(f"Event: direction must be -1, 0 or 1, got {direction!r}.")
    if not isinstance(terminal, (bool, np.bool_)):
        raise TypeError(f"Event: terminal must be a bool, got {terminal!r}.")
    if not _integer(capacity):
        raise TypeError(f"Event: capacity must be an integer >= 1, got {capacity!r}.")
    if capacity < 1:
        raise ValueError(f"Event: capacity must be an integer >= 1, got {capacity!r}.")


@pytree_dataclass
class Events:
    """The events of a run (``Solution.events``), in the order found.

    Attributes:
        t: the event times, shape ``(capacity,)``, NaN in unused rows.
        q: the positions at the events, ``(capacity,) + shape``, NaN in unused rows.
        p: the momenta at the events, likewise.
        count: the number of events found; it may exceed the capacity, the later ones being
            counted, not stored.
        ended: whether this event ended the run (a terminal event's first crossing).
    """

    t: jax.Array
    q: jax.Array
    p: jax.Array
    count: jax.Array
    ended: jax.Array


def embedded_error(H, q0, p0, W, h, increment, field=None, alpha=1.0):
    """The controller's estimate of one element: the defect ``delta(alpha) = w~'(alpha) - h F(w~(alpha))``
    (F = J DH, ``_defect``) of its polynomial made continuous at the nodes,
    ``w~ = w + (1 - alpha) (z0 - w(0)) + alpha (z1 - w(1))`` (its jumps spread linearly), at
    ``alpha`` (1 by default: the element's end, where w~ = z1), shape ``(2d,)``.

    The Galerkin equations make the defect orthogonal to the test space, not zero, and its
    value at alpha = 1 is O(h^q) with q = m, the number of Legendre coefficients of w - z0
    (degree + 1): an embedded estimate of order q from what the element already has, at the
    cost of one evaluation of Hamilton's field. A polynomial with jumps (GalerkinVI, whose
    momentum P has degree s - 1 and misses p0 and p1 [Tang, eqs. (2.26), (2.32)]) has its
    defect taken on w~: GalerkinVI(1)'s constant P itself has the defect -h F_p(z1), the force,
    of order one (a controller's steps would shrink in proportion to the tolerance); w~'s P is
    the line from p0 to p1, whose defect at 1 is Stormer-Verlet's against its one-sided
    end, O(h^2) = O(h^m). A polynomial that matches Hamilton's field at the element's end (the
    Hermite cubic of compositions and splittings) has no defect there: its ``embedded_alpha``
    is 1/4, where the defect is the derivative of the cubic's interpolation error
    h^4 z^(4) alpha^2 (1 - alpha)^2 / 24, O(h^4) (at 1/2 its leading term vanishes), large
    where the solution's derivatives are, as the local error is. It ranks elements for the
    default ``error_estimate`` (those methods refuse a ``PIDController``); the local error's
    own elementary differentials may peak elsewhere where they vary little over a run
    (``tests/test_splitting.py``). The full a posteriori estimate
    (``_defect.local_error``) has the method's own order (2k + 1 for cG(k)) and costs J + 1
    field evaluations and J products with its Jacobian.

    Args:
        W: the polynomial's Legendre coefficients, shape ``(m, 2d)`` (``polynomial``).
        increment: z1 - z0, shape ``(2d,)``.
        field: F(z1) where the element has it already (an explicit element's force,
            ``_explicit``), else None; read at alpha = 1 only.
        alpha: a static float in [0, 1].
    """
    m = W.shape[0]
    z0 = jnp.concatenate([q0, p0])
    start, end = jnp.sum((-1.0) ** np.arange(m)[:, None] * W, axis=0), jnp.sum(W, axis=0)  # w(0) - z0, w(1) - z0
    spread = start + increment - end  # d/dalpha of the jumps spread linearly
    if alpha == 1.0:
        slopes = jnp.asarray([j * (j + 1.0) for j in range(m)], W.dtype)  # d/dalpha P_j(2 alpha - 1) at 1
        slope, at = jnp.sum(slopes[:, None] * W, axis=0), z0 + increment
    else:
        point = jnp.full((1,), alpha, W.dtype)
        slope = (legendre_derivatives(point, m) @ W)[0]
        at = z0 + (legendre_values(point, m) @ W)[0] - (1.0 - alpha) * start + alpha * (increment - end)
        field = None
    if field is None:
        field = symplectic_field(H)(at)
    return slope + spread - h * field


def scaled_error(e, z0, z1, controller):
    """``rms(e / (atol + rtol max(|z0|, |z1|)))``; inf where it is not finite."""
    tolerance = controller.atol + controller.rtol * jnp.maximum(jnp.abs(z0), jnp.abs(z1))
    err = jnp.sqrt(jnp.mean((e / tolerance) ** 2))
    return jnp.where(jnp.isfinite(err), err, jnp.inf)


def poincare(H, transform, q0, p0, t0, args):
    """The time-transformed problem: ``(K, q~0, p~0, args~, s~)`` with the Poincare-transformed
    Hamiltonian ``K(q~, p~, args~) = s(q, p) (H(q, p) + p_t)`` on ``q~ = (q, t)``, ``p~ = (p, p_t)``,
    ``p_t(0) = -H(q0, p0)`` (module docstring), and ``s~(q, p)`` the step density bound to
    ``args~``. H and s take ``args`` when it is not None; ``transform.s`` None:
    ``default_step_density`` with u = ``field_scale`` in ``args~``, and K's gradient in closed
    form (``_default_transformed``).
    """
    d = q0.shape[0]
    s = transform.s
    s_max = S_MAX if transform.s_max is None else float(transform.s_max)
    step_density = lambda a: default_step_density(_bind(H, a[0]), a[1], s_max) if s is None else _bind(s, a[0])

    def K(qt, pt, a):
        q, p = qt[:d], pt[:d]
        return step_density(a)(q, p) * (_bind(H, a[0])(q, p) + pt[d])

    H0 = _bind(H, args)(q0, p0)
    extended = (args, field_scale(_bind(H, args), q0, p0)) if s is None else (args, None)
    qt0 = jnp.concatenate([q0, jnp.asarray(t0, q0.dtype)[None]])
    pt0 = jnp.concatenate([p0, -H0[None]])
    transformed = K if s is not None else _default_transformed(K, H, d, _floor_share(s_max))
    return transformed, qt0, pt0, extended, step_density(extended)


def _bind(f, args):
    return f if args is None else (lambda q, p: f(q, p, args))


def _default_transformed(K, H, d, k2):
    """``K`` of the default step density s = ((1 + k^2) / (u |DH|^2 + k^2))^(3/8)
    (``default_step_density``; s = 1 where u = 0), with its gradient in closed form.

    |F| = |J DH| = |DH| (J is orthogonal), so DK = (H + p_t) Ds + s DH with
    Ds = -(3/4) s u D^2H DH / (u |DH|^2 + k^2) (0 where u = 0): one Hessian-vector product, by
    forward mode over H's gradient. ``jax.grad`` of K as written differentiates the reverse-mode
    |DH|^2 in reverse mode again, a program several times as large (the residual of every
    element holds DK). The derivatives in ``args~`` (H's args and u) are forward mode over K.
    """

    @jax.custom_jvp
    def transformed(qt, pt, a):
        return K(qt, pt, a)

    @functools.partial(transformed.defjvp, symbolic_zeros=True)
    def transformed_jvp(primals, tangents):
        qt, pt, a = primals
        dqt, dpt, da = tangents
        q, p, H_a, u = qt[:d], pt[:d], _bind(H, a[0]), a[1]
        energy, dH = jax.value_and_grad(H_a, argnums=(0, 1))(q, p)
        s, denominator = _density(u, sum(jnp.sum(g * g) for g in dH), k2)
        hessian_dH = jax.jvp(jax.grad(H_a, argnums=(0, 1)), (q, p), dH)[1]
        slope = -0.75 * s * (energy + pt[d]) * u / denominator
        gradient = (jnp.concatenate([slope * hessian_dH[0] + s * dH[0], jnp.zeros_like(qt[d:])]),
                    jnp.concatenate([slope * hessian_dH[1] + s * dH[1], s[None]]))
        tangent = sum(g @ t for g, t in zip(gradient, (dqt, dpt)) if not symbolic_zero(t))
        if not all(symbolic_zero(t) for t in jax.tree.leaves(da, is_leaf=symbolic_zero)):
            da = jax.tree.map(lambda t, x: jnp.zeros_like(x) if symbolic_zero(t) else t, da, a,
                              is_leaf=symbolic_zero)
            tangent = tangent + jax.jvp(lambda a: K(qt, pt, a), (a,), (da,))[1]
        return s * (energy + pt[d]), jnp.asarray(tangent, qt.dtype)

    return transformed


def symbolic_zero(t):
    """A custom_jvp tangent that JAX passes as a symbolic zero (``symbolic_zeros=True``)."""
    return isinstance(t, jax.custom_derivatives.SymbolicZero)
