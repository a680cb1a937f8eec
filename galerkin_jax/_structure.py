"""The structure of a Hamiltonian read from its program: is H separable, H = T(p) + V(q)?

``structure`` traces Hamilton's field ``(dH/dq, dH/dp)`` to a jaxpr and follows which inputs
each value depends on, equation by equation (a dependency analysis, not a test at a state):
H is separable exactly where dH/dq reads no p and dH/dp reads no q. The analysis over-
approximates: an equation's outputs depend on all its inputs unless its inner program is
followed (calls, custom derivatives, ``cond``, ``scan``, ``while_loop`` by a fixed point), so a
"separable" answer is always right, and a term that vanishes only by value (``eps * q * p``
with ``eps = 0`` in ``args``, ``q * p - p * q``, ``0.0 * q * p``) reads as general. A program with
effects (``io_callback``, mutable references) is not analysed: general.
"""

import dataclasses

import jax
import jax.numpy as jnp
from jax.extend import core as jcore

_Q, _P = 1, 2  # dependency bits: on q, on p (args and constants: none)


@dataclasses.dataclass(frozen=True)
class Structure:
    """What ``gj.structure`` read from H's program.

    Attributes:
        separable: True where H = T(p) + V(q) (up to terms in args alone): dH/dq does not
            depend on p and dH/dp not on q, as a program, whatever the values. False where
            it may not be so ("general"): the answer is never a wrong True.
        force_reads_p: dH/dq may depend on p.
        velocity_reads_q: dH/dp may depend on q.
        reason: why H reads as general ("" where separable).
        kinetic_quadratic: True where moreover T is quadratic in p with a constant matrix,
            T = p^T M p / 2 + b^T p + c: the Hessian d^2H/dp^2 reads neither q nor p, as a
            program (a Runge-Kutta-Nystrom splitting has its order there). False where it may
            not be so: never a wrong True.
    """

    separable: bool
    force_reads_p: bool
    velocity_reads_q: bool
    reason: str = ""
    kinetic_quadratic: bool = False


class _Undecidable(Exception):
    pass


def _read(deps, v):
    return deps.get(v, 0) if isinstance(v, jcore.Var) else 0  # a Literal is a constant


def _run(jaxpr, in_deps):
    """The dependency bits of ``jaxpr``'s outputs from those of its inputs."""
    jaxpr = jaxpr.jaxpr if isinstance(jaxpr, jcore.ClosedJaxpr) else jaxpr
    deps = dict(zip(jaxpr.invars, in_deps))
    for eqn in jaxpr.eqns:
        if eqn.effects:
            raise _Undecidable(f"the program has effects ({eqn.primitive.name})")
        ins = [_read(deps, v) for v in eqn.invars]
        for v, d in zip(eqn.outvars, _equation(eqn, ins)):
            deps[v] = d
    return [_read(deps, v) for v in jaxpr.outvars]


def _union(bits):
    out = 0
    for b in bits:
        out |= b
    return out


def _loop(step, carry):
    """The least fixed point of ``carry |= step(carry)`` (bits only grow: it ends)."""
    while True:
        new = [a | b for a, b in zip(carry, step(carry))]
        if new == carry:
            return carry
        carry = new


def _equation(eqn, ins):
    """Output bits of one equation: its inner program followed where it is one of the known
    forms, else every output on every input (always sound)."""
    name, params, n_out = eqn.primitive.name, eqn.params, len(eqn.outvars)
    if name == "scan":
        nc, nk = params["num_consts"], params["num_carry"]
        consts, xs = ins[:nc], ins[nc + nk:]
        body = lambda carry: _run(params["jaxpr"], consts + carry + xs)[:nk]
        carry = _loop(body, ins[nc:nc + nk])
        return carry + _run(params["jaxpr"], consts + carry + xs)[nk:]
    if name == "while":
        cn, bn = params["cond_nconsts"], params["body_nconsts"]
        cc, bc = ins[:cn], ins[cn:cn + bn]

        def body(carry):  # a value the loop's condition reads decides every output
            stop = _run(params["cond_jaxpr"], cc + carry)[0]
            return [b | stop for b in _run(params["body_jaxpr"], bc + carry)]

        return _loop(body, ins[cn + bn:])
    if name == "cond":
        index, operands = ins[0], ins[1:]
        outs = [_run(branch, operands) for branch in params["branches"]]
        return [_union(col) | index for col in zip(*outs)]
    inner = [v for v in params.values() if isinstance(v, (jcore.ClosedJaxpr, jcore.Jaxpr))]
    if name in ("pjit", "jit", "closed_call", "core_call", "custom_jvp_call", "custom_vjp_call",
                "custom_vjp_call_jaxpr", "remat", "checkpoint", "custom_lin") and len(inner) >= 1:
        j = inner[0].jaxpr if isinstance(inner[0], jcore.ClosedJaxpr) else inner[0]
        if len(j.invars) == len(ins) and len(j.outvars) == n_out:
            return _run(inner[0], ins)
    for j in inner:  # not followed, but its effects would be missed
        body = j.jaxpr if isinstance(j, jcore.ClosedJaxpr) else j
        if any(e.effects for e in body.eqns):
            raise _Undecidable(f"the program has effects (inside {name})")
    return [_union(ins)] * n_out


