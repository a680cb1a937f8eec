"""``galerkin_jax.plot``: each helper draws the expected artists with the papers' numbers."""

import subprocess
import sys

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
import pytest

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import galerkin_jax as gj  # noqa: E402
from galerkin_jax import plot, scenes  # noqa: E402

OSCILLATOR = scenes.oscillator()  # m = 2, c = -0.25: omega = sqrt(1/8)
OMEGA = np.sqrt(0.125)
KEPLER = scenes.kepler(0.5)


@pytest.fixture(autouse=True)
def close_figures():
    yield
    plt.close("all")


def rho2_dg1_exact(Om):
    """[GBS, eq. (65)]: dG(1) with exact quadrature on the oscillator."""
    return (4 * Om**2 + 36) / (Om**4 + 4 * Om**2 + 36)


def test_import_galerkin_jax_does_not_import_matplotlib():
    code = "import sys, galerkin_jax; assert 'matplotlib' not in sys.modules, 'matplotlib imported'"
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.fixture(scope="module")
def oscillator_runs():
    """cG(1) and dG(1) with exact quadrature, h = 1, 30 steps (Figs. 4.1, 4.4)."""
    run = lambda family: gj.integrate(OSCILLATOR.H, OSCILLATOR.q0, OSCILLATOR.p0,
                                      method=family(1, gj.gauss_legendre(2)), h=1.0, n_steps=30)
    return run(gj.CG), run(gj.DG)


def test_energy_error_is_one_minus_rho_to_the_2n_for_dg1(oscillator_runs):
    """H_n = rho^(2n) H_0 (Lemma 4.5 with eq. (65)); cG(1) conserves H (Prop. 4.1): drawn at the floor or round-off."""
    cg, dg = oscillator_runs
    ax = plot.energy_error(cg, OSCILLATOR.H, label="cG(1)")
    assert plot.energy_error(dg, OSCILLATOR.H, ax=ax, label="dG(1)") is ax
    assert len(ax.lines) == 2 and ax.get_yscale() == "log"
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["cG(1)", "dG(1)"]
    t, conserved = ax.lines[0].get_data()
    np.testing.assert_array_equal(t, np.arange(31.0))
    assert conserved.min() >= plot.FLOOR and conserved.max() < 1e-14  # round-off over 30 steps
    _, decay = ax.lines[1].get_data()
    # 30 steps of a linear map: relative round-off ~30 eps on each value, so 1e-12 on 1 - rho^2n ~ 1e-2
    np.testing.assert_allclose(decay, 1 - rho2_dg1_exact(OMEGA) ** np.arange(31), rtol=1e-10, atol=1e-15)
    assert ax.get_xlabel() == "$t$" and "H_0" in ax.get_ylabel()


def test_invariant_error_of_angular_momentum_decays_with_rho2_too(oscillator_runs):
    """L_n = rho^(2n) L_0 [GBS, Prop. 4.5]; absolute error = (1 - rho^2n) |L_0|."""
    _, dg = oscillator_runs
    L = OSCILLATOR.invariants["L"]
    ax = plot.invariant_error(dg, L, relative=False)
    L0 = float(L(jnp.asarray(OSCILLATOR.q0), jnp.asarray(OSCILLATOR.p0)))
    _, change = ax.lines[0].get_data()
    np.testing.assert_allclose(change, (1 - rho2_dg1_exact(OMEGA) ** np.arange(31)) * L0, rtol=1e-10, atol=1e-15)
    assert ax.get_yscale() == "log" and ax.get_ylabel() == "$|{L}_n - {L}_0|$"
    with pytest.raises(ValueError, match="solution"):
        batched = jax.tree.map(lambda x: jnp.stack([x, x]), dg)
        plot.invariant_error(batched, L)


@pytest.fixture(scope="module")
def kepler_midpoint():
    """cG(1) + midpoint on Kepler (e = 0.5), 512 steps of h = 2 pi / n, n = 128, 256, 512 (vmapped)."""
    ns = np.array([128, 256, 512])  # at n = 64 (h ~ 0.1) the error is 0.47, not yet O(h^2)
    solutions = jax.vmap(lambda h: gj.integrate(KEPLER.H, KEPLER.q0, KEPLER.p0, method=gj.CG(1, gj.midpoint()),
                                                h=h, n_steps=512))(jnp.asarray(2 * np.pi / ns))
    return ns, solutions


