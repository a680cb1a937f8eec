"""The papers' table and figures, regenerated from the library: ``reproduce(folder)``.

- [GBS] Table 5.1 (``table51``): the class of the total energy H and of |L| for cG(1) and
  dG(1) with the rules of each column, measured on the isotropic oscillator (Hooke's
  potential) and on the quartic central force V = c (r^2 - 1)^2 / 2.
- [GBS] Figs. 4.1-4.7: H and L_zeta against time for those runs, and dG(1)'s spectral
  radius against Omega = h omega for several symmetric rules.
- [Tang]: the order 2s of GalerkinVI(s), its symplecticity against non-symplectic Galerkin
  methods, and its equivalence with LagrangianVI for L = qdot^T M qdot / 2 - U(q).

Everything runs in float64 (inside ``jax.enable_x64(True)``; the global config is left alone):
the class C means a relative change below 1e-12.
"""

import dataclasses
import functools
import pathlib
import types

import jax
import jax.numpy as jnp
import numpy as np

import galerkin_jax as gj

from . import plot, scenes

HOOKE, QUARTIC = scenes.oscillator(), scenes.quartic()  # built once: jit caches by H
KEPLER = scenes.kepler(0.5)
_angular_momentum = HOOKE.invariants["L"]  # |q x p| = L_zeta, its one nonzero component

RULES = {
    "exact": gj.gauss_legendre(3),  # exact for Hooke's potential (integrands of degree <= 2)
    "midpoint": gj.midpoint(),
    "gauss2": gj.gauss_legendre(2),
    "gauss3": gj.gauss_legendre(3),
    "lobatto3": gj.gauss_lobatto(3),
    "trapezoid": gj.trapezoid(),
}
MODIFIED_MIDPOINT = "modified midpoint"  # gj.ModifiedMidpoint(), eqs. (90)-(91); for dG(1) too (Prop. 3.2)
FAMILIES = {"cG(1)": gj.CG, "dG(1)": gj.DG}
# scene: (H and state, step sizes, steps, rules run); Hooke h = 1: Figs. 4.1, 4.4; h = 0.1: Figs. 4.2, 4.5
TABLE_SCENES = {
    "Hooke": (HOOKE, (1.0, 0.1), 200, ("exact", "midpoint", "gauss2", "lobatto3", "trapezoid")),
    "quartic": (QUARTIC, (0.01,), 2000, ("midpoint", "gauss2", "gauss3", "lobatto3", "trapezoid")),  # Figs. 4.6, 4.7
}

# [GBS, Table 5.1]: each column as (scene, rules measured); the classes as printed, None where the box is empty.
COLUMNS = {
    "Hooke: exact": ("Hooke", ("exact",)),
    "Hooke: N_q = 1": ("Hooke", ("midpoint",)),
    "Hooke: 1 < N_q": ("Hooke", ("gauss2", "lobatto3", "trapezoid")),
    "arbitrary V: N_q = 1": ("quartic", (MODIFIED_MIDPOINT, "midpoint")),
    "arbitrary V: 1 < N_q": ("quartic", ("gauss2", "gauss3", "lobatto3", "trapezoid")),
}
PAPER_TABLE51 = {
    ("cG(1)", "H"): ("C", "C", "C", "C*", None),
    ("cG(1)", "L"): ("C", "C", "C", "C", "NC"),
    ("dG(1)", "H"): ("D", "C", "D", "C*", None),
    ("dG(1)", "L"): ("D", "C", "D", "C", "NC"),
}
C_TOLERANCE = 1e-12  # ~10^4 eps: round-off over thousands of steps stays far below


def classify(values):
    """The class of a sequence of values of H or |L| [GBS, Table 5.1].

    Args:
        values: shape ``(m,)``, the quantity at the nodes, the initial value first.
    Returns:
        "C" (conserved: every relative change below 1e-12), "D" (strictly decreasing) or
        "NC" (neither).
    """
    values = np.asarray(values, dtype=float)
    if values.ndim != 1 or values.shape[0] < 2 or values[0] == 0:
        raise ValueError(f"values must have shape (m,), m >= 2, a nonzero first value; got shape {values.shape}.")
    if np.max(np.abs(values / values[0] - 1)) < C_TOLERANCE:
        return "C"
    if np.all(np.diff(values) < 0):
        return "D"
    return "NC"


