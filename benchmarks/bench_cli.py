"""The command line tool's compilation cache: a command's compile and wall time, cold and again.

    python benchmarks/bench_cli.py

Runs ``python -m galerkin_jax run`` (Kepler, cG(3) + Gauss 3, 1000 steps) and ``sweep``
(cg2:gauss2 and mm over two step sizes) in fresh processes with a fresh cache folder:
without the cache, with it cold, the same command again, and with other step sizes (which
are arguments of the compiled programs, so the cache serves them). Compile time is the
tool's own figure (trace, lower and compile, or load); wall time is the whole process
(imports, plots and files included). Writes results/cli.json.
"""

import os
import re
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from _common import write  # noqa: E402
from galerkin_jax import cli  # noqa: E402

COMMANDS = {
    "run": (["run"], ["run", "--step-size", "0.04"]),
    "sweep": (["sweep", "--methods", "cg2:gauss2,mm", "--step-sizes", "0.1,0.05"],
              ["sweep", "--methods", "cg2:gauss2,mm", "--step-sizes", "0.2,0.02"]),
}


def command(argv, cache, out):
    env = dict(os.environ, **{cli.CACHE_VARIABLE: cache})
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "galerkin_jax", *argv, "--out", out], env=env, capture_output=True,
                          text=True, check=True)
    wall = time.perf_counter() - t0
    return {"compile_s": float(re.search(r"compile ([\d.]+) s", done.stdout).group(1)), "wall_s": wall}


def main():
    results = {}
    with tempfile.TemporaryDirectory() as folder:
        for name, (argv, other) in COMMANDS.items():
            cache, out = os.path.join(folder, f"cache_{name}"), os.path.join(folder, "out")
            rows = {"no cache": command(argv, "", out), "cold cache": command(argv, cache, out),
                    "same command again": command(argv, cache, out), "other step sizes": command(other, cache, out)}
            rows["cache entries"] = len(os.listdir(cache))
            results[name] = rows
            for label, row in rows.items():
                if isinstance(row, dict):
                    print(f"{name:6s} {label:20s} compile {row['compile_s']:5.2f} s   wall {row['wall_s']:5.2f} s")
    write("cli", results)


if __name__ == "__main__":
    main()