def test_orbit_and_phase_portrait_join_the_saved_states(kepler_midpoint):
    sol = jax.tree.map(lambda x: x[2], kepler_midpoint[1])
    ax = plot.orbit(sol, label="cG(1)")
    (line,) = ax.lines
    np.testing.assert_array_equal(np.column_stack(line.get_data()), np.asarray(sol.q))
    assert line.get_marker() == "." and (ax.get_xlabel(), ax.get_ylabel()) == ("$q_{1}$", "$q_{2}$")
    ax = plot.phase_portrait(sol, index=1)
    np.testing.assert_array_equal(ax.lines[0].get_xdata(), np.asarray(sol.q[:, 1]))
    np.testing.assert_array_equal(ax.lines[0].get_ydata(), np.asarray(sol.p[:, 1]))
    with pytest.raises(ValueError, match="dims"):
        plot.orbit(sol, dims=(0, 2))


def test_orbit_with_dense_output_draws_the_element_polynomials():
    """samples_per_step points per element, from ``evaluate``; the markers on the saved states."""
    sol = gj.integrate(KEPLER.H, KEPLER.q0, KEPLER.p0, method=gj.CG(2, gj.gauss_legendre(2)), h=0.1,
                       n_steps=20, save_every=2, dense=True)
    ax = plot.orbit(sol, samples_per_step=5)
    x, y = ax.lines[0].get_data()
    assert len(x) == 20 * 5 + 1 and ax.lines[0].get_markevery() == 2 * 5
    fine = np.linspace(0.0, 2.0, 101)
    q, _ = sol.evaluate(fine)
    np.testing.assert_allclose(np.column_stack([x, y]), np.asarray(q), atol=1e-15)
    np.testing.assert_allclose(np.column_stack([x, y])[::10], np.asarray(sol.q), atol=1e-15)  # the nodes
    # between the nodes the polynomial is not the chord: 4th-order cG(2) on Kepler, h = 0.1
    q_exact, _ = KEPLER.exact(fine[5])
    assert np.abs(np.array([x[5], y[5]]) - q_exact).max() < 1e-4


def test_spectral_radius_is_eq59_for_cg1_midpoint_and_eq65_for_dg1_exact():
    omegas = np.logspace(-1, 2, 7)
    ax = plot.spectral_radius({"cG(1) midpoint": gj.CG(1, gj.midpoint()),
                               "dG(1) exact": gj.DG(1, gj.gauss_legendre(2))}, omegas)
    assert len(ax.lines) == 2 and ax.get_xscale() == "log"
    np.testing.assert_array_equal(ax.lines[0].get_xdata(), omegas)
    # eigenvalues of a 2 x 2 matrix with entries ~1: round-off a few eps
    np.testing.assert_allclose(ax.lines[0].get_ydata(), 1.0, rtol=1e-13)  # Lemma 4.4: symmetric rule, rho = 1
    np.testing.assert_allclose(ax.lines[1].get_ydata(), np.sqrt(rho2_dg1_exact(omegas)), rtol=1e-12)
    with pytest.raises(ValueError, match="omegas"):
        plot.spectral_radii(gj.CG(1, gj.midpoint()), [0.0, 1.0])


def test_convergence_legend_shows_order_2_for_cg1_midpoint_on_kepler(kepler_midpoint):
    """cG(1) + midpoint is the implicit midpoint rule (Prop. 3.2): order 2 at t = 2 pi."""
    ns, sols = kepler_midpoint
    hs = 2 * np.pi / ns
    q_exact, _ = KEPLER.exact(2 * np.pi)
    errors = np.abs(np.asarray(sols.q)[np.arange(3), ns] - q_exact).max(axis=1)
    at_round_off = np.append(hs[:2] ** 4, 1e-14)  # the last point is below the floor: left out of the fit
    ax = plot.convergence(hs, {"cG(1) midpoint": errors, "h^4": at_round_off}, floor=1e-12)
    assert len(ax.lines) == 2 and ax.get_xscale() == ax.get_yscale() == "log"
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    slope = float(labels[0].split("slope ")[1].rstrip(")"))
    assert slope == pytest.approx(2.0, abs=0.1)  # measured 1.99 (local slopes 1.98, 2.00)
    assert labels[1] == "h^4 (slope 4.00)"
    assert abs(plot.fitted_slope(hs, at_round_off) - 4) > 1  # without the floor the round-off point bends the fit
    assert plot.fitted_slope(hs, [1e-13, 1e-14, 1e-15], floor=1e-12) is None