def summarize(measured):
    """One class for a box from the classes of its runs (label -> class): the class they
    share; "C*" when only the modified midpoint rule conserves; else e.g. "C (gauss2), NC (trapezoid)"."""
    classes = set(measured.values())
    if len(classes) == 1:
        return classes.pop()
    if measured.get(MODIFIED_MIDPOINT) == "C" and list(measured.values()).count("C") == 1:
        return "C*"
    order = sorted(classes, key=["C", "D", "NC"].index)
    return ", ".join(f"{c} ({', '.join(k for k, v in measured.items() if v == c)})" for c in order)


def agrees(paper, measured):
    """Whether a box's runs (label -> class) agree with the paper's class; NC
    ("nonconservation") holds when no run conserves, so a measured D meets it too."""
    if paper == "NC":
        return "C" not in measured.values()
    return summarize(measured) == paper


@dataclasses.dataclass(frozen=True)
class Cell:
    """One box of [GBS, Table 5.1].

    Attributes:
        method, quantity, column: "cG(1)" or "dG(1)"; "H" or "L"; a key of ``COLUMNS``.
        paper: "C", "D", "C*", "NC", or None where the paper leaves the box empty.
        measured: run label (the rule, and for Hooke the step size) -> class (``classify``).
    """

    method: str
    quantity: str
    column: str
    paper: object
    measured: dict

    def render(self):
        """The box's text: the paper's class, what the runs add, or what fills an empty box."""
        summary = summarize(self.measured)
        if self.paper is None:
            return f"*empty in the paper*: {summary}"
        if not agrees(self.paper, self.measured):
            return f"**paper {self.paper}, measured {summary}**"
        return self.paper if summary == self.paper else f"{self.paper} (measured {summary})"


@dataclasses.dataclass(frozen=True)
class Table51:
    """[GBS, Table 5.1] as measured.

    Attributes:
        cells: every box, row by row (cG(1) H, cG(1) L, dG(1) H, dG(1) L), column by column.
        runs: run label ("quartic, gauss2, h = 0.01") -> {"cG(1) H": class, ...}.
    """

    cells: tuple
    runs: dict

    def cell(self, method, quantity, column):
        return next(c for c in self.cells if (c.method, c.quantity, c.column) == (method, quantity, column))

    def _rows(self):
        return [[f"{m} {q}"] + [self.cell(m, q, c).render() for c in COLUMNS] for m, q in PAPER_TABLE51]

    def markdown(self):
        """The table in markdown, then the class of every run."""
        lines = ["| | " + " | ".join(COLUMNS) + " |", "|" + " --- |" * (len(COLUMNS) + 1)]
        lines += ["| " + " | ".join(row) + " |" for row in self._rows()]
        lines += ["", "C: relative change < 1e-12 throughout; D: strictly decreasing; NC: neither; C*: C only "
                  "with the modified midpoint rule. The paper's NC (nonconservation) is met by D too.", ""]
        rows = [f"{m} {q}" for m, q in PAPER_TABLE51]
        lines += ["| run | " + " | ".join(rows) + " |", "|" + " --- |" * (len(rows) + 1)]
        lines += [f"| {run} | " + " | ".join(c.get(r, "") for r in rows) + " |" for run, c in self.runs.items()]
        return "\n".join(lines) + "\n"

    def text(self):
        """The table as plain text, for printing."""
        rows = [[""] + list(COLUMNS)] + [[x.replace("*empty in the paper*", "(empty)").replace("**", "") for x in row]
                                         for row in self._rows()]
        widths = [max(len(r[j]) for r in rows) for j in range(len(rows[0]))]
        return "\n".join("  ".join(x.ljust(w) for x, w in zip(r, widths)).rstrip() for r in rows) + "\n"

    __str__ = text


