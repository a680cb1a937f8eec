"""Batched parameter sweeps: one scene over many configurations in one jitted call.

The batch is solved by ``_batched``'s batch-aware simplified Newton method (Jacobians kept
across elements, refreshed per member on demand). Diagnostics are folded into the scan
carry, so a sweep stores no trajectory unless ``save_every`` asks for one. Each
configuration has its own status and its own iterates: a failed one turns NaN, stops
costing Newton iterations and leaves the others' values and gradients as they are alone.
"""

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from . import _checks
from ._batched import march_batched
from ._configs import Configs
from ._integrate import DEFAULT_MAX_NEWTON_ITERATIONS, Solution, bind_args, nan_if_failed
from ._pytree import pytree_dataclass


@pytree_dataclass
class SweepResult:
    """Per-configuration diagnostics, each with a leading axis B.

    Attributes:
        energy_error: max_n |H_n - H_0| / |H_0| (absolute where H_0 = 0) of the function
            passed; for ``LagrangianVI`` that is L, not an energy: use ``invariants``.
        invariant_errors: name -> max_n max_i |I_n - I_0|_i / max_i |I_0|_i (absolute where I_0 = 0).
        final_error: max |(q_N, p_N) - reference| or None.
        q, p: the final state, ``(B, d)``.
        status: ``Status`` codes; NaN diagnostics go with a nonzero status.
        num_newton_iterations, max_newton_iterations: total and largest per element.
        batch_newton_iterations: the iterations the batch ran, the sum over elements of the
            largest member count (the same for every member; ``1 - num / batch`` is the share
            of the batch's work a member spent waiting for slower members).
        solution: a batched ``Solution`` when ``save_every`` was given, else None; its
            ``stats`` are the Newton counts above.
    """

    energy_error: jax.Array
    invariant_errors: dict
    final_error: Any
    q: jax.Array
    p: jax.Array
    status: jax.Array
    num_newton_iterations: jax.Array
    max_newton_iterations: jax.Array
    batch_newton_iterations: jax.Array
    solution: Any = None


def _relative_change(value, initial):
    scale = jnp.max(jnp.abs(initial))
    return jnp.max(jnp.abs(value - initial)) / jnp.where(scale > 0, scale, 1.0)


def _diagnostics(H, invariants, q0, p0, args):
    """``(acc0, observe)``: the largest relative changes of H and of the invariants, folded
    into the scan carry by the batched ``observe(acc, q, p)``; the initial values and args
    are closed over, not carried."""

    def initial(q, p, a):
        return bind_args(H, a)(q, p), tuple(I(q, p) for I in invariants.values())

    def observe_one(acc, q, p, start, args):
        (energy, others), (H0, I0s) = acc, start
        energy = jnp.fmax(energy, _relative_change(bind_args(H, args)(q, p), H0))
        others = tuple(jnp.fmax(e, _relative_change(I(q, p), I0)) for e, I, I0 in zip(others, invariants.values(), I0s))
        # fmax ignores NaN: a failed run is flagged by its status and made NaN below
        return energy, others

    start = jax.vmap(initial)(q0, p0, args)
    zero = jnp.zeros(q0.shape[0], q0.dtype)
    return (zero, tuple(zero for _ in invariants)), lambda acc, q, p: jax.vmap(observe_one)(acc, q, p, start, args)


def _block_size(n_steps, save_every, checkpoint):
    """Elements per block of the nested scan: ``save_every``, else one block, or with
    ``checkpoint`` the divisor of ``n_steps`` nearest sqrt(n_steps) (memory ~ blocks + block)."""
    if save_every or not checkpoint:
        return save_every or n_steps
    divisors = [b for b in range(1, n_steps + 1) if n_steps % b == 0]
    return min(divisors, key=lambda b: abs(b - n_steps**0.5))