def test_work_precision_and_sweep_map():
    ax = plot.work_precision({"a": ([1e-3, 1e-2], [1e-4, 1e-8]), "b": ([2e-3, 3e-2], [1e-5, 1e-9])})
    assert len(ax.lines) == 2 and ax.get_xscale() == ax.get_yscale() == "log"
    values = np.array([[1.2e-7, 0.0, np.nan], [3e-3, 4.5e-12, 1e-16]])
    ax = plot.sweep_map(values, ["cG(1)", "dG(1)"], ["h = 0.1", "h = 0.2", "h = 0.4"], title="energy error")
    texts = [t.get_text() for t in ax.texts]
    assert texts == ["1.2e-07", "0.0e+00", "failed", "3.0e-03", "4.5e-12", "1.0e-16"]
    (image,) = ax.images
    assert isinstance(image.norm, matplotlib.colors.LogNorm) and image.get_array().mask[0, 2]
    assert len(ax.figure.axes) == 2  # the colour bar
    assert [t.get_text() for t in ax.get_yticklabels()] == ["cG(1)", "dG(1)"]
    with pytest.raises(ValueError, match="values"):
        plot.sweep_map(values, ["one row"], ["a", "b", "c"])


def test_bodies_draws_each_body_from_states_of_shape_m_n_d_or_flat_with_the_layout():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(7, 3, 2))  # 7 saved states of 3 bodies in the plane
    ax = plot.bodies(q, center=(0.0, 0.0))
    flat = plot.bodies(q.reshape(7, 6), shape=(3, 2))
    for axes in (ax, flat, plot.bodies(q, shape=(3, 2))):
        paths = axes.lines[0:6:2]  # a line and a start dot per body
        for n, line in enumerate(paths):
            np.testing.assert_array_equal(np.column_stack(line.get_data()), q[:, n])
            np.testing.assert_array_equal(np.column_stack(axes.lines[2 * n + 1].get_data()), q[:1, n])
        assert [t.get_text() for t in axes.get_legend().get_texts()][:3] == ["body 1", "body 2", "body 3"]
    star = ax.lines[-1]
    assert star.get_marker() == "*" and star.get_label() == "central body" and star.get_xydata().tolist() == [[0, 0]]
    assert len(flat.lines) == 6  # no central body where none is given
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("$x$", "$y$")
    with pytest.raises(ValueError, match="shape"):
        plot.bodies(q.reshape(7, 6), shape=(4, 2))
    with pytest.raises(ValueError, match="center"):
        plot.bodies(q, center=(0.0, 0.0, 0.0))


def test_bodies_in_3d_draw_the_plane_of_most_spread():
    t = np.linspace(0, 2 * np.pi, 50)
    q = np.zeros((50, 2, 3))
    q[:, :, 0] = 0.01 * np.cos(t)[:, None]  # x barely moves: the paths lie in the y-z plane
    q[:, 0, 1], q[:, 0, 2] = np.cos(t), np.sin(t)
    q[:, 1, 1], q[:, 1, 2] = 2 * np.cos(t), -np.sin(t)
    assert plot.plane(q) == (1, 2)
    ax = plot.bodies(q)
    np.testing.assert_array_equal(ax.lines[2].get_xdata(), q[:, 1, 1])
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("$y$", "$z$")
    np.testing.assert_array_equal(plot.bodies(q, dims=(0, 2)).lines[0].get_xdata(), q[:, 0, 0])


def test_bodies_and_coordinates_of_a_run(kepler_midpoint):
    sol = jax.tree.map(lambda x: x[0], kepler_midpoint[1])
    ax = plot.bodies(sol, shape=(1, 2), center=(0.0, 0.0))  # one body around the Sun
    np.testing.assert_array_equal(np.column_stack(ax.lines[0].get_data()), np.asarray(sol.q))
    assert ax.get_legend().get_texts()[0].get_text() == "central body"  # a single body is not labelled
    ax = plot.coordinates(sol, ("q", 1), ("p", 0))
    np.testing.assert_array_equal(ax.lines[0].get_xdata(), np.asarray(sol.q[:, 1]))
    np.testing.assert_array_equal(ax.lines[0].get_ydata(), np.asarray(sol.p[:, 0]))
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("$q_{1}$", "$p_{0}$")
    with pytest.raises(ValueError, match="index"):
        plot.coordinates(sol, ("q", 2), ("p", 0))