def table_runs():
    """Every run of Table 5.1 (also those of Figs. 4.1, 4.2, 4.4-4.7), saving every state.

    One ``gj.sweep`` per method and scene (one compilation each), and ``gj.integrate`` for
    the modified midpoint rule, which is cG(1) and dG(1) alike (Prop. 3.2).

    Returns:
        ``{(method, scene, rule, h): Solution}``, scene "Hooke" or "quartic" (``TABLE_SCENES``).
    """
    runs = {}
    for name, (scene, hs, n_steps, rules) in TABLE_SCENES.items():
        for method, family in FAMILIES.items():
            configs = gj.grid(method=[family(1, RULES[r]) for r in rules], h=hs, state=[(scene.q0, scene.p0)])
            # NumPy copies, sliced without compiling a program per array shape and index
            batch = jax.tree.map(np.asarray, gj.sweep(scene.H, configs, n_steps=n_steps, save_every=1).solution)
            for i, (rule, h) in enumerate((r, h) for r in rules for h in hs):  # grid order: method, then h
                runs[method, name, rule, h] = jax.tree.map(lambda x: x[i], batch)
    _, (h,), n_steps, _ = TABLE_SCENES["quartic"]
    modified = gj.integrate(QUARTIC.H, QUARTIC.q0, QUARTIC.p0, method=gj.ModifiedMidpoint(), h=h, n_steps=n_steps)
    return {**runs, **{(method, "quartic", MODIFIED_MIDPOINT, h): modified for method in FAMILIES}}


@functools.partial(jax.jit, static_argnums=0)
def _along(H, q, p):
    """H and L_zeta at every node: one compiled program per scene and run length."""
    return jax.vmap(H)(q, p), jax.vmap(_angular_momentum)(q, p)


def _classes(scene, solution):
    """{"H": class, "L": class} of one run."""
    if int(solution.status) != 0:
        raise RuntimeError(f"a Table 5.1 run failed: {gj.status_message(int(solution.status))}")
    H, L = _along(scene.H, solution.q, solution.p)
    return {"H": classify(H), "L": classify(L)}


def table51(runs=None):
    """[GBS, Table 5.1] measured box by box, the boxes the paper leaves empty included.

    Args:
        runs: the output of ``table_runs`` if already computed.
    Returns:
        ``Table51``; ``.markdown()`` and ``.text()`` render it.
    """
    with jax.enable_x64(True):
        runs = table_runs() if runs is None else runs
        classes = {key: _classes(TABLE_SCENES[key[1]][0], sol) for key, sol in runs.items()}
    cells = []
    for (method, quantity), paper_row in PAPER_TABLE51.items():
        for (column, (scene, rules)), paper in zip(COLUMNS.items(), paper_row):
            hs = TABLE_SCENES[scene][1]
            label = (lambda r, h: f"{r}, h = {h:g}") if len(hs) > 1 else (lambda r, h: r)
            measured = {label(r, h): classes[method, scene, r, h][quantity] for r in rules for h in hs}
            cells.append(Cell(method, quantity, column, paper, measured))
    by_run = {}
    for (method, scene, rule, h), c in classes.items():
        by_run.setdefault(f"{scene}, {rule}, h = {h:g}", {}).update({f"{method} {q}": c[q] for q in c})
    return Table51(tuple(cells), by_run)


# ---------------------------------------------------------------- [GBS] figures


def _figure(ncols=1):
    from matplotlib.figure import Figure  # no pyplot: no global state, no GUI backend

    fig = Figure(figsize=(5.5 * ncols, 4.2), layout="constrained")
    return fig, fig.subplots(1, ncols, squeeze=False)[0]


def _save(fig, path):
    fig.savefig(path, dpi=90)
    return str(path)


# [GBS, Fig. 4.n]: (quantity, scene, h, rules). Quartic: the radial period is ~0.14
# (omega_r = sqrt(4c/m)), so the figures show t <= 1 of the 20 time units run.
GBS_FIGURES = {
    "4.1": ("H", "Hooke", 1.0, ("exact",)),
    "4.2": ("H", "Hooke", 0.1, ("midpoint",)),
    "4.4": ("L", "Hooke", 1.0, ("exact",)),
    "4.5": ("L", "Hooke", 0.1, ("midpoint",)),
    "4.6": ("H", "quartic", 0.01, ("midpoint", MODIFIED_MIDPOINT)),
    "4.7": ("L", "quartic", 0.01, ("midpoint", MODIFIED_MIDPOINT)),
}
_SHOWN = {"Hooke": (np.inf, "isotropic oscillator (Hooke)"), "quartic": (1.0, "V = c (r^2 - 1)^2 / 2")}