def structure(H, q0, p0, args=None) -> Structure:
    """Whether ``H`` is separable, H = T(p) + V(q), read from its program (not its values).

    Traces ``jax.grad(H, argnums=(0, 1))`` at the shapes and dtypes of ``q0, p0`` (and
    ``args``, whose values are constants of the analysis) and follows each value's
    dependencies on q and p through the jaxpr: H is separable where dH/dq reads no p and
    dH/dp no q; its T is quadratic where, moreover, the Hessian d^2H/dp^2 reads neither.
    Sound, not complete: a term that cancels only by value reads as general
    ([Explicit elements](methods.md#explicit-elements-and-compositions)). A separable H lets ``GalerkinVI(1,
    gj.trapezoid())`` (Stormer-Verlet) and its compositions run without iteration.

    Args:
        H: the Hamiltonian, ``H(q, p)``, or ``H(q, p, args)`` with ``args`` given; required.
        q0, p0: a state (arrays of any shape, or pytrees of them) whose shapes and dtypes
            are read, not its values; required.
        args: the extra input of H, passed as its third argument; default None.
    Returns:
        ``Structure``.
    """
    shape = lambda x: jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x))
    q0, p0 = jax.tree.map(shape, q0), jax.tree.map(shape, p0)
    field = jax.grad(H if args is None else (lambda q, p, a: H(q, p, a)), argnums=(0, 1))
    operands = (q0, p0) if args is None else (q0, p0, jax.tree.map(shape, args))
    n_q, n_p = len(jax.tree.leaves(q0)), len(jax.tree.leaves(p0))
    try:
        closed = jax.make_jaxpr(field)(*operands)
    except Exception as e:  # noqa: BLE001 -- what cannot be traced cannot be read: general
        return Structure(False, True, True, f"undecidable: dH/dq, dH/dp could not be traced ({type(e).__name__})")
    try:
        out = _outputs_read(closed, n_q, n_p)
    except _Undecidable as e:
        return Structure(False, True, True, f"undecidable: {e}")
    force_reads_p = any(b & _P for b in out[:n_q])
    velocity_reads_q = any(b & _Q for b in out[n_q:])
    reasons = ["dH/dq reads p"] * force_reads_p + ["dH/dp reads q"] * velocity_reads_q
    quadratic = not reasons and _constant_in_p(H, operands, n_q, n_p)
    return Structure(not reasons, force_reads_p, velocity_reads_q, "; ".join(reasons), quadratic)


def _outputs_read(closed, n_q, n_p):
    """The dependency bits of a traced function's outputs, its inputs n_q leaves of q, n_p of p
    and then args (constants of the analysis)."""
    return _run(closed, [_Q] * n_q + [_P] * n_p + [0] * (len(closed.jaxpr.invars) - n_q - n_p))


def _constant_in_p(H, operands, n_q, n_p):
    """Whether the program of d^2H/dp^2 reads neither q nor p (False where undecidable)."""
    hessian = jax.jacfwd(jax.grad(H, argnums=1), argnums=1)
    try:
        return not any(_outputs_read(jax.make_jaxpr(hessian)(*operands), n_q, n_p))
    except Exception:  # noqa: BLE001 -- what cannot be traced or read (effects) is not constant
        return False
