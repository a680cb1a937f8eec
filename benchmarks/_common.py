"""What the benchmarks share: one BLAS thread, timing (compile apart from run), the record of
the machine, and one writer of results (JSON, and a markdown table where there is one)."""

import os

for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS", "VECLIB_MAXIMUM_THREADS"):
    os.environ.setdefault(_var, "1")  # before NumPy and JAX load a BLAS: SciPy's peers and LAPACK on one thread

import contextlib  # noqa: E402
import datetime  # noqa: E402
import importlib.metadata  # noqa: E402
import json  # noqa: E402
import pathlib  # noqa: E402
import platform  # noqa: E402
import shlex  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)  # the benchmarks' processes only, never the library

# where results go: benchmarks/results, or $BENCHMARKS_RESULTS (the smoke tests write elsewhere)
RESULTS = pathlib.Path(os.environ.get("BENCHMARKS_RESULTS") or pathlib.Path(__file__).parent / "results")


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


def timed(fn, *args, repeat=5):
    """(compile_s, run_s): ``compiled``, one warm-up call, then ``best_time``."""
    compile_s, call = compiled(fn, *args)
    jax.block_until_ready(call(*args))
    return compile_s, best_time(call, *args, repeat=repeat)


def _commit():
    """The git commit of the tree the benchmark ran on ("+" where it had uncommitted changes)."""
    here = pathlib.Path(__file__).parent
    try:
        git = lambda *a: subprocess.run(["git", *a], cwd=here, capture_output=True, text=True, timeout=10).stdout.strip()
        head, dirty = git("rev-parse", "--short", "HEAD"), git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return None
    return (head + ("+" if dirty else "")) or None


def _version(package):
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return None


def machine():
    """The record every result file carries: command, commit, date, the machine and the versions."""
    with open("/proc/loadavg") as f:
        load = f.read().split()[:3]
    return {
        "command": "python " + shlex.join(sys.orig_argv[1:]),  # as typed: ``-m benchmarks NAME`` or the script
        "commit": _commit(),
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "processor": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "versions": {p: _version(p) for p in ("numpy", "scipy", "diffrax", "optimistix", "equinox")},
        "jax_enable_x64": bool(jax.config.jax_enable_x64),
        "devices": [str(d) for d in jax.devices()],
        "load_average": load,
    }


def write(name, results, markdown=None):
    """``results/<name>.json``: the machine's record (``machine``) and ``results``; with
    ``markdown`` also ``results/<name>.md`` (the command and date first) and the table in the JSON."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    record = machine()
    if markdown is not None:
        results = dict(results, table=markdown)
        (RESULTS / f"{name}.md").write_text(f"`{record['command']}` at {record['commit']}, {record['date']}\n\n"
                                            + markdown)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps({"machine": record, **results}, indent=2))
    print(f"wrote {path}")


def show(label, row, *keys):
    """One progress line: ``label`` and ``row``'s ``keys`` (all, without them; numbers to three digits)."""
    text = ", ".join(f"{k} {row[k]:.3g}" if isinstance(row[k], float) else f"{k} {row[k]}" for k in keys or row
                     if row.get(k) is not None and not isinstance(row[k], (dict, list)))
    print(f"  {label}: {text}", flush=True)


def markdown_table(header, rows):
    """A markdown table of ``header`` (column names) and ``rows`` (lists of cells)."""
    return "\n".join("| " + " | ".join(map(str, row)) + " |" for row in [header, ["---"] * len(header), *rows])


def energy_quarters(t, dH, T):
    """The largest |dH| over the nodes (times t) of a run to T, in its first and in its last
    quarter, and their ratio (a drift shows as a ratio well above 1)."""
    first, last = (float(np.max(dH[(t >= a * T / 4) & (t <= (a + 1) * T / 4)])) for a in (0, 3))
    return dict(max_energy_error=float(np.max(dH)), first_quarter=first, last_quarter=last,
                last_over_first=last / first)


@contextlib.contextmanager
def figure(path, ncols=1, nrows=1, size=(6, 4.5), dpi=100):
    """``with figure(path) as axes``: a headless Matplotlib figure of ``nrows`` x ``ncols`` Axes
    (each ``size`` inches; one row: a flat array), laid out and saved to ``path`` on exit."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pathlib.Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(nrows, ncols, figsize=(size[0] * ncols, size[1] * nrows), squeeze=False)
    yield axes[0] if nrows == 1 else axes
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