def gbs_history_figure(runs, folder, number):
    """[GBS, Fig. ``number``] (4.1, 4.2, 4.4-4.7): H or L_zeta = |q x p| against t for cG(1)
    and dG(1) (left, as in the paper) and its relative change on a log scale (right)."""
    quantity, scene, h, rules = GBS_FIGURES[number]
    t_shown, title = _SHOWN[scene]
    H = TABLE_SCENES[scene][0].H
    fig, (left, right) = _figure(2)
    for method in FAMILIES:
        for rule in rules:
            run = runs[method, scene, rule, h]
            keep = np.asarray(run.t) <= t_shown
            sol = types.SimpleNamespace(**{x: np.asarray(getattr(run, x))[keep] for x in "tqp"})
            label = f"{method}, {'m.m.r.' if rule == MODIFIED_MIDPOINT else rule}"
            if quantity == "H":
                plot.time_series(sol.t, jax.vmap(H)(sol.q, sol.p), ax=left, label=label, ylabel="$H$")
                plot.energy_error(sol, H, ax=right, label=label)
            else:
                values = jax.vmap(_angular_momentum)(sol.q, sol.p)
                plot.time_series(sol.t, values, ax=left, label=label, ylabel=r"$L_\zeta$")
                plot.invariant_error(sol, _angular_momentum, name=r"L_\zeta", ax=right, label=label)
            if method == "dG(1)":  # dashed: with one point at 1/2 dG(1) is cG(1) (Prop. 3.2)
                left.lines[-1].set_linestyle("--"), right.lines[-1].set_linestyle("--")
    right.set_ylim(plot.FLOOR / 2, max(right.get_ylim()[1], 1e-10))  # round-off looks like round-off
    middle = np.mean(left.get_ylim())
    if np.ptp(left.get_ylim()) < 1e-3 * abs(middle):  # a conserved quantity: not zoomed into its round-off
        left.set_ylim(middle - 0.01 * abs(middle), middle + 0.01 * abs(middle))
    left.ticklabel_format(axis="y", useOffset=False)
    fig.suptitle(f"[GBS, Fig. {number}] {title}, h = {h:g}")
    name = "energy" if quantity == "H" else "angular_momentum"
    return _save(fig, folder / f"fig{number.replace('.', '_')}_{name}_{scene}_h{h:g}.png")


SPECTRAL_RULES = {  # symmetric rules [GBS, Definition 4.1], Fig. 4.3
    "exact (Gauss 2, Lobatto 3, ...)": gj.gauss_legendre(2),  # the dG(1) integrand has degree 2
    "midpoint": gj.midpoint(),
    "trapezoid": gj.trapezoid(),
    "points 1/4, 3/4": gj.QuadratureRule([0.25, 0.75], [0.5, 0.5]),
    "points 0.1, 0.9": gj.QuadratureRule([0.1, 0.9], [0.5, 0.5]),
    "points 0, 1/2, 1; weights 1/4, 1/2, 1/4": gj.QuadratureRule([0.0, 0.5, 1.0], [0.25, 0.5, 0.25]),
}


def gbs_spectral_radius_figure(path, quick):
    """[GBS, Fig. 4.3]: rho of dG(1)'s amplification matrix against Omega (eq. (69))."""
    omegas = np.logspace(-2, 3, 41 if quick else 201)
    # zero-weight points give the same step: one compilation for every rule
    methods = {label: gj.DG(1, gj.pad_rule(rule, 3)) for label, rule in SPECTRAL_RULES.items()}
    fig, (ax,) = _figure()
    plot.spectral_radius(methods, omegas, ax=ax)
    ax.set_title("[GBS, Fig. 4.3] dG(1), symmetric quadrature rules")
    return _save(fig, path)


# ---------------------------------------------------------------- [Tang]


# steps per period for each s: in the asymptotic range and above the 1e-12 Newton floor
ORDER_STEPS = {1: (256, 512, 1024), 2: (128, 256, 512), 3: (64, 96, 128, 192), 4: (48, 64, 96, 128)}