@functools.partial(jax.jit, static_argnums=(0, 1, 2, 3, 4, 5))
def _run(H, invariants, n_steps, save_every, max_iterations, checkpoint, configs, reference):
    invariants = dict(invariants)
    c = configs
    acc0, observe = _diagnostics(H, invariants, c.q0, c.p0, c.args)
    block = _block_size(n_steps, save_every, checkpoint)
    final, (qs, ps) = march_batched(
        c.method, H, c.args, c.q0, c.p0, c.h, n_blocks=n_steps // block, block_size=block,
        max_iterations=max_iterations, observe=observe, acc0=acc0, checkpoint=checkpoint,
    )
    energy, others = final["acc"]
    final_error = None
    if reference is not None:
        final_error = jnp.max(jnp.abs(jnp.concatenate([final["q"] - reference[0], final["p"] - reference[1]], axis=1)), axis=1)
    solution = None
    if save_every:
        times = jnp.arange(n_steps // block + 1, dtype=c.q0.dtype)
        solution = Solution(
            t=times[None, :] * (block * c.h[:, None]),
            q=jnp.concatenate([c.q0[:, None], qs], axis=1), p=jnp.concatenate([c.p0[:, None], ps], axis=1),
            status=final["status"],
            stats={"num_newton_iterations": final["total"], "max_newton_iterations": final["most"]},
        )
    return SweepResult(
        energy_error=nan_if_failed(energy, final["status"]),
        invariant_errors={name: nan_if_failed(e, final["status"]) for name, e in zip(invariants, others)},
        final_error=final_error,
        q=final["q"], p=final["p"], status=final["status"],
        num_newton_iterations=final["total"], max_newton_iterations=final["most"],
        batch_newton_iterations=jnp.broadcast_to(final["batch"], final["total"].shape),
        solution=solution,
    )


def _check(H, configs, n_steps, save_every, invariants, reference):
    _checks.check_function(H)
    if not isinstance(configs, Configs):
        raise TypeError(f"configs must be gj.Configs (see gj.grid), got {type(configs).__name__}.")
    B = configs.size
    if configs.q0.ndim != 2 or configs.q0.shape != configs.p0.shape or configs.q0.shape[0] != B:
        raise ValueError(f"configs: q0 and p0 need shape (B, d) with B = {B}, got {configs.q0.shape}, {configs.p0.shape}.")
    for leaf in jax.tree_util.tree_leaves((configs.method, configs.args)):
        if jnp.ndim(leaf) == 0 or jnp.shape(leaf)[0] != B:
            raise ValueError(f"configs: every method and args leaf needs a leading axis of size B = {B}.")
    if not isinstance(configs.h, jax.core.Tracer) and not np.all(np.asarray(configs.h) > 0):
        raise ValueError("configs: every h must be finite and > 0.")
    _checks.check_counts(n_steps, n_steps or 1 if save_every is None else save_every)
    if n_steps < 1:
        raise ValueError("n_steps must be >= 1.")
    if not all(callable(I) for I in invariants.values()):
        raise TypeError("invariants must map names to functions I(q, p).")
    if reference is not None and (len(reference) != 2 or jnp.shape(reference[0]) != configs.q0.shape):
        raise ValueError(f"reference must be (q_ref, p_ref), each of shape {configs.q0.shape}.")


def _shard(tree, devices):
    """Pad the batch axis to a multiple of the device count and place it along a 1-D mesh."""
    mesh = Mesh(np.asarray(devices), ("batch",))
    sharding = NamedSharding(mesh, PartitionSpec("batch"))
    size = jax.tree_util.tree_leaves(tree)[0].shape[0]
    pad = (-size) % len(devices)
    # padding repeats the last configuration: valid values, discarded afterwards
    padded = jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]), tree)
    return jax.device_put(padded, sharding)


def sweep(
    H,
    configs,
    *,
    n_steps,
    invariants=None,
    reference=None,
    save_every=None,
    max_newton_iterations=DEFAULT_MAX_NEWTON_ITERATIONS,
    devices=None,
    checkpoint=False,
):
    """Run every configuration of ``configs`` for ``n_steps`` elements in one compiled call.

    Args:
        H: ``H(q, p)`` or ``H(q, p, args)``.
        configs: ``Configs`` with batch size B (e.g. from ``grid``).
        n_steps: elements per configuration. Static.
        invariants: ``{name: I(q, p)}`` whose relative change is tracked (e.g. angular momentum).
        reference: ``(q_ref, p_ref)`` of shape ``(B, d)`` for ``final_error``.
        save_every: store a trajectory with this stride (``SweepResult.solution``); default none.
        devices: shard the batch over these devices (e.g. ``jax.devices()``); results equal
            the unsharded run (up to how XLA compiles the per-device batch size). Several hosts: call ``jax.distributed.initialize()`` first and
            pass ``jax.devices()`` (all global devices).
        checkpoint: rematerialise blocks of elements in reverse mode (blocks of ``save_every``,
            or of the divisor of ``n_steps`` nearest its square root: choose an ``n_steps``
            with one), so that a gradient stores one carry per block instead of every
            element's residuals. Static.
    Returns:
        ``SweepResult`` with a leading axis B on every field.
    """
    invariants = dict(invariants or {})
    _check(H, configs, n_steps, save_every, invariants, reference)
    _checks.check_iterations(max_newton_iterations)
    reference = None if reference is None else tuple(jnp.asarray(r) for r in reference)
    inputs = (configs, reference)
    if devices is not None:
        inputs = _shard(inputs, devices)
    result = _run(H, tuple(invariants.items()), n_steps, save_every, max_newton_iterations, checkpoint, *inputs)
    if devices is not None:
        result = jax.tree.map(lambda x: x[: configs.size], result)
    return result
