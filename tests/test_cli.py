"""The ``galerkin-jax`` command line tool: end to end in subprocesses (the default run, --help,
a bad option) and in-process through ``cli.main`` for the rest."""

import os
import subprocess
import sys

import jax
import numpy as np
import pytest

import galerkin_jax as gj
from galerkin_jax import _cli_specs as specs
from galerkin_jax import _cli_sweep as sweeps
from galerkin_jax import cli, reproduce

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

USER_SCENE = '''
import jax.numpy as jnp
description = "anharmonic central force with a stiffness parameter"
def H(q, p, args):
    return 0.5 * p @ p + 0.5 * args["k"] * (q @ q) + 0.25 * (q @ q) ** 2
q0, p0 = [1.0, 0.0], [0.0, 1.0]
args = {"k": 2.0}
h, n_steps = 0.05, 40
invariants = {"L": lambda q, p: q[0] * p[1] - q[1] * p[0]}
'''

# q' = dH/dp = q^2 + 1 from q = 1: the element equations of h = 1 have no real solution
NO_SOLUTION_SCENE = '''
import jax.numpy as jnp
H = lambda q, p: jnp.sum(p * (q ** 2 + 1))
q0, p0, h, n_steps = [1.0], [0.0], 1.0, 4
'''


# a stiff chain of 50 masses (cG(3): 300 unknowns, h omega = 10): Newton-Krylov only
STIFF_CHAIN_SCENE = '''
import jax.numpy as jnp
import numpy as np
def H(q, p):
    strain = jnp.diff(jnp.concatenate([jnp.zeros(1, q.dtype), q, jnp.zeros(1, q.dtype)]))
    return 0.5 * p @ p + 50.0 * strain @ strain
q0, p0 = np.sin(np.arange(1, 51) / 8.0), np.zeros(50)
h, n_steps = 0.5, 4
'''


def galerkin_jax(*argv, cwd, cache=""):
    """``python -m galerkin_jax ARGV`` in ``cwd``, its compilation cache in ``cache`` (none
    by default: the suite writes nothing to the user's cache); returns the CompletedProcess."""
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""),
               **{cli.CACHE_VARIABLE: cache})
    return subprocess.run([sys.executable, "-m", *argv], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=300)


