"""One entry point for the benchmarks.

    python -m benchmarks                  # what it can run, one line each
    python -m benchmarks NAME [OPTIONS]   # run benchmarks/bench_NAME.py with its options

Each writes ``benchmarks/results/<name>.json`` with the command, machine, commit and date
(``_common.write``).
"""

import ast
import pathlib
import runpy
import sys

HERE = pathlib.Path(__file__).parent


def available():
    """``{name: the first paragraph of its docstring}`` of every ``bench_*.py``."""
    first = lambda path: (ast.get_docstring(ast.parse(path.read_text())) or "").split("\n\n")[0]
    return {path.stem[len("bench_"):]: " ".join(first(path).split()) for path in sorted(HERE.glob("bench_*.py"))}


def main(argv):
    names = available()
    if not argv or argv[0] in ("-h", "--help", "list"):
        width = max(map(len, names))
        print("python -m benchmarks NAME [OPTIONS]; NAME is one of:\n")
        for name, line in names.items():
            print(f"  {name:{width}s}  {line}")
        return 0
    name, options = argv[0], argv[1:]
    if name not in names:
        print(f"no benchmark named {name!r}; `python -m benchmarks` lists them.", file=sys.stderr)
        return 2
    path = HERE / f"bench_{name}.py"
    sys.argv = [str(path), *options]
    sys.path.insert(0, str(HERE))
    runpy.run_path(str(path), run_name="__main__")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
