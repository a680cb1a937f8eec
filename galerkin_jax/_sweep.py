"""Batched parameter sweeps: one scene over many configurations in one jitted call.

A sweep is ``jax.vmap`` of the single-run ``march`` over the configurations: every member
runs exactly the code of ``integrate``, and the root finder folds the batch into one loop
(``_solve``). Diagnostics are folded into the scan carry, so a sweep stores no trajectory
unless ``save_every`` asks for one. Each configuration has its own status and its own
iterates: a failed one turns NaN, stops costing iterations and leaves the others' values
and gradients as they are alone.
"""

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from . import _adjoint, _checks, _shape, _span
from ._controllers import TimeTransform
from ._explicit import sweep_form
from ._integrate import DEFAULT_MAX_STEPS, solution
from ._output import user_view
from ._march import bind_args, march, nan_if_failed, reserved_to_t1, short_of_t1, solver_options
from ._solve import Status, throw_if_failed
from ._pytree import pytree_dataclass


@pytree_dataclass
class SweepResult:
    """Per-configuration diagnostics, each with a leading axis B.

    Attributes:
        energy_error: the largest relative change of the function passed over the run,
            max_n |H_n - H_0| / |H_0| (absolute where H_0 = 0); for ``LagrangianVI`` that is L,
            not an energy: use ``invariants``.
        invariant_errors: the largest relative change of each invariant, name ->
            max_n max_i |I_n - I_0|_i / max_i |I_0|_i (absolute where I_0 = 0).
        final_error: the final state's error against ``reference``,
            max |(q_N, p_N) - reference|; None without a reference.
        q: the final position, ``(B,) + shape`` (a pytree state: each leaf with the leading axis B).
        p: the final momentum, likewise.
        status: each run's ``Status`` code; NaN diagnostics go with a nonzero status.
        error_estimate: the largest estimated local error of each run (``Solution.error_estimate``).
        num_newton_iterations: the iterations of each run's implicit solves, in total.
        max_newton_iterations: each run's largest count in one element.
        batch_newton_iterations: the iterations the batch ran, the sum over elements of the
            largest member count (the same for every member; ``1 - num / batch`` is the share
            of the batch's iterations a member spent waiting for slower members; in a batch of
            64 or more, the last eighth of the members to converge iterate apart, gathered,
            at an eighth of the cost).
        num_accepted_stalled: elements accepted other than at round-off
            (``Solution.stats``).
        num_steps: every attempt of each run, accepted or rejected (as in diffrax; fixed steps:
            the elements).
        num_accepted_steps: the accepted steps of each run.
        num_rejected_steps: the rejected steps of each run.
        solution: a batched ``Solution`` when ``save_every`` was given, else None; its
            ``stats`` are the Newton counts above.
    """

    energy_error: jax.Array
    invariant_errors: dict
    final_error: Any
    q: jax.Array
    p: jax.Array
    status: jax.Array
    error_estimate: jax.Array
    num_newton_iterations: jax.Array
    max_newton_iterations: jax.Array
    batch_newton_iterations: jax.Array
    num_accepted_stalled: Any = None
    num_steps: Any = None
    num_accepted_steps: Any = None
    num_rejected_steps: Any = None
    solution: Any = None


def _relative_change(value, initial):
    scale = jnp.max(jnp.abs(initial))
    return jnp.max(jnp.abs(value - initial)) / jnp.where(scale > 0, scale, 1.0)


def _diagnostics(H, invariants):
    """``(acc0, observe)``: ``acc0(q0, p0, args)`` starts the largest relative changes of H and of
    the invariants, and ``observe(acc, q, p)`` folds a state into them (the scan's carry, or a
    controlled run's). The start values H_0, I_0 and args travel in acc, so that both are
    functions of their arguments alone, which a controlled run's derivatives need (``_adjoint``)."""

    def acc0(q0, p0, args):
        fn, zero = bind_args(H, args), jnp.zeros((), q0.dtype)
        return dict(args=args, H0=fn(q0, p0), I0=tuple(I(q0, p0) for I in invariants.values()), energy=zero,
                    others=tuple(zero for _ in invariants))

    def observe(acc, q, p):
        fn = bind_args(H, acc["args"])
        # fmax ignores NaN: a failed run is flagged by its status and made NaN afterwards
        energy = jnp.fmax(acc["energy"], _relative_change(fn(q, p), acc["H0"]))
        others = tuple(jnp.fmax(e, _relative_change(I(q, p), I0))
                       for e, I, I0 in zip(acc["others"], invariants.values(), acc["I0"]))
        return dict(acc, energy=energy, others=others)

    return acc0, observe