def tang_order(quick):
    """Errors of GalerkinVI(s), s + 2 Gauss points, on Kepler (e = 0.5) at t = 2 pi against
    the exact orbit, s = 1..4 (``quick``: 1, 2): ``{label: (hs, errors)}``; the slope is 2s
    [Tang, Section 2]."""
    period = 2 * np.pi
    q_exact, p_exact = KEPLER.exact(period)
    errors = {}
    for s in (1, 2) if quick else (1, 2, 3, 4):
        ns = np.asarray(ORDER_STEPS[s])
        method = gj.GalerkinVI(s, gj.gauss_legendre(s + 2))
        # one run per h, vmapped (one compilation); the run of n steps is read at its step n
        sol = jax.vmap(lambda h: gj.integrate(KEPLER.H, KEPLER.q0, KEPLER.p0, method=method, h=h,
                                              n_steps=int(ns.max())))(jnp.asarray(period / ns))
        q, p = np.asarray(sol.q)[np.arange(len(ns)), ns], np.asarray(sol.p)[np.arange(len(ns)), ns]
        errors[f"GalerkinVI({s})"] = (period / ns, np.maximum(np.abs(q - q_exact).max(1), np.abs(p - p_exact).max(1)))
    return errors


def symplecticity_defect(A):
    """max |A^T J A - J| of a one-step Jacobian A, z = (q, p) [Tang, Corollary 2.1]."""
    A = np.asarray(A)
    d = A.shape[-1] // 2
    J = np.block([[np.zeros((d, d)), np.eye(d)], [-np.eye(d), np.zeros((d, d))]])
    return np.abs(np.swapaxes(A, -1, -2) @ J @ A - J).max(axis=(-2, -1))


@functools.partial(jax.jit, static_argnums=0)
def _step_jacobians(H, method, q0, p0, hs):
    return jax.vmap(lambda h: gj.amplification_matrix(H, q0, p0, method=method, h=h))(hs)


SYMPLECTICITY_METHODS = {
    "GalerkinVI(2), Gauss 3": gj.GalerkinVI(2, gj.gauss_legendre(3)),
    "GalerkinVI(2), Lobatto 3": gj.GalerkinVI(2, gj.gauss_lobatto(3)),
    "cG(2), Gauss 5": gj.CG(2, gj.gauss_legendre(5)),
    "dG(1), Gauss 2": gj.DG(1, gj.gauss_legendre(2)),
}


def tang_symplecticity(quick):
    """max |A^T J A - J| of one Kepler step (e = 0.5, from perihelion) against h:
    ``(hs, {label: defects})``. Round-off for GalerkinVI; not for cG(2) with 5 Gauss points
    (energy-conserving, Theorem 3.1 of [GBS]) nor dG(1). ``quick``: 4 step sizes, no cG(2)."""
    hs = np.logspace(-2, -0.5, 4 if quick else 10)
    q0, p0 = jnp.asarray(KEPLER.q0), jnp.asarray(KEPLER.p0)
    methods = {k: m for k, m in SYMPLECTICITY_METHODS.items() if not (quick and k.startswith("cG"))}
    return hs, {label: symplecticity_defect(_step_jacobians(KEPLER.H, method, q0, p0, jnp.asarray(hs)))
                for label, method in methods.items()}


# [Tang, Section 3]: L = qdot^T M qdot / 2 - U(q) with a non-diagonal SPD M, and its H.
M_TANG = np.array([[2.0, 0.5], [0.5, 1.0]])


def _potential(q):
    return 0.5 * q @ q + 0.25 * q[0] ** 4 + 0.1 * q[0] * q[1] ** 2


def lagrangian_quadratic(q, qdot):
    return 0.5 * qdot @ jnp.asarray(M_TANG) @ qdot - _potential(q)


def hamiltonian_quadratic(q, p):
    return 0.5 * p @ jnp.linalg.solve(jnp.asarray(M_TANG), p) + _potential(q)


def tang_equivalence(quick):
    """max_i |(q, p)_n of LagrangianVI(s) - of GalerkinVI(s)| against t_n, s + 1 Gauss points,
    h = 0.05, s = 1, 2, 3 (``quick``: s = 2, 100 steps instead of 1000): ``(t, {label: differences})``;
    round-off if the two are one scheme [Tang, Section 3]."""
    q0, p0 = np.array([1.0, 0.2]), np.array([0.1, 0.8])
    n_steps = 100 if quick else 1000
    differences = {}
    for s in (2,) if quick else (1, 2, 3):
        rule = gj.gauss_legendre(s + 1)
        a = gj.integrate(hamiltonian_quadratic, q0, p0, method=gj.GalerkinVI(s, rule), h=0.05, n_steps=n_steps)
        b = gj.integrate(lagrangian_quadratic, q0, p0, method=gj.LagrangianVI(s, rule), h=0.05, n_steps=n_steps)
        differences[f"s = {s}"] = np.maximum(np.abs(np.asarray(a.q - b.q)).max(1), np.abs(np.asarray(a.p - b.p)).max(1))
    return np.asarray(a.t), differences


