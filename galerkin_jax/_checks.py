"""Input validation, run before anything is traced.

Shapes and kinds are always checked (they are static); values only where they are
concrete. Traced values are checked inside jit and reported through ``Solution.status``.
"""

import dataclasses
import os
import sys
import warnings
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from ._configs import Configs
from ._state import Float32Warning, check_state, state_dtype, warn_if_low_precision  # noqa: F401
from ._method import MEMBERS, check_method, layers  # noqa: F401 (check_method: every entry point checks here)


def _concrete(x):
    return not isinstance(x, jax.core.Tracer)


def check_function(H, name="H"):
    if not callable(H):
        raise TypeError(f"{name} must be a callable H(q, p) or H(q, p, args), got {type(H).__name__}.")


def check_step_size(h):
    if jnp.ndim(h) != 0:
        raise ValueError(f"h must be a scalar, got shape {jnp.shape(h)}.")
    if _concrete(h):
        value = float(h)
        if not np.isfinite(value) or value <= 0.0:
            raise ValueError(f"h must be finite and > 0, got {value}.")


def check_counts(n_steps, save_every, name="n_steps"):
    if isinstance(n_steps, jax.core.Tracer):
        raise ValueError(f"A traced {name} needs max_steps, the elements reserved (n_steps is then a value).")
    for label, value in ((name, n_steps), ("save_every", save_every)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{label} must be an integer >= 1, got {value!r}.")
    if n_steps % save_every:
        raise ValueError(f"{name} ({n_steps}) must be a multiple of save_every ({save_every}).")


def check_count(n_steps):
    """``n_steps`` of a reserve (``max_steps``): an integer >= 1, or a traced integer scalar
    (whose value the run checks: INVALID_INPUT below 0). Returns it as an int32 value."""
    if isinstance(n_steps, jax.core.Tracer):
        if jnp.ndim(n_steps) != 0 or not jnp.issubdtype(jnp.result_type(n_steps), jnp.integer):
            raise TypeError(f"A traced n_steps must be an integer scalar, got {jax.typeof(n_steps)}.")
        return jnp.asarray(n_steps, jnp.int32)
    if isinstance(n_steps, bool) or not isinstance(n_steps, (int, np.integer)) and not (
            isinstance(n_steps, jax.Array) and n_steps.ndim == 0 and jnp.issubdtype(n_steps.dtype, jnp.integer)):
        raise ValueError(f"n_steps must be an integer >= 1, got {n_steps!r}.")
    if int(n_steps) < 1:
        raise ValueError(f"n_steps must be an integer >= 1, got {n_steps!r}.")
    return jnp.asarray(n_steps, jnp.int32)


def check_iterations(max_newton_iterations):
    value = max_newton_iterations
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"max_newton_iterations must be an integer >= 1, got {value!r}.")


def check_scalar_output(fn, q0, p0, name="H"):
    """The bound function must return a real scalar; checked by ``jax.eval_shape``."""
    try:
        out = jax.eval_shape(fn, q0, p0)
    except TypeError as error:
        raise TypeError(f"{name} could not be called as {name}(q, p[, args]): {error}") from error
    if out.shape != ():
        raise ValueError(f"{name} must return a scalar, got shape {out.shape}.")
    if not jnp.issubdtype(out.dtype, jnp.floating):
        raise TypeError(f"{name} must return a real floating scalar, got dtype {out.dtype}.")



CENTRAL_FORCE_RTOL = 100.0  # in eps * d: round-off of H at the probes is a few eps * d


def _orthogonal(d, seed):
    """A fixed orthogonal d x d matrix (QR of a seeded Gaussian matrix); a reflection for d = 1."""
    if d == 1:
        return -np.ones((1, 1))
    Q, R = np.linalg.qr(np.random.default_rng(seed).normal(size=(d, d)))
    return Q * np.sign(np.diag(R))


def _probe(H, q0, p0):
    """H and its round-off scale |H| + |q| |dH/dq| + |p| |dH/dp| at points derived from q0, p0:
    dicts keyed by (q name, p name), or None where H's values are traced."""
    d = q0.shape[0]
    a, b = (np.asarray(x, np.float64) for x in (q0, p0))
    a, b = (a if np.any(a) else np.eye(d)[0]), (b if np.any(b) else np.eye(d)[-1])
    u = _orthogonal(d, 2) @ b
    qs = {"q": a, "Rq": _orthogonal(d, 1) @ a, "sq": 1.1 * a, "Rsq": _orthogonal(d, 2) @ (1.1 * a)}
    ps = {"0": 0.0 * b, "p": b, "2p": 2.0 * b, "-p": -b, "Rp": _orthogonal(d, 1) @ b, "u": u, "p+u": b + u, "p-u": b - u}
    keys = [(i, j) for i in qs for j in ps]
    Q = jnp.asarray(np.stack([qs[i] for i, _ in keys]), q0.dtype)
    P = jnp.asarray(np.stack([ps[j] for _, j in keys]), q0.dtype)
    values = jax.vmap(H)(Q, P)
    dq, dp = jax.vmap(jax.grad(H, argnums=(0, 1)))(Q, P)
    if any(isinstance(x, jax.core.Tracer) for x in (values, dq, dp)):
        return None
    norm = lambda x: np.linalg.norm(np.asarray(x, np.float64), axis=-1)
    scale = np.abs(np.asarray(values, np.float64)) + norm(Q) * norm(dq) + norm(P) * norm(dp)
    return dict(zip(keys, np.asarray(values, np.float64))), dict(zip(keys, scale))