def _block_size(n_steps, save_every, checkpoint):
    """Elements per block of the nested scan: ``save_every``, else one block, or with
    ``checkpoint`` the divisor of ``n_steps`` nearest sqrt(n_steps) (memory ~ blocks + block)."""
    if save_every or not checkpoint:
        return save_every or n_steps
    divisors = [b for b in range(1, n_steps + 1) if n_steps % b == 0]
    return min(divisors, key=lambda b: abs(b - n_steps**0.5))


def _final_error(final, reference):
    if reference is None:
        return None
    return jnp.max(jnp.abs(jnp.concatenate([final["q"] - reference[0], final["p"] - reference[1]], axis=1)), axis=1)


def _result(final, runs, invariants, reference):
    energy, others = final["acc"]["energy"], final["acc"]["others"]
    return SweepResult(
        energy_error=nan_if_failed(energy, final["status"]),
        invariant_errors={name: nan_if_failed(e, final["status"]) for name, e in zip(invariants, others)},
        final_error=_final_error(final, reference),
        q=final["q"], p=final["p"], status=final["status"], error_estimate=final["estimate"],
        num_newton_iterations=final["total"], max_newton_iterations=final["most"],
        batch_newton_iterations=final["trips"], num_accepted_stalled=final["lenient"],
        num_steps=final["attempts"], num_accepted_steps=final["steps"],
        num_rejected_steps=final["rejected"], solution=runs,
    )


@functools.partial(jax.jit, static_argnums=(0, 1, 2, 3, 4, 5, 6, 7, 8))
def _run(H, invariants, n_steps, save_every, options, checkpoint, progress, estimate, batch_size, configs, reference,
         t0, t1):
    """Fixed steps: ``n_steps`` elements, or to ``t1`` (each member its own count, at most n_steps)."""
    invariants = dict(invariants)
    block = _block_size(n_steps, save_every, checkpoint)

    acc0, observe = _diagnostics(H, invariants)

    def one(method, q0, p0, h, args):
        to_t1, t_end = {}, None
        if t1 is not None:
            n_active, h_last, t_end = reserved_to_t1(t0, t1, h, n_steps)
            to_t1 = dict(n_active=n_active, h_last=h_last)
        final, saved, _ = march(method, H, q0, p0, h, args, n_blocks=n_steps // block, block_size=block,
                                options=options, checkpoint=checkpoint, observe=observe, acc0=acc0(q0, p0, args),
                                progress=progress, estimate=estimate, **to_t1)
        final["rejected"], final["attempts"] = jnp.zeros_like(final["steps"]), final["steps"]
        if t1 is not None:
            final["status"] = short_of_t1(final["status"], t_end, t1)
        return final, (solution(final, saved, None, q0, p0, h, block, t0, t_end) if save_every else None)

    c = configs
    final, runs = _members(one, batch_size, c.method, c.q0, c.p0, c.h, c.args)
    return _result(final, runs, invariants, reference)


@functools.partial(jax.jit, static_argnums=(0, 1, 2, 3, 4, 5, 6))
def _run_adaptive(H, invariants, max_steps, options, estimate, checkpoint, batch_size, configs, reference, t0, t1,
                  controller):
    """A controller's runs to ``t1``, each member its own steps, with derivatives (``_adjoint``)."""
    invariants = dict(invariants)
    acc0, observe = _diagnostics(H, invariants)
    transform = controller if isinstance(controller, TimeTransform) else None
    spec = _adjoint.Spec(H, transform, options, max_steps, estimate=estimate, observe=observe, acc0=acc0,
                         checkpoint=checkpoint)

    def one(method, q0, p0, h, args, controller):
        c = _adjoint.run(spec, dict(q0=q0, p0=p0, args=args, method=method, controller=controller, t0=t0, t1=t1,
                                    ts=None, h=h))
        q, p = user_view(nan_if_failed(c["z"], c["status"]), None if transform is None else q0.shape[0])
        return dict(q=q, p=p, estimate=nan_if_failed(c["estimate"], c["status"]), acc=c["acc"],
                    **{k: c[k] for k in ("status", "total", "most", "trips", "steps", "attempts", "rejected", "lenient")})

    c = configs
    final = _members(one, batch_size, c.method, c.q0, c.p0, c.h, c.args, None if transform else controller)
    return _result(final, None, invariants, reference)


