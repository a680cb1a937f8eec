"""The state (q0, p0): its checks, its dtype and the warning below float64, before anything is traced.

A state is an array of any shape with at least one element, or a pytree of such arrays; q0 and
p0 share the structure and shapes. Everything else depends on this module, which depends on
nothing of the package.
"""

import os
import sys
import warnings

import jax
import jax.numpy as jnp
import numpy as np


def _concrete(x):
    return not isinstance(x, jax.core.Tracer)


def state_dtype(*arrays):
    """The real floating dtype the library computes in for these state arrays."""
    dtype = jnp.result_type(*arrays, float)
    if not jnp.issubdtype(dtype, jnp.floating):
        raise TypeError(f"q0 and p0 must be real arrays, got dtype {dtype}.")
    return dtype


class Float32Warning(UserWarning):
    """The library is computing in float32 (or a lower precision): JAX's default without x64.

    Round-off then limits every result to ~1e-6 relative, energy conservation included.
    Silence it with ``warnings.filterwarnings("ignore", category=gj.Float32Warning)``.
    """


_warned_low_precision = False


def _caller_stacklevel():
    """``stacklevel`` for ``warnings.warn`` that points at the first frame outside this package."""
    package = os.path.dirname(os.path.abspath(__file__))
    frame, level = sys._getframe(2), 2
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(package + os.sep):
        frame, level = frame.f_back, level + 1
    return level


def warn_if_low_precision(dtype):
    """Warn, once per process, when the state's dtype is less precise than float64."""
    global _warned_low_precision
    eps = float(jnp.finfo(dtype).eps)
    if _warned_low_precision or eps <= float(np.finfo(np.float64).eps):
        return
    floor = 10.0 ** np.ceil(np.log10(eps))
    warnings.warn(
        f"galerkin_jax is computing in {jnp.dtype(dtype).name} (eps = {eps:.1e}; JAX's default unless "
        f"x64 is enabled): expect a round-off floor of ~{floor:.0e} relative in the states, and "
        f"energy conserved only to ~{floor:.0e} relative (float64: ~1e-15). For float64 call "
        'jax.config.update("jax_enable_x64", True) at start-up, before creating arrays. To '
        'silence this warning: warnings.filterwarnings("ignore", category=gj.Float32Warning). '
        "It is shown once per process.",
        Float32Warning,
        stacklevel=_caller_stacklevel(),
    )
    _warned_low_precision = True  # after warn: with an "error" filter every call raises


def _is_numbers(x):
    """A (nested) list or tuple of numbers, which is read as one array (not a pytree)."""
    if isinstance(x, (list, tuple)):
        return len(x) > 0 and all(_is_numbers(v) for v in x)
    return isinstance(x, (int, float, np.number)) and not isinstance(x, bool)


def state_leaves(x, name):
    """``(leaves, treedef, paths)`` of a state: an array of any shape or a pytree of arrays
    (a nested list of numbers is one array); leaves as JAX arrays of real numbers."""
    if _is_numbers(x):
        x = jnp.asarray(x)
    flat, treedef = jax.tree_util.tree_flatten_with_path(x)
    paths, leaves = [jax.tree_util.keystr(path) for path, _ in flat], []
    for path, (_, leaf) in zip(paths, flat):
        try:
            leaf = leaf if isinstance(leaf, jax.Array) else jnp.asarray(leaf)
        except (TypeError, ValueError):
            raise ValueError(f"{name}{path} must be an array of real numbers, got {type(leaf).__name__}.") from None
        kind = leaf.dtype
        if kind == jnp.bool_ or not (jnp.issubdtype(kind, jnp.floating) or jnp.issubdtype(kind, jnp.integer)):
            raise ValueError(f"{name}{path} must hold real numbers (a float dtype), got dtype {kind}.")
        leaves.append(leaf)
    return leaves, treedef, paths


def check_state(q0, p0):
    """Convert q0, p0 to states of one shape and one float dtype; returns them.

    A state is an array of any shape with at least one element (``(d,)``, ``(N, 3)``, ...)
    or a pytree of such arrays; q0 and p0 have the same structure and shapes. The dtype is
    that of the inputs (floats promote, integers become JAX's default float); below float64
    a ``Float32Warning`` is given once per process.
    """
    (qs, q_tree, paths), (ps, p_tree, _) = state_leaves(q0, "q0"), state_leaves(p0, "p0")
    if q_tree != p_tree:
        raise ValueError(f"q0 and p0 must have the same structure, got {q_tree} and {p_tree}.")
    if sum(x.size for x in qs) == 0:
        raise ValueError(f"q0 must have at least one element (an array of any shape, or a pytree of arrays), "
                         f"got shapes {[x.shape for x in qs]}.")
    for path, q, p in zip(paths, qs, ps):
        if q.shape != p.shape:
            raise ValueError(f"q0{path} and p0{path} must have the same shape, got {q.shape} and {p.shape}.")
    dtype = state_dtype(*qs, *ps)
    warn_if_low_precision(dtype)
    qs, ps = [x.astype(dtype) for x in qs], [x.astype(dtype) for x in ps]
    for name, xs in (("q0", qs), ("p0", ps)):
        for path, x in zip(paths, xs):
            if _concrete(x) and not np.all(np.isfinite(np.asarray(x))):
                raise ValueError(f"{name}{path} must be finite, got {non_finite(x)}.")
    return q_tree.unflatten(qs), p_tree.unflatten(ps)


def non_finite(x):
    """Where a concrete array is not finite, in a few words: ``3 of 100 entries are not finite,
    the first nan at index (0,)``, however large the array."""
    values = np.asarray(x)
    bad = ~np.isfinite(values)
    first = np.unravel_index(int(np.argmax(bad)), values.shape) if values.ndim else ()
    return (f"{int(bad.sum())} of {values.size} entries not finite, the first {values[first]} at index "
            f"{tuple(int(i) for i in first)}")