def write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def test_default_run_writes_trajectory_plots_and_summary(tmp_path):
    done = galerkin_jax("galerkin_jax", "run", "--out", "out", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    stem = tmp_path / "out" / "kepler_cG3-gauss3"
    for suffix in (".npz", "_energy.png", "_orbit.png"):
        assert os.path.getsize(f"{stem}{suffix}") > 1000, suffix
    data = np.load(f"{stem}.npz")
    assert data["q"].shape == (1001, 2) and int(data["status"]) == 0
    # Gauss collocation on Kepler e = 0.6, h = 0.05: measured 3.5e-8, bounded (symplectic); 3x margin
    energy_error = np.max(np.abs(data["energy"] / data["energy"][0] - 1))
    assert 1e-9 < energy_error < 1e-7
    assert np.max(np.abs(data["invariant_L"] - data["invariant_L"][0])) < 1e-13  # quadratic invariant: round-off
    out = done.stdout
    assert "cG(3): continuous Galerkin, degree 3 [GBS, eq. (16)], 3-point Gauss-Legendre rule" in out
    assert "compile" in out and "Newton" in out and "kepler_cG3-gauss3.npz (" in out
    assert out.strip().splitlines()[-1].startswith(f"Look at {os.path.join('out', 'kepler_cG3-gauss3_energy.png')}")


def test_a_run_again_with_another_step_size_loads_its_programs_from_the_cache(tmp_path):
    cache = str(tmp_path / "cache")
    first = galerkin_jax("galerkin_jax", "run", "--steps", "200", "--out", "out", cwd=tmp_path, cache=cache)
    assert first.returncode == 0, first.stderr
    entries = sorted(os.listdir(cache))
    assert len(entries) >= 2  # the integration and the plots' programs (24 measured for the default run)
    again = galerkin_jax("galerkin_jax", "run", "--steps", "200", "--step-size", "0.04", "--out", "out", cwd=tmp_path,
                         cache=cache)
    assert again.returncode == 0, again.stderr
    assert sorted(os.listdir(cache)) == entries  # h is an argument of the programs: nothing new to compile
    energy = lambda done: next(line for line in done.stdout.splitlines() if line.startswith("energy"))
    assert energy(again) != energy(first)  # ... and it did run with the new h


def test_the_cache_defaults_to_the_user_cache_folder_and_an_empty_variable_turns_it_off():
    assert cli.compile_cache_folder({"XDG_CACHE_HOME": "/x"}) == os.path.join("/x", "galerkin_jax", "xla")
    assert cli.compile_cache_folder({"HOME": "/h"}).endswith(os.path.join(".cache", "galerkin_jax", "xla"))
    assert cli.compile_cache_folder({cli.CACHE_VARIABLE: "/c", "XDG_CACHE_HOME": "/x"}) == "/c"
    assert cli.compile_cache_folder({cli.CACHE_VARIABLE: ""}) is None


def test_help_names_the_tool_and_a_bad_option_exits_2(tmp_path):
    help_text = galerkin_jax("galerkin_jax", "--help", cwd=tmp_path)
    assert help_text.returncode == 0 and help_text.stdout.startswith("usage: galerkin-jax")
    assert ":math:" not in help_text.stdout and "``" not in help_text.stdout  # plain text, no reST
    bad = galerkin_jax("galerkin_jax.demo", "--step-size", "-1", cwd=tmp_path)  # demo = `run`
    assert bad.returncode == 2
    assert "usage: galerkin-jax run" in bad.stderr and "--step-size: expected a positive number" in bad.stderr
    assert "Traceback" not in bad.stderr


class _Table:
    def text(self):  # the interface of reproduce.Table51 that the command uses
        return "         Hooke: exact\ncG(1) H  C\ndG(1) L  D\n"


def test_reproduce_prints_table51_and_the_files(tmp_path, capsys, monkeypatch):
    # reproduce(quick=True) itself (~75 s of CPU) is run by test_reproduce.py; here only the command
    def fake(folder, *, quick):
        assert quick is True
        path = os.path.join(folder, "table51.md")
        os.makedirs(folder)
        with open(path, "w") as f:
            f.write("# [GBS] Table 5.1, measured\n")
        return {"folder": str(folder), "files": {"table51": path}, "table51": _Table(), "numbers": {}}

    monkeypatch.setattr(reproduce, "reproduce", fake)
    assert cli.main(["reproduce", "--quick", "--out", str(tmp_path / "repro")]) == 0
    printed = capsys.readouterr().out
    assert "Table 5.1 of [GBS]" in printed and "cG(1) H  C" in printed
    assert f"{tmp_path / 'repro' / 'table51.md'} (28 B)" in printed  # the path and its size


def test_user_scene_file_with_args_and_invariants(tmp_path, capsys):
    scene = write(tmp_path, "anharmonic.py", USER_SCENE)
    out = str(tmp_path / "out")
    assert cli.main(["run", scene, "--method", "vi2:gauss2", "--format", "csv", "--out", out]) == 0
    printed = capsys.readouterr().out
    assert "anharmonic central force" in printed and "GalerkinVI(2)" in printed
    with open(os.path.join(out, "anharmonic_GalerkinVI2-gauss2.csv")) as f:
        lines = [line for line in f if not line.startswith("#")]
    assert lines[0].strip() == "t,q_0,q_1,p_0,p_1,energy,invariant_L"
    table = np.loadtxt(lines[1:], delimiter=",")
    assert table.shape == (41, 7)
    # a symplectic collocation method keeps the quadratic invariant L to round-off (measured 2e-16)
    assert np.max(np.abs(table[:, 6] - table[0, 6])) < 1e-14
    # H(q, p, args) with k = 2: H0 = 1/2 + 1 + 1/4
    assert table[0, 5] == pytest.approx(1.75, abs=1e-15)
    assert jax.config.read("jax_enable_x64")  # main restores the caller's setting


def test_failed_solve_exits_3_with_the_status_message(tmp_path, capsys):
    scene = write(tmp_path, "blowup.py", NO_SOLUTION_SCENE)
    assert cli.main(["run", scene, "--out", str(tmp_path / "out")]) == cli.EXIT_FAILED_SOLVE
    captured = capsys.readouterr()
    assert "the run failed between t = 0 and t = 1" in captured.out
    assert captured.err.startswith("galerkin-jax: error: the solve failed (status 1)")
    assert gj.status_message(gj.Status.NEWTON_MAX_ITERATIONS) in captured.err


def test_krylov_solves_a_stiff_chain_that_fails_without_it(tmp_path, capsys):
    scene = write(tmp_path, "chain.py", STIFF_CHAIN_SCENE)
    out = ["--out", str(tmp_path / "out"), "--no-progress"]
    assert cli.main(["run", scene, *out]) == cli.EXIT_FAILED_SOLVE
    assert "krylov=True" in capsys.readouterr().err
    assert cli.main(["run", scene, "--krylov", *out]) == 0


@pytest.mark.parametrize(
    "argv, message",
    [
        (["run", "saturn"], "unknown scene 'saturn'. The built-in scenes are oscillator, quartic, kepler"),
        (["run", "{noh}"], "it does not define H."),
        (["run", "{raises}"], "raised ZeroDivisionError: division by zero"),
        (["run", "--method", "cg2:simpson"], "unknown rule 'simpson'"),
        (["run", "kepler", "--method", "lvi"], "LagrangianVI integrates L(q, qdot)"),
        (["run", "kepler", "--steps", "10", "--save-every", "3"], "--steps (10) must be a multiple of --save-every"),
        (["sweep", "kepler", "--methods", "mm:gauss2"], "ModifiedMidpoint takes no degree and no quadrature rule"),
    ],
)
def test_bad_input_is_a_message_with_exit_1(tmp_path, capsys, argv, message):
    files = {"noh": write(tmp_path, "noh.py", "q0 = [1.0]\np0 = [0.0]\n"),
             "raises": write(tmp_path, "raises.py", "q0 = [1.0]\nx = 1 / 0\n")}
    assert cli.main([a.format(**files) for a in argv]) == 1
    captured = capsys.readouterr()
    assert captured.err.startswith("galerkin-jax: error: ") and message in captured.err


def test_sweep_table_in_one_batch_and_cg1_conserves_quadratic_H(tmp_path, capsys):
    out = str(tmp_path / "out")
    argv = ["sweep", "oscillator", "--methods", "cg1:gauss2,cg1:trapezoid", "--step-sizes", "1,0.5", "--steps", "20"]
    assert cli.main(argv + ["--out", out]) == 0
    printed = capsys.readouterr().out
    assert "4 configurations of 20 steps each, in 1 batched sweep(s)" in printed
    with open(os.path.join(out, "oscillator_sweep.csv")) as f:
        header, *rows = [line.strip().split(",") for line in f]
    assert header == ["method", "h", "status", "energy error", "L error", "final error", "error estimate",
                      "Newton per element", "max Newton"]
    energy, final = (np.array([float(r[header.index(c)]) for r in rows]) for c in ("energy error", "final error"))
    assert [r[0] for r in rows] == ["cG(1) Gauss-Legendre 2"] * 2 + ["cG(1) trapezoid"] * 2
    assert np.all(energy < 1e-14)  # [GBS, Thm. 3.1], quadratic H: measured <= 4.4e-16
    # second order at a fixed step count: t = 20 h, so the final error scales like h^3 (measured 7.3)
    assert 6 < final[0] / final[1] < 10 and 6 < final[2] / final[3] < 10
    for name in ("oscillator_sweep.md", "oscillator_sweep_energy_map.png", "oscillator_sweep_error_vs_h.png"):
        assert os.path.getsize(os.path.join(out, name)) > 100


def test_method_specs_and_sweep_groups():
    spec = specs.complete(specs.parse_spec("dg1:lobatto3"))
    assert specs.describe(spec) == "dG(1): discontinuous Galerkin, degree 1 [GBS, eq. (19)], 3-point Gauss-Lobatto rule"
    assert specs.complete(specs.parse_spec("cg")) == specs.MethodSpec("cg", 3, "gauss", 3)  # Gauss collocation
    assert specs.complete(specs.parse_spec("DiscreteGradient")) == specs.MethodSpec("dgrad")
    groups = sweeps.groups(specs.parse_specs("cg2:gauss2,mm,cg2:lobatto3,dg1,cg1:midpoint"))
    assert [[specs.tag(s) for s in g] for g in groups] == [["cG2-gauss2", "cG2-lobatto3"], ["ModifiedMidpoint"],
                                                           ["dG1-gauss2"], ["cG1-midpoint"]]