def _members(one, batch_size, *xs):
    """``one`` over the members (the leading axis of ``xs``): all at once (``vmap``), or in chunks
    of ``batch_size``, one after another (``lax.map``; chunks of one run unbatched)."""
    if batch_size is None:
        return jax.vmap(one)(*xs)
    return jax.lax.map(lambda x: one(*x), xs, batch_size=None if batch_size == 1 else batch_size)


def _check_batch_size(batch_size, devices, progress):
    """``batch_size`` as a Python int (a static argument), or None; bad values raise."""
    if batch_size is None:
        return None
    if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) or batch_size < 1:
        raise ValueError(f"batch_size must be a positive integer or None, got {batch_size!r}.")
    if devices is not None:
        raise ValueError("batch_size and devices exclude each other: a sharded sweep runs each device's members "
                         "at once.")
    if progress:
        raise ValueError("batch_size and progress exclude each other: the bar counts the elements of members "
                         "that advance together.")
    return int(batch_size)


def _shard(tree, devices):
    """Pad the batch axis to a multiple of the device count and place it along a 1-D mesh."""
    mesh = Mesh(np.asarray(devices), ("batch",))
    sharding = NamedSharding(mesh, PartitionSpec("batch"))
    size = jax.tree_util.tree_leaves(tree)[0].shape[0]
    pad = (-size) % len(devices)
    # padding repeats the last configuration: valid values, discarded afterwards
    padded = jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]), tree)
    return jax.device_put(padded, sharding)


