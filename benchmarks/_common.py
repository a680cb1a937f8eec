"""Timing and result-writing helpers shared by the benchmarks."""

import contextlib
import datetime
import json
import pathlib
import platform
import subprocess
import sys
import time
import timeit

import jax
import jax.numpy as jnp
import numpy as np

RESULTS = pathlib.Path(__file__).parent / "results"


def timed(fn, *args, repeat=5):
    """(compile_s, run_s): ahead-of-time compilation, then the best of ``repeat`` runs."""
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(*args))
    run_s = min(timeit.repeat(lambda: jax.block_until_ready(compiled(*args)), number=1, repeat=repeat))
    return compile_s, run_s


def _commit():
    """The git commit of the tree the benchmark ran on ("+" where it had uncommitted changes)."""
    here = pathlib.Path(__file__).parent
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=here, capture_output=True, text=True,
                              timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                               capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return (head + ("+" if dirty else "")) or None


def machine():
    with open("/proc/loadavg") as f:
        load = f.read().split()[:3]
    return {
        "command": " ".join(["python"] + sys.argv),
        "commit": _commit(),
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "processor": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "devices": [str(d) for d in jax.devices()],
        "load_average": load,
    }


def write(name, results):
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps({"machine": machine(), **results}, indent=2))
    print(f"wrote {path}")


def energy_quarters(t, dH, T):
    """The largest |dH| over the nodes (times t) of a run to T, in its first and in its last
    quarter, and their ratio (a drift shows as a ratio well above 1)."""
    first, last = (float(np.max(dH[(t >= a * T / 4) & (t <= (a + 1) * T / 4)])) for a in (0, 3))
    return dict(max_energy_error=float(np.max(dH)), first_quarter=first, last_quarter=last,
                last_over_first=last / first)


def compiled(fn, *args):
    """(compile_s, call): ``fn`` jitted and compiled ahead of time for ``args``."""
    t0 = time.perf_counter()
    call = jax.jit(fn).lower(*args).compile()
    return time.perf_counter() - t0, call


def best_time(call, *args, repeat=3, min_s=0.1, budget_s=3.0):
    """Best wall time of ``call(*args)``, already warmed up: ``repeat`` runs, more until they
    total ``min_s`` (short runs are noisy), fewer once ``budget_s`` has passed (long runs are
    not); at least one run, at most 1000."""
    times, start = [], time.perf_counter()
    while len(times) < 1000:
        t0 = time.perf_counter()
        jax.block_until_ready(call(*args))
        times.append(time.perf_counter() - t0)
        elapsed = time.perf_counter() - start
        if elapsed > budget_s or (len(times) >= repeat and elapsed > min_s):
            break
    return min(times)


def chained_us(step, carry, calls=200, repeat=5):
    """Microseconds per call of ``step`` (carry -> carry of the same shapes), from ``calls``
    chained calls in one compiled loop (one program's launch spread over them), warmed up, the
    best of ``repeat`` (``best_time``)."""
    _, call = compiled(lambda c: jax.lax.fori_loop(0, calls, lambda _, c: step(c), c), carry)
    jax.block_until_ready(call(carry))
    return 1e6 * best_time(call, carry, repeat=repeat) / calls


@contextlib.contextmanager
def figure(path, ncols=1, size=(6, 4.5)):
    """``with figure(path) as axes``: a headless Matplotlib figure of ``ncols`` Axes side by
    side (each ``size`` inches), laid out and saved to ``path`` (dpi 100) on exit."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, ncols, figsize=(size[0] * ncols, size[1]), squeeze=False)
    yield axes[0]
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def element_polynomials(method, H, z, h):
    """Each element's own polynomial ``W`` (m, 2d), solved again from its start node ``z[n]``
    over ``h[n]`` (H bound to its args): dense output holds it refined (``_output.refined``)."""
    from galerkin_jax._march import solve_element, solver_options

    options = solver_options(method)

    def one(z0, h):
        q, p = jnp.split(z0, 2)
        return method.polynomial(H, q, p, solve_element(method, H, q, p, h, None, options)[2], h)

    return jax.jit(jax.vmap(one))(jnp.asarray(z), jnp.broadcast_to(jnp.asarray(h), (len(z),)))
