"""The progress bar is ticked from inside the compiled loop, once per element count, under vmap too."""

import jax
import jax.numpy as jnp

import galerkin_jax as gj
from galerkin_jax import _progress
import helpers

TICKS = []  # one list: a trace reused under vmap keeps the callback it was traced with


def recorded_ticks(run):
    TICKS.clear()
    jax.block_until_ready(run())
    jax.effects_barrier()  # debug callbacks may run after the outputs are ready
    return list(TICKS)


def test_ticks_count_elements_once_per_run_under_vmap_and_in_a_sweep(monkeypatch):
    monkeypatch.setattr(_progress, "_update", lambda done, total: TICKS.append((int(done), int(total))))
    H, q0, p0 = helpers.kepler(0.5)
    H = lambda q, p, H=H: H(q, p)  # a new function: a new trace that calls the patched _update
    method = gj.CG(1, gj.midpoint())
    single = recorded_ticks(lambda: gj.integrate(H, q0, p0, method=method, h=0.01, n_steps=500,
                                                              progress=True).q)
    vmapped = recorded_ticks(lambda: jax.vmap(
        lambda h: gj.integrate(H, q0, p0, method=method, h=h, n_steps=500, progress=True).q)(jnp.array([0.01, 0.02, 0.03])))
    swept = recorded_ticks(lambda: gj.sweep(H, gj.grid(method=method, h=[0.01, 0.02], state=(q0, p0)),
                                                         n_steps=500, progress=True).q)
    for ticks in (single, vmapped, swept):
        done = sorted(d for d, _ in ticks)
        # every 500 // 50 = 10 elements, and the last: 50 ticks, counting elements, not members
        assert done == list(range(10, 501, 10))
        assert {total for _, total in ticks} == {500}