def tang_figures(folder, quick):
    """The three [Tang] figures; returns ``(paths, numbers)``."""
    paths, numbers = {}, {}
    errors = tang_order(quick)
    fig, (ax,) = _figure()
    for label, (hs, e) in errors.items():
        plot.convergence(hs, {label: e}, ax=ax, floor=1e-12)  # below: the Newton floor
    ax.set_ylabel(r"$\max |(q, p)_N - (q, p)(2\pi)|$")
    ax.set_title("[Tang] GalerkinVI(s) on Kepler (e = 0.5): order 2s")
    paths["tang_order"] = _save(fig, folder / "tang_order.png")
    numbers["tang_order"] = {label: plot.fitted_slope(hs, e, 1e-12) for label, (hs, e) in errors.items()}

    hs, defects = tang_symplecticity(quick)
    fig, (ax,) = _figure()
    plot.convergence(hs, defects, ax=ax, floor=1e-13)  # below: round-off
    ax.set_ylabel(r"$\max |A^T J A - J|$")
    ax.set_title("[Tang] symplecticity defect of one Kepler step")
    paths["tang_symplecticity"] = _save(fig, folder / "tang_symplecticity.png")
    numbers["tang_symplecticity"] = {label: float(d.max()) for label, d in defects.items()}

    t, differences = tang_equivalence(quick)
    fig, (ax,) = _figure()
    for label, diff in differences.items():
        plot.time_series(t, diff, ax=ax, label=label, log=True, ylabel=r"$\max |(q, p)^{L} - (q, p)^{G}|$")
    ax.set_title(r"[Tang] LagrangianVI = GalerkinVI for $L = \dot q^T M \dot q / 2 - U(q)$")
    paths["tang_equivalence"] = _save(fig, folder / "tang_equivalence.png")
    numbers["tang_equivalence"] = {label: float(d.max()) for label, d in differences.items()}
    return paths, numbers


# ---------------------------------------------------------------- everything


def reproduce(folder, *, quick=False):
    """Write [GBS] Table 5.1 (``table51.md``), [GBS] Figs. 4.1-4.7 and the [Tang] figures
    (PNG) into ``folder`` (created if missing).

    Args:
        folder: a directory path.
        quick: fewer methods, step sizes and samples in the [Tang] figures and Fig. 4.3 (the
            same code, about half the compilations); Table 5.1 is measured in full either way.
    Returns:
        ``{"folder": str, "files": {name: path}, "table51": Table51, "numbers": {...}}``,
        ``numbers`` holding the fitted GalerkinVI orders, the largest symplecticity defects
        and the largest LagrangianVI - GalerkinVI differences.
    """
    if not isinstance(quick, bool):
        raise TypeError(f"quick must be True or False, got {quick!r}.")
    try:
        folder = pathlib.Path(folder)
    except TypeError as error:
        raise TypeError(f"folder must be a path, got {type(folder).__name__}.") from error
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"folder {str(folder)!r} exists and is not a directory.")
    folder.mkdir(parents=True, exist_ok=True)
    with jax.enable_x64(True):
        runs = table_runs()
        table = table51(runs)
        files = {"table51": str(folder / "table51.md")}
        (folder / "table51.md").write_text("# [GBS] Table 5.1, measured\n\n" + table.markdown())
        for number in GBS_FIGURES:
            files[f"fig{number.replace('.', '_')}"] = gbs_history_figure(runs, folder, number)
        files["fig4_3"] = gbs_spectral_radius_figure(folder / "fig4_3_spectral_radius.png", quick)
        tang_paths, numbers = tang_figures(folder, quick)
    files.update(tang_paths)
    return {"folder": str(folder), "files": dict(sorted(files.items())), "table51": table, "numbers": numbers}