def check_central_force(H, q0, p0):
    """ModifiedMidpoint's premise: H = |p|^2 / (2m) + V(|q|) [GBS, eq. (77)], tested numerically.

    At points derived deterministically from q0, p0 (rotations by fixed orthogonal matrices,
    scalings), in the state's dtype: H(q, 0) = V must not change when q is rotated, and
    T(q, p) = H(q, p) - H(q, 0) must not depend on q and must be a quadratic form in p
    (T(2p) = 4 T(p), T(-p) = T(p), the parallelogram law). Any constant mass matrix passes:
    the scheme conserves energy with it too. Each equality holds to 100 d eps times the
    round-off scale |H| + |q| |dH/dq| + |p| |dH/dp| of its terms. Skipped where q0, p0 or H's
    values are traced, and at probes where H or its gradient is not finite.

    Args:
        H: ``H(q, p)`` with any args bound.
        q0, p0: shape ``(d,)``, one float dtype (as returned by ``check_state``).
    Raises:
        ValueError: naming the property that fails, and pointing to gj.DiscreteGradient().
    """
    if not (_concrete(q0) and _concrete(p0)):
        return
    probed = _probe(H, q0, p0)
    if probed is None:
        return
    value, scale = probed
    T = lambda i, j: (value[i, j] - value[i, "0"], scale[i, j] + scale[i, "0"])
    tests = {
        "H(q, 0) changes when q is rotated, so V is not a function of |q|": [
            ((value["q", "0"], scale["q", "0"]), (value["Rq", "0"], scale["Rq", "0"])),
            ((value["sq", "0"], scale["sq", "0"]), (value["Rsq", "0"], scale["Rsq", "0"])),
        ],
        "H(q, p) - H(q, 0) changes with q, so the kinetic energy depends on q": [
            (T("q", j), T(i, j)) for i in ("Rq", "sq", "Rsq") for j in ("p", "Rp", "p+u")
        ],
        "H(q, p) - H(q, 0) is not a quadratic form in p": [
            (T("q", "2p"), _combine((4.0, T("q", "p")))),
            (T("q", "-p"), T("q", "p")),
            (_combine((1.0, T("q", "p+u")), (1.0, T("q", "p-u"))), _combine((2.0, T("q", "p")), (2.0, T("q", "u")))),
        ],
    }
    tol = CENTRAL_FORCE_RTOL * q0.shape[0] * float(jnp.finfo(q0.dtype).eps)
    for problem, pairs in tests.items():
        for (x, sx), (y, sy) in pairs:
            if np.isfinite(x) and np.isfinite(y) and np.isfinite(sx + sy) and abs(x - y) > tol * (sx + sy):
                raise ValueError(
                    "ModifiedMidpoint needs H = |p|^2/(2m) + V(|q|) (more generally T(p) + V(|q|) with T "
                    f"a quadratic form) [GBS, eq. (77)]; here {problem} (tested at points derived from "
                    f"q0 = {np.asarray(q0)}, p0 = {np.asarray(p0)}: {float(x)!r} against {float(y)!r}). "
                    "Use gj.DiscreteGradient() for other Hamiltonians."
                )


def _combine(*terms):
    """sum c (value, scale) as (sum c value, sum |c| scale)."""
    return sum(c * v for c, (v, _) in terms), sum(abs(c) * s for c, (_, s) in terms)


def check_premise(method, H, q0, p0):
    """Checks that a method's assumption about H holds (ModifiedMidpoint: a central force), and
    the ``premise(H, q0, p0)`` of the method and of the methods it wraps (``method.method``;
    ``Splitting``: H separable)."""
    from ._midpoint import ModifiedMidpoint  # here: _midpoint's lead-edited imports may grow

    if isinstance(method, ModifiedMidpoint):
        check_central_force(H, q0, p0)
    for layer in layers(method):
        premise = getattr(layer, "premise", None)
        if callable(premise):
            premise(H, q0, p0)