@_shape.on_sweep
def sweep(
    H,
    configs,
    *,
    n_steps=None,
    t0=0.0,
    t1=None,
    controller=None,
    max_steps=None,
    invariants=None,
    reference=None,
    save_every=None,
    max_newton_iterations=None,
    krylov=None,
    solver=None,
    throw=False,
    devices=None,
    checkpoint=False,
    progress=False,
    error_estimate=True,
    batch_size=None,
) -> SweepResult:
    """Run every configuration of ``configs`` for ``n_steps`` elements, or to ``t1``, in one compiled call.

    Args:
        H: the Hamiltonian, ``H(q, p)`` or ``H(q, p, args)``; required.
        configs: the configurations to run, a ``Configs`` with batch size B (e.g. from ``grid``);
            required.
        n_steps: the number of elements per configuration; default None, then give ``t1``.
            Static.
        t0: the start time; default 0.0.
        t1: the end time, > t0, which every configuration reaches; default None, then give
            ``n_steps``. With fixed steps the last element is shortened and members of a smaller h
            take more elements. A traced t1 < t0 is status INVALID_INPUT; runs backwards in time
            are ``integrate``'s (under ``vmap`` over t1).
        controller: what chooses the steps, as in ``integrate``; default None, fixed steps. The
            fields of a ``PIDController`` may have shape (B,) to sweep tolerances.
        max_steps: a controller's cap on attempts per configuration; default None (4096). With
            fixed steps to t1 it is the elements reserved per member (a sweep to another t1
            within it compiles nothing new; required with traced step sizes). Static.
        invariants: the quantities whose largest relative change to track, ``{name: I(q, p)}``
            (e.g. angular momentum); default None, energy only.
        reference: the exact final state ``(q_ref, p_ref)``, each like ``configs.q0``
            (``(B,) + shape``), for ``SweepResult.final_error``; default None.
        save_every: the stride of a stored trajectory (``SweepResult.solution``); default None,
            no trajectory. Fixed steps of ``n_steps`` only.
        max_newton_iterations: the iteration cap of the implicit solve; default None (48), as in
            ``integrate``. Static.
        krylov: solve by Newton-Krylov; default None (False), as in ``integrate``. Static.
        solver: the implicit solve's options, a ``SolverOptions``; default None, as in
            ``integrate``. Static.
        throw: raise ``SolverError`` naming the configurations whose status is nonzero; default
            False. Outside ``jit`` only, as in ``integrate``.
        devices: the devices to shard the batch over (e.g. ``jax.devices()``); default None, one
            device. Results equal the unsharded run (up to how XLA compiles the per-device batch
            size). Several hosts: call ``jax.distributed.initialize()`` first and pass
            ``jax.devices()`` (all global devices).
        checkpoint: rematerialise blocks of elements in reverse mode; default False. A gradient
            then stores one carry per block (of ``save_every`` elements, or of the divisor of
            ``n_steps`` nearest its square root: choose an ``n_steps`` with one) instead of every
            element's residuals; with a ``controller``, as in ``integrate``. Static.
        progress: show a progress bar over the elements (all members advance together); default
            False. Static.
        error_estimate: how ``SweepResult.error_estimate`` is computed: True, ``"full"`` or
            False, as in ``integrate``; default True. Static.
        batch_size: run the configurations in chunks of this many, one chunk after another
            (``jax.lax.map``); default None, all at once (``vmap``). A chunk's run takes as many
            elements as its longest member (its gradient's adjoint sweep, on a CPU, each member's
            own): with a controller, ``batch_size=1`` makes each configuration's run and gradient
            cost its own steps. Static.

    Returns:
        ``SweepResult`` with a leading axis B on every field.
    """
    _span.check_span(n_steps, t0, t1, controller, sweep=True)
    sigma = _span.direction(t0, t1, float)
    if isinstance(sigma, int) and sigma == -1:
        raise ValueError("sweep runs forwards in time (t1 > t0); a run backwards is integrate's (under vmap, "
                         "with t1 per member).")
    batch_size = _check_batch_size(batch_size, devices, progress)
    if t1 is not None and save_every is not None:
        raise ValueError("save_every needs n_steps: a sweep to t1 saves no trajectory.")
    counts = None
    if t1 is not None and controller is None:
        hs = getattr(configs, "h", None)
        if _span.concrete(hs):
            hs = np.atleast_1d(np.asarray(hs, dtype=float))
            if not np.all(np.isfinite(hs) & (hs > 0)):
                raise ValueError("configs.h must be finite and > 0.")
        if max_steps is not None:  # reserved: a sweep to another t1 runs the same program
            _span.check_max_steps(max_steps)
            counts = max_steps
        elif _span.concrete(hs, t0, t1):
            counts = max(_span.fixed_step_count(t0, t1, h)[0] for h in hs)
        else:
            raise ValueError("A sweep to t1 with traced step sizes needs max_steps: the elements reserved per member.")
    configs = _checks.check_sweep(H, configs, n_steps or counts or 1, save_every, invariants, reference)
    _span.check_controller(controller, configs.method, configs.size)
    invariants = dict(invariants or {})
    reference = None if reference is None else tuple(jnp.asarray(r) for r in reference)
    dtype = configs.q0.dtype
    estimate = _span.check_estimate(error_estimate)
    if checkpoint == "reversible":
        raise ValueError("checkpoint='reversible' is integrate's (one fixed-step run); sweep takes True or False.")
    if controller is not None:
        if max_steps is not None:
            _span.check_max_steps(max_steps)
        controller = jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x, dtype), (configs.size,)), controller)
    options = solver_options(configs.method, max_newton_iterations, krylov, solver)
    # the explicit form (``_explicit``) where H's structure and the members' method have one
    configs = dataclasses.replace(configs, method=sweep_form(configs.method, H, configs.q0, configs.p0, configs.args,
                                                             options.solver))
    inputs = (configs, reference) if controller is None else (configs, reference, controller)
    if devices is not None:
        inputs = _shard(inputs, devices)
    span = (jnp.asarray(t0, dtype), None if t1 is None else jnp.asarray(t1, dtype))
    if controller is None:
        result = _run(H, tuple(invariants.items()), n_steps or counts, save_every, options, checkpoint,
                      bool(progress), estimate, batch_size, *inputs[:2], *span)
    else:
        result = _run_adaptive(H, tuple(invariants.items()), max_steps or DEFAULT_MAX_STEPS, options, estimate,
                               checkpoint, batch_size, inputs[0], inputs[1], *span, inputs[2])
    if devices is not None:
        result = jax.tree.map(lambda x: x[: configs.size], result)
    if not isinstance(sigma, int):  # a traced t1 < t0 is bad input (a concrete one raises above)
        status = jnp.where(sigma < 0, Status.INVALID_INPUT, result.status).astype(result.status.dtype)
        result = dataclasses.replace(result, status=status, q=nan_if_failed(result.q, status),
                                     p=nan_if_failed(result.p, status))
    if throw:
        throw_if_failed(result.status)
    return result
