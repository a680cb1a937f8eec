"""The ``galerkin-jax`` command line tool: end to end in subprocesses (the default run, --help,
a bad option) and in-process through ``cli.main`` for the rest."""

import os
import subprocess
import sys
from types import SimpleNamespace

import jax
import numpy as np
import pytest

import galerkin_jax as gj
from galerkin_jax import _cli_output as output
from galerkin_jax import _cli_specs as specs
from galerkin_jax import _cli_summary as summary
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


# the figure-eight of three equal masses (Chenciner and Montgomery), positions of shape (3, 2):
# H and the invariant index the bodies' axis, so that a flat state would fail
THREE_BODY_SCENE = '''
import jax.numpy as jnp
import numpy as np
description = "figure-eight three-body choreography"
def H(q, p):
    r = q[:, None, :] - q[None, :, :]
    distance = jnp.sqrt(jnp.sum(r ** 2, axis=-1) + jnp.eye(3))
    return 0.5 * jnp.sum(p ** 2) - 0.5 * jnp.sum((1.0 - jnp.eye(3)) / distance)
x1 = np.array([0.97000436, -0.24308753])
v3 = np.array([-0.93240737, -0.86473146])
q0 = np.stack([x1, -x1, np.zeros(2)])
p0 = np.stack([-v3 / 2, -v3 / 2, v3])
h, n_steps = 0.02, 40
invariants = {"P": lambda q, p: jnp.sum(p, axis=0)}
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


def test_default_run_writes_trajectory_plots_and_summary_and_a_run_again_with_another_h_loads_the_cache(tmp_path):
    cache = str(tmp_path / "cache")
    done = galerkin_jax("galerkin_jax", "run", "--out", "out", cwd=tmp_path, cache=cache)
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
    assert "1000 steps of h = 0.05" in out and "per step" in out and "element" not in out
    line = lambda key: next(x for x in out.splitlines() if x.startswith(key))
    global_error = float(line("global   error at t = 50 against the exact solution: ").split(": ")[1].split()[0])
    local = float(line("local    estimated error of one step, the largest of the run: ").split(": ")[1].split()[0])
    # the global error accumulates over 1000 steps (measured 9.5e-6) far above one step's (1.2e-8)
    assert global_error == pytest.approx(np.abs(np.concatenate([data["q"][-1], data["p"][-1]]) - np.concatenate(
        specs.load_scene("kepler").exact(50.0))).max(), rel=1e-2)
    assert 100 * local < global_error
    last = out.strip().splitlines()[-1]
    assert last.startswith(f"Look at {os.path.join('out', 'kepler_cG3-gauss3_energy.png')}: the energy error is ")
    assert "no drift. As expected: " in last and "symplectic" in last  # the numbers agree with the method
    # the same run again with another step size loads its programs from the cache
    entries = sorted(os.listdir(cache))
    assert len(entries) >= 2  # the integration and the plots' programs (24 measured for the default run)
    again = galerkin_jax("galerkin_jax", "run", "--step-size", "0.04", "--out", "out", cwd=tmp_path, cache=cache)
    assert again.returncode == 0, again.stderr
    assert sorted(os.listdir(cache)) == entries  # h is an argument of the programs: nothing new to compile
    energy = lambda done: next(line for line in done.stdout.splitlines() if line.startswith("energy"))
    assert energy(again) != energy(done)  # ... and it did run with the new h


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


def test_failed_solve_exits_3_with_the_status_message_and_no_krylov_advice_for_2_unknowns(tmp_path, capsys):
    scene = write(tmp_path, "blowup.py", NO_SOLUTION_SCENE)
    assert cli.main(["run", scene, "--out", str(tmp_path / "out")]) == cli.EXIT_FAILED_SOLVE
    captured = capsys.readouterr()
    assert "the run failed between t = 0 and t = 1" in captured.out
    assert captured.err.startswith("galerkin-jax: error: the solve failed (status 1, NEWTON_MAX_ITERATIONS)")
    assert captured.err.count("\n") == 1 and captured.err.rstrip().endswith("Try a smaller --step-size than 1.")
    # cG(3) of d = 1: 6 unknowns per element, far below the dense limit: Newton-Krylov cannot help
    assert "rylov" not in captured.err and "rylov" not in captured.out
    first = gj.status_message(gj.Status.NEWTON_MAX_ITERATIONS).split(". ")[0]
    assert first in captured.err


def test_krylov_solves_a_stiff_chain_that_fails_without_it(tmp_path, capsys):
    scene = write(tmp_path, "chain.py", STIFF_CHAIN_SCENE)
    out = ["--out", str(tmp_path / "out"), "--no-progress"]
    assert cli.main(["run", scene, *out]) == cli.EXIT_FAILED_SOLVE
    captured = capsys.readouterr()
    err = captured.err
    assert "--krylov" in err and "krylov=True" not in err  # 300 unknowns: the advice applies, in the tool's terms
    assert "--krylov" in captured.out  # the summary's status line too
    assert cli.main(["run", scene, "--krylov", *out]) == 0


@pytest.mark.parametrize(
    "argv, message",
    [
        (["run", "saturn"], "unknown scene 'saturn'. The built-in scenes are oscillator, quartic, kepler"),
        (["run", "{noh}"], "it does not define H."),
        (["run", "{raises}"], "raised ZeroDivisionError: division by zero"),
        (["run", "kepler", "--method", "lvi"], "LagrangianVI integrates L(q, qdot)"),
    ],
)
def test_bad_input_is_a_message_with_exit_1(tmp_path, capsys, argv, message):
    files = {"noh": write(tmp_path, "noh.py", "q0 = [1.0]\np0 = [0.0]\n"),
             "raises": write(tmp_path, "raises.py", "q0 = [1.0]\nx = 1 / 0\n")}
    assert cli.main([a.format(**files) for a in argv]) == 1
    captured = capsys.readouterr()
    assert captured.err.startswith("galerkin-jax: error: ") and message in captured.err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["run", "--method", "cg3:gaus3"], "--method: unknown rule 'gaus' (did you mean 'gauss'?)"),
        (["run", "--method", "cg2:simpson"], "--method: unknown rule 'simpson'"),
        (["run", "--method", "cgg2"], "--method: unknown method 'cgg' (did you mean 'cg'?)"),
        (["run", "--method", "dg", "--rule", "lobatto", "--points", "1"], "Gauss-Lobatto rule has at least 2 point(s)"),
        (["run", "kepler", "--steps", "10", "--save-every", "3"], "--steps (10) must be a multiple of --save-every"),
        (["run", "kepler", "--plot", "q0,q2"], "--plot: q2 does not exist; the scene has q0 .. q1 and p0 .. p1."),
        (["sweep", "kepler", "--methods", "mm:gauss2"], "--methods: ModifiedMidpoint takes no degree and no quadrature"),
        (["sweep", "kepler", "--methods", "cg2,cg3:gaus3"], "--methods: unknown rule 'gaus'"),
        (["run", "--method", "kahan_li7@verlet"], "--method: unknown composition scheme 'kahan_li7' (did you mean"),
        (["run", "--method", "split:blanes_moan5"], "--method: unknown splitting scheme 'blanes_moan5'"),
        (["run", "--method", "yoshida4@verlet", "--degree", "2"], "takes no --degree, --rule or --points"),
    ],
)
def test_a_bad_option_is_one_line_with_exit_2_and_writes_nothing(tmp_path, capsys, argv, message):
    """The README's promise: 2 for a bad option, a method spec included."""
    assert cli.main(argv + ["--out", str(tmp_path / "out")]) == 2
    captured = capsys.readouterr()
    assert captured.err.startswith("galerkin-jax: error: ") and message in captured.err
    assert captured.err.count("\n") == 1 and captured.out == ""
    assert not (tmp_path / "out").exists()


SCENE_HEAD = "import jax.numpy as jnp\nH = lambda q, p: 0.5 * p @ p - 1 / jnp.sqrt(q @ q)\nn_steps = 20\n"


@pytest.mark.parametrize(
    "values, message",
    [
        ("q0, p0 = [1.0, float('nan')], [0.0, 1.0]",
         "q0 must be finite, got 1 of 2 entries not finite, the first nan at index (1,)."),
        ("q0, p0 = [1.0, 0.0], [0.0, float('inf')]", "p0 must be finite"),
        ("q0, p0, h = [1.0, 0.0], [0.0, 1.0], -0.1", "h must be finite and > 0, got -0.1."),
        ("q0, p0, h = [1.0, 0.0], [0.0, 1.0], float('nan')", "h must be finite and > 0, got nan."),
        ("q0, p0, h = [1.0, 0.0], [0.0, 1.0], 'small'", "h must be a number, got 'small'."),
        ("q0, p0, n_steps = [1.0, 0.0], [0.0, 1.0], 0", "n_steps must be an integer >= 1, got 0."),
        ("q0, p0, n_steps = [1.0, 0.0], [0.0, 1.0], 10.5", "n_steps must be an integer >= 1, got 10.5."),
        ("q0, p0 = [1.0, 0.0], [0.0, 1.0, 0.0]", "q0 and p0 must have the same shape, got (2,) and (3,)."),
        ("q0, p0, center = [1.0, 0.0], [0.0, 1.0], [0.0, 0.0, 0.0]", "center must be a point of shape (2,)"),
    ],
)
@pytest.mark.parametrize("command", ["run", "sweep"])
def test_bad_scene_values_are_one_line_with_exit_1_before_anything_is_written(tmp_path, capsys, values, message,
                                                                               command):
    scene = write(tmp_path, "bad.py", SCENE_HEAD + values + "\n")
    assert cli.main([command, scene, "--out", str(tmp_path / "out"), "--no-progress"]) == 1
    captured = capsys.readouterr()
    assert captured.err.startswith(f"galerkin-jax: error: scene file {scene!r}: ") and message in captured.err
    assert captured.err.count("\n") == 1 and "Traceback" not in captured.err
    assert captured.out == "" and not (tmp_path / "out").exists()  # no NPZ, no plot, no folder


def test_a_bad_scene_value_gives_no_traceback_from_the_script(tmp_path):
    write(tmp_path, "bad.py", SCENE_HEAD + "q0, p0, h = [1.0, 0.0], [0.0, 1.0], float('nan')\n")
    done = galerkin_jax("galerkin_jax", "run", "bad.py", "--out", "out", cwd=tmp_path)
    assert done.returncode == 1
    assert done.stderr == "galerkin-jax: error: scene file 'bad.py': h must be finite and > 0, got nan.\n"
    assert done.stdout == "" and not (tmp_path / "out").exists()


def test_sweep_table_in_one_batch_and_cg1_conserves_quadratic_H(tmp_path, capsys):
    out = str(tmp_path / "out")
    argv = ["sweep", "oscillator", "--methods", "cg1:gauss2,cg1:trapezoid", "--step-sizes", "1,0.5", "--steps", "20"]
    assert cli.main(argv + ["--out", out]) == 0
    printed = capsys.readouterr().out
    assert "4 configurations of 20 steps each, in 1 batched sweep(s)" in printed
    with open(os.path.join(out, "oscillator_sweep.csv")) as f:
        header, *rows = [line.strip().split(",") for line in f]
    assert header == ["method", "h", "status", "energy error", "L error", "final error", "error estimate",
                      "Newton per step", "max Newton"]
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


def test_composition_and_splitting_specs():
    comp = specs.parse_spec("kahan_li6@verlet")
    assert comp == specs.MethodSpec("comp", scheme="kahan_li6", inner=specs.MethodSpec("vi", 1, "trapezoid", 2))
    built = specs.build(comp)
    assert isinstance(built, gj.Composition) and built.scheme == "kahan_li6" and built.method.s == 1
    np.testing.assert_array_equal(built.method.quadrature.points, [0.0, 1.0])
    assert specs.tag(comp) == "kahan_li6-GalerkinVI1-trapezoid" and specs.short(comp) == "kahan_li6(GalerkinVI(1) trapezoid)"
    assert specs.build(specs.parse_spec("split:blanes_moan_rkn6")) == gj.Splitting("blanes_moan_rkn6")
    assert specs.build(specs.parse_spec("split")) == gj.Splitting("blanes_moan4")
    assert specs.describe(specs.parse_spec("split:blanes_moan_rkn4")).endswith(
        "order 4 where T is quadratic in p [Blanes & Moan 2002]")
    groups = sweeps.groups(specs.parse_specs("split:leapfrog,split:blanes_moan4,yoshida4@verlet,split:leapfrog"))
    assert [[specs.tag(s) for s in g] for g in groups] == [["split-leapfrog", "split-leapfrog"], ["split-blanes_moan4"],
                                                           ["yoshida4-GalerkinVI1-trapezoid"]]


@pytest.mark.parametrize("method, bound", [("kahan_li6@verlet", 1e-6), ("split:blanes_moan_rkn6", 1e-9)])
def test_run_takes_compositions_and_splittings(tmp_path, capsys, method, bound):
    """The Kepler scene (separable, e = 0.6): explicit elements; 1000 steps of h = 0.05 of these
    order-6 methods keep the energy to 6.2e-7 and 6.3e-10 (measured; the plain composition's
    large substeps near the pericentre cost it three digits)."""
    out = tmp_path / "out"
    assert cli.main(["run", "kepler", "--method", method, "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "symplectic" in printed
    data = np.load(next(out.glob("*.npz")))
    H = lambda q, p: 0.5 * p @ p - 1 / np.sqrt(q @ q)
    energies = np.array([H(q, p) for q, p in zip(data["q"], data["p"])])
    assert np.max(np.abs(energies - energies[0])) / abs(energies[0]) < bound
    assert "Newton   0 iterations" in printed


def test_run_refuses_a_splitting_of_a_general_h_and_a_tolerance(tmp_path, capsys):
    scene = write(tmp_path, "general.py", "import jax.numpy as jnp\nH = lambda q, p: 0.5 * (1 + q @ q) * p @ p\n"
                                          "q0, p0 = [1.0], [0.5]\n")
    assert cli.main(["run", scene, "--method", "split", "--out", str(tmp_path / "out"), "--no-progress"]) == 1
    assert "Splitting('blanes_moan4') needs a separable H" in capsys.readouterr().err
    assert cli.main(["run", "kepler", "--method", "split", "--tol", "1e-6", "--out", str(tmp_path / "out"),
                     "--no-progress"]) == 1
    assert "Splitting with a PIDController" in capsys.readouterr().err


def test_sweep_exits_3_when_a_configuration_fails_and_still_writes_its_table(tmp_path, capsys):
    scene = write(tmp_path, "blowup.py", NO_SOLUTION_SCENE)
    out = str(tmp_path / "out")
    argv = ["sweep", scene, "--methods", "cg1:gauss1", "--step-sizes", "1,0.001", "--steps", "4", "--out", out]
    assert cli.main(argv) == cli.EXIT_FAILED_SOLVE
    captured = capsys.readouterr()
    with open(os.path.join(out, "blowup_sweep.csv")) as f:
        header, *rows = [line.strip().split(",") for line in f]
    failed, passed = (int(row[header.index("status")]) for row in rows)
    assert failed != 0 and passed == 0  # h = 1 has no root; h = 0.001 does
    name = gj.Status(failed).name
    assert captured.err.startswith("galerkin-jax: error: 1 of 2 configurations failed, their diagnostics shown as '-': "
                                   f"status {failed} ({name}) in 1 (cG(1) Gauss-Legendre 1 at h = 1): ")
    assert gj.status_message(failed).split(";")[0] in captured.err
    assert captured.err.count("\n") == 1 and "rylov" not in captured.err  # 2 unknowns per element


def oscillator_dg1_energy_change(n):
    """1 - rho^(2n) of dG(1) with exact quadrature on the oscillator at h = 1 [GBS, eq. (65)]."""
    Om2 = 0.125  # Omega = h omega, omega^2 = 1/8
    return 1 - ((4 * Om2 + 36) / (Om2**2 + 4 * Om2 + 36)) ** n


def test_the_closing_line_follows_the_numbers_a_large_drifting_energy_error(tmp_path, capsys):
    """dG(1) on the oscillator at h = 1: H_n = rho^(2n) H_0, 15.7 % lost in 400 steps."""
    argv = ["run", "oscillator", "--method", "dg1:gauss2", "--step-size", "1", "--steps", "400", "--no-progress"]
    assert cli.main(argv + ["--out", str(tmp_path / "out")]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    percent = float(last.split("up to ")[1].split(" %")[0])
    assert percent == pytest.approx(100 * oscillator_dg1_energy_change(400), abs=0.05)  # printed to 3 digits
    first, final = (float(x) for x in last.split("grows from ")[1].split(" in the last")[0].split(
        " in the first quarter of the run to "))
    assert first == pytest.approx(oscillator_dg1_energy_change(100), rel=0.02)  # two digits printed
    assert final == pytest.approx(oscillator_dg1_energy_change(400), rel=0.02)
    assert "it drifts. The steps are too large for this scene: try a smaller --step-size than 1." in last
    assert "no drift" not in last and "oscillates" not in last and "expected" not in last


def test_energy_verdict_reads_round_off_drift_and_bounded_from_the_numbers():
    eps = np.finfo(np.float64).eps
    t = np.linspace(0.0, 1.0, 101)
    assert summary.energy_verdict(1e-14 * t, eps)[0] == "round-off"  # 45 eps < 1000 eps
    assert summary.energy_verdict(1e-6 * t, eps)[0] == "drift"  # linear growth: last / first quarter = 4
    assert summary.energy_verdict(1e-6 * np.sqrt(t), eps)[0] == "bounded"  # sqrt: a ratio of 2, not above it
    oscillating = 1e-6 * np.sin(10 * np.pi * t) ** 2  # peaks on the grid, at t = 0.05 + 0.1 j
    verdict, words = summary.energy_verdict(oscillating, eps)
    assert verdict == "bounded" and words.startswith("is 1.0e-06 at most in the first quarter")
    assert summary.energy_verdict(1e-6 * t[:8], eps)[0] == "short"
    line = summary.closing_line("e.png", specs.complete(specs.parse_spec("cg2:gauss2")), 1.39 * t, eps, True, 0.5)
    assert "large, up to 139 % of |H(0)|" in line and "does not drift" not in line and "symplectic" not in line
    line = summary.closing_line("e.png", specs.complete(specs.parse_spec("cg2:gauss2")), 1e-6 * t, eps, True, 0.5)
    assert "it drifts. Not what the method usually does: " in line  # Gauss collocation should not drift


def test_steps_too_large_is_judged_against_the_initial_state_not_a_blown_up_run():
    problem = specs.load_scene("kepler")  # initial state of size 2 (|p_2| = 2 at perihelion, e = 0.6)
    blown_up = np.full((3, 2), 1e6)
    solution = SimpleNamespace(t=np.array([0.0, 1.0, 2.0]), q=blown_up, p=blown_up, error_estimate=0.5)
    local = dict(summary.accuracy_lines(problem, solution, 2))["local"]
    assert "2.5e-01 of the initial state's largest |q_i|, |p_i|; the steps are too large to mean much" in local
    solution.error_estimate = 0.1  # 0.05 of the initial state: below the 0.1 that makes a step meaningless
    assert "too large" not in dict(summary.accuracy_lines(problem, solution, 2))["local"]


def test_failure_words_keep_the_krylov_advice_only_above_the_dense_limit():
    status = int(gj.Status.NEWTON_MAX_ITERATIONS)
    small, large = summary.failure_words(status, 12, False), summary.failure_words(status, 300, False)
    assert "rylov" not in small and "--krylov" in large and small in gj.status_message(status)
    assert "rylov" not in summary.failure_words(status, 300, True)  # --krylov given: nothing more to try there
    assert summary.unknowns(gj.CG(3, gj.gauss_legendre(3)), np.zeros(50), np.zeros(50)) == 300  # k * 2d


def test_bodies_of_shape_n_by_2_run_flat_and_draw_their_paths(tmp_path, capsys):
    scene = write(tmp_path, "eight.py", THREE_BODY_SCENE)
    out = tmp_path / "out"
    assert cli.main(["run", scene, "--method", "cg2:gauss2", "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "(3 bodies in 2-D, d = 6 degrees of freedom)" in printed
    data = np.load(out / "eight_cG2-gauss2.npz")
    assert data["q"].shape == (41, 6) and data["state_shape"].tolist() == [3, 2]
    # body 1 starts where the scene put it: the flat state is the (3, 2) array row by row
    np.testing.assert_array_equal(data["q"][0, :2], [0.97000436, -0.24308753])
    # total momentum sum_n p_n, an invariant written for (3, 2) states: zero and kept to round-off
    assert np.abs(data["invariant_P"]).max() < 1e-13
    assert os.path.getsize(out / "eight_cG2-gauss2_bodies.png") > 1000
    assert cli.main(["run", scene, "--method", "cg2:gauss2", "--out", str(out), "--plot", "q0,p_0",
                     "--no-progress"]) == 0
    assert os.path.getsize(out / "eight_cG2-gauss2_q0p0.png") > 1000


def test_the_second_plot_fits_the_scene():
    q = np.zeros((5, 4))
    q[:, 2] = np.linspace(0, 3, 5)  # q_2 varies most
    assert output.choose_view((4,), q) == ("phase", 2)
    assert output.choose_view((2, 2), q) == ("bodies", (2, 2))
    assert output.choose_view((3,), q[:, :3]) == ("bodies", (1, 3))
    assert output.choose_view((4,), q, (("q", 0), ("p", 3))) == ("pair", (("q", 0), ("p", 3)))
    assert output.parse_coordinate("q_12") == ("q", 12) and output.parse_coordinate("x1") is None
    assert specs.load_scene("kepler").center == (0.0, 0.0)  # the Sun, marked in the orbit plot
    assert specs.load_scene("oscillator").center is None


def test_run_to_an_end_time_with_a_tolerance_prints_its_steps(tmp_path, capsys):
    """--t-end with --tol: error-per-step control lands on T and the summary tells the steps,
    the rejections and the range of h; the trajectory holds the steps' nodes."""
    out = str(tmp_path / "out")
    assert cli.main(["run", "kepler", "--t-end", "6.2832", "--tol", "1e-8", "--no-progress", "--out", out]) == 0
    printed = capsys.readouterr().out
    control = next(line for line in printed.splitlines() if line.startswith("control"))
    assert "error per step, tol = 1e-08" in control and "rejected" in control
    # the files say the controller, so that they do not overwrite a fixed-step run's
    assert sorted(os.listdir(out)) == [f"kepler_cG3-gauss3_pid{suffix}" for suffix in
                                       (".npz", "_energy.png", "_orbit.png")]
    data = np.load(os.path.join(out, "kepler_cG3-gauss3_pid.npz"))
    assert str(data["step_rule"]) == "error per step, tol = 1e-08"
    steps = int(control.split(":")[1].split()[0])
    assert len(data["t"]) == steps + 1 and abs(data["t"][-1] - 6.2832) < 1e-12
    h = np.diff(data["t"])
    assert h.max() / h.min() > 5  # e = 0.6: small steps at perihelion, large at aphelion
    # steps chosen from the state are not symplectic: the summary does not promise a bounded error
    hint = printed.strip().splitlines()[-1].split(": ", 2)[2]
    assert "a symplectic method with fixed steps; steps chosen from the state by error-per-step control break " \
           "that structure, so the energy error can drift over long runs" in hint
    assert "oscillates and does not drift" not in hint


def test_a_scene_file_may_set_t1_and_tol_and_the_time_transformation_lands_on_it(tmp_path, capsys):
    scene = tmp_path / "s.py"
    scene.write_text(USER_SCENE + "t1 = 1.5\ntol = 1e-9\n")
    out = str(tmp_path / "out")
    assert cli.main(["run", str(scene), "--time-transform", "--no-progress", "--out", out]) == 0
    printed = capsys.readouterr().out
    control = next(line for line in printed.splitlines() if line.startswith("control"))
    assert control.startswith("control  time transformation (default s), h in tau: ")
    data = np.load(os.path.join(out, "s_cG3-gauss3_time-transform.npz"))
    assert abs(float(data["t"][-1]) - 1.5) < 1e-13
    steps = np.diff(data["t"])
    assert control.endswith(f"; steps in t from {steps.min():.3g} to {steps.max():.3g}")
    # the time transformation keeps Gauss collocation symplectic: this promise stays
    assert printed.strip().endswith("Gauss collocation, a symplectic method, and the time transformation keeps it "
                                    "symplectic (a constant step in the fictive time tau on the extended phase space): "
                                    "the energy error oscillates and does not drift.")
    scene.write_text(USER_SCENE + "t1 = -1.0\n")
    assert cli.main(["run", str(scene), "--out", out + "2"]) == 1
    assert "t1 must be finite and > 0" in capsys.readouterr().err
    assert not os.path.exists(out + "2")


@pytest.mark.parametrize("argv", [["--tol", "1e-8", "--time-transform"], ["--steps", "10", "--t-end", "1"]])
def test_conflicting_step_options_exit_2(tmp_path, capsys, argv):
    out = str(tmp_path / "out")
    assert cli.main(["run", "kepler", *argv, "--out", out]) == cli.EXIT_BAD_OPTION
    assert capsys.readouterr().err.count("\n") == 1 and not os.path.exists(out)


def test_sweep_to_an_end_time_reaches_it_with_every_step_size(tmp_path, capsys):
    """--t-end on sweep: every h reaches T (its last step shortened), so the final errors
    against the exact solution at T fall with h."""
    out = str(tmp_path / "out")
    assert cli.main(["sweep", "kepler", "--methods", "cg2:gauss2", "--step-sizes", "0.1,0.07,0.05",
                     "--t-end", "3.0", "--no-progress", "--out", out]) == 0
    rows = [line.split(",") for line in open(os.path.join(out, "kepler_sweep.csv")).read().splitlines()]
    column = rows[0].index("final error")
    finals = [float(row[column]) for row in rows[1:]]
    assert finals[0] > finals[1] > finals[2]


def test_the_file_names_and_the_plot_title_say_how_the_steps_were_chosen():
    """A controlled run writes files of its own (a fixed-step run's are not overwritten), and
    the title gives the time transformation's h as its step in tau, with the steps in t."""
    problem, spec = specs.load_scene("kepler"), specs.complete(specs.parse_spec("cg"))
    pid = dict(name="pid", tol=1e-8)
    tt, fixed_to_t1 = dict(name="time-transform", tol=None), dict(name=None, tol=None)
    assert cli.run_stem(problem, spec, None) == cli.run_stem(problem, spec, fixed_to_t1) == "kepler_cG3-gauss3"
    assert cli.run_stem(problem, spec, pid) == "kepler_cG3-gauss3_pid"
    assert cli.run_stem(problem, spec, tt) == "kepler_cG3-gauss3_time-transform"
    nodes = SimpleNamespace(t=np.array([0.0, 0.05, 0.3, 0.32]), stats={"num_accepted_steps": 3})
    between = SimpleNamespace(t=np.linspace(0.0, 0.32, 11), stats={"num_accepted_steps": 3})  # save_at: steps unknown
    title = lambda span, solution: cli.plot_title(problem, spec, 0.05, span, solution)
    assert title(None, nodes) == "kepler, cG(3) Gauss-Legendre 3, h = 0.05"
    assert title(tt, nodes) == "kepler, cG(3) Gauss-Legendre 3\nh = 0.05 in tau, steps in t from 0.02 to 0.25"
    assert title(tt, between) == "kepler, cG(3) Gauss-Legendre 3\nh = 0.05 in tau"
    assert title(pid, nodes) == "kepler, cG(3) Gauss-Legendre 3\ntol = 1e-08, h from 0.02 to 0.25"


def test_the_closing_line_under_a_controller_promises_what_the_step_rule_keeps():
    eps = np.finfo(np.float64).eps
    t = np.linspace(0.0, 1.0, 101)
    gauss, vi = (specs.complete(specs.parse_spec(text)) for text in ("cg2:gauss2", "vi2"))
    line = lambda spec, change, controller, tol=None: summary.closing_line("e.png", spec, change, eps, True, 0.5,
                                                                          controller, tol)
    # error-per-step control breaks symplecticity: a drift is what it may do
    assert line(gauss, 1e-6 * t, "pid", 1e-6).startswith(
        "Look at e.png: the energy error grows from 2.5e-07 in the first quarter of the run to 1.0e-06 in the last: "
        "it drifts. As expected: cG(k) with k Gauss points is Gauss collocation, a symplectic method with fixed "
        "steps; steps chosen from the state by error-per-step control break that structure")
    assert "As expected: a variational integrator is symplectic with fixed steps; " in line(vi, 1e-6 * t, "pid", 1e-6)
    # the time transformation keeps it: a drift is not
    kept = line(gauss, 1e-6 * t, "time-transform")
    assert "it drifts. Not what the method usually does: cG(k) with k Gauss points is Gauss collocation, a " \
           "symplectic method, and the time transformation keeps it symplectic" in kept
    assert "it drifts. Not what the method usually does: " in line(gauss, 1e-6 * t, None)
    # a large error: under error-per-step control the tolerance is what to change, in tau the step
    assert line(gauss, 1.39 * t, "pid", 1e-6).endswith(
        "it drifts. The tolerance is too loose for this scene: try a smaller --tol than 1e-06.")
    assert line(gauss, 1.39 * t, "time-transform").endswith(
        "try a smaller --step-size than 0.5 (the step in the fictive time tau).")


def test_a_failed_controlled_run_says_what_to_change_in_the_commands_terms():
    tt, max_steps = int(gj.Status.TIME_TRANSFORM), int(gj.Status.MAX_STEPS)
    message = summary.failure_message(tt, 6, False, 0.05, "time-transform", None, 1000)
    assert message == (
        "the solve failed (status 6, TIME_TRANSFORM): The time transformation's step density s(q, p) was not "
        "positive and finite at a state of the run: the command's s, the default (|F(z0)| / |F(z)|)^(3/4) with F "
        "Hamilton's field (at most 3 where F vanishes), fails where F overflows, at a collision. Try --tol or "
        "fixed steps (--t-end alone): the command's time transformation has only the default s.")
    assert summary.failure_message(max_steps, 6, False, 0.05, "pid", 1e-8, 1000).endswith(
        "The run reached --max-steps (accepted and rejected steps together) before its end time. Try a larger "
        "--max-steps than 1000 or a looser --tol than 1e-08.")
    assert summary.failure_message(max_steps, 6, False, 0.05, "time-transform", None, 1000).endswith(
        "Try a larger --max-steps than 1000 or a larger --step-size than 0.05.")
    dtmin = summary.failure_message(int(gj.Status.DTMIN), 6, False, 0.05, "pid", 1e-8, 1000)
    assert dtmin.endswith("Try a looser --tol than 1e-08, or fixed steps.") and "--step-size" not in dtmin


def test_a_time_transformed_run_from_an_equilibrium_stays_there(tmp_path, capsys):
    """The default density at an equilibrium is s = 1 (it was 0 / 0, status 6, exit 3, before
    its bound: tests/test_step_density.py): the run exits 0 and the state stays at rest."""
    scene = write(tmp_path, "rest.py", "H = lambda q, p: 0.5 * (q @ q + p @ p)\nq0, p0 = [0.0], [0.0]\n")
    out = tmp_path / "out"
    assert cli.main(["run", scene, "--time-transform", "--t-end", "1", "--no-progress", "--out", str(out)]) == 0
    data = np.load(out / "rest_cG3-gauss3_time-transform.npz")
    assert float(data["t"][-1]) == 1.0 and not np.any(data["q"]) and not np.any(data["p"])