def check_sweep(H, configs, n_steps, save_every, invariants, reference):
    """Every input check of ``sweep``, before anything is traced; returns ``configs`` with
    q0, p0 and h in the state's float dtype (a ``Float32Warning`` below float64).

    Args:
        H: ``H(q, p)`` or ``H(q, p, args)``.
        configs: ``Configs`` with batch size B.
        n_steps: int >= 1; save_every: None or an int >= 1 dividing n_steps.
        invariants: None or a dict ``{name: I(q, p)}`` (as the user passed it).
        reference: None or ``(q_ref, p_ref)``, each of shape ``(B, d)``.
    Returns:
        ``Configs``.
    """
    check_function(H)
    if not isinstance(configs, Configs):
        raise TypeError(f"configs must be gj.Configs (see gj.grid), got {type(configs).__name__}.")
    configs = _check_configs(configs)
    if isinstance(n_steps, bool) or not isinstance(n_steps, (int, np.integer)) or n_steps < 1:
        raise ValueError(f"n_steps must be an integer >= 1, got {n_steps!r}.")
    check_counts(n_steps, n_steps if save_every is None else save_every)
    args0 = jax.tree.map(lambda x: x[0], configs.args)
    fn = H if configs.args is None else (lambda q, p: H(q, p, args0))
    check_scalar_output(fn, configs.q0[0], configs.p0[0])
    _check_invariants(invariants, configs.q0[0], configs.p0[0])
    _check_reference(reference, configs.q0.shape)
    for b in sorted({0, configs.size - 1}):
        member = jax.tree.map(lambda x: x[b], (configs.method, configs.args))
        bound = H if configs.args is None else (lambda q, p: H(q, p, member[1]))
        check_premise(member[0], bound, configs.q0[b], configs.p0[b])
    return configs


def _check_configs(configs):
    h, q0, p0 = (jnp.asarray(x) for x in (configs.h, configs.q0, configs.p0))
    if h.ndim != 1 or h.shape[0] == 0:
        raise ValueError(f"configs.h must have shape (B,) with B >= 1, got shape {h.shape}.")
    B = h.shape[0]
    for name, x in (("q0", q0), ("p0", p0)):
        if x.ndim != 2 or x.shape[0] != B or x.shape[1] == 0:
            raise ValueError(
                f"configs.{name} must have shape (B, d) with B = {B} (the length of configs.h), d >= 1; got {x.shape}."
            )
    if q0.shape != p0.shape:
        raise ValueError(f"configs.q0 and configs.p0 must have the same shape (B, d), got {q0.shape} and {p0.shape}.")
    _check_batched_method(configs.method, B)
    for path, leaf in jax.tree_util.tree_leaves_with_path(configs.args):
        if jnp.ndim(leaf) == 0 or jnp.shape(leaf)[0] != B:
            raise ValueError(
                f"configs.args{jax.tree_util.keystr(path)} needs a leading axis of size B = {B}, got shape "
                f"{jnp.shape(leaf)}; gj.grid stacks args for you."
            )
    dtype = state_dtype(q0, p0)
    warn_if_low_precision(dtype)
    q0, p0, h = q0.astype(dtype), p0.astype(dtype), h.astype(dtype)
    for name, x in (("h", h), ("q0", q0), ("p0", p0)):
        if _concrete(x):
            values = np.asarray(x).reshape(B, -1)
            bad = ~np.all(np.isfinite(values) & ((values > 0) if name == "h" else True), axis=1)
            if np.any(bad):
                b = int(np.argmax(bad))
                need = "finite and > 0" if name == "h" else "finite"
                raise ValueError(f"configs.{name}: every {name} must be {need}, got {values[b]} in configuration {b}.")
    return dataclasses.replace(configs, q0=q0, p0=p0, h=h)


def _check_batched_method(method, B):
    if not all(callable(getattr(method, m, None)) for m in MEMBERS):
        raise TypeError(
            "configs.method must be a galerkin_jax method with stacked arrays (gj.stack_methods), "
            f"got {type(method).__name__}."
        )
    for path, leaf in jax.tree_util.tree_leaves_with_path(method):
        if jnp.ndim(leaf) < 2 or jnp.shape(leaf)[0] != B:
            raise ValueError(
                f"configs.method{jax.tree_util.keystr(path)} needs shape (B, n_q) with B = {B}, got "
                f"{jnp.shape(leaf)}; stack the methods with gj.stack_methods([...]) (gj.grid does)."
            )


def _check_invariants(invariants, q, p):
    if invariants is None:
        return
    if not isinstance(invariants, Mapping):
        raise TypeError(f"invariants must be a dict {{name: I(q, p)}}, got {type(invariants).__name__}.")
    for name, I in invariants.items():
        if not callable(I):
            raise TypeError(f"invariants[{name!r}] must be a function I(q, p), got {type(I).__name__}.")
        try:
            out = jax.eval_shape(I, q, p)
        except TypeError as error:
            raise TypeError(f"invariants[{name!r}] could not be called as I(q, p): {error}") from error
        if not isinstance(out, jax.ShapeDtypeStruct) or not jnp.issubdtype(out.dtype, jnp.floating):
            raise TypeError(f"invariants[{name!r}] must return a real floating array (any shape), got {out}.")


def _check_reference(reference, shape):
    if reference is None:
        return
    shapes = None
    if isinstance(reference, (tuple, list)) and len(reference) == 2:
        shapes = [jnp.shape(r) for r in reference]
    if shapes != [shape, shape]:
        got = shapes if shapes is not None else type(reference).__name__
        raise ValueError(f"reference must be (q_ref, p_ref), each of shape (B, d) = {shape}, got {got}.")
