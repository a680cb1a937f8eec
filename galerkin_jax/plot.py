"""matplotlib helpers for runs and for method properties.

``import galerkin_jax`` does not import this module, and this module imports matplotlib
only inside its functions: ``from galerkin_jax import plot`` then ``plot.energy_error(...)``.
Every helper draws into ``ax`` (a new figure from ``plt.subplots()`` when ``ax`` is None),
labels the axes in the papers' notation and returns the Axes.

On logarithmic axes a zero (an exact invariant, a vanishing difference) is drawn at
``FLOOR = 1e-17``, below the float64 round-off of any O(1) quantity.
"""

import jax
import jax.numpy as jnp
import numpy as np

from ._integrate import amplification_matrix

FLOOR = 1e-17
_MAX_MARKED_NODES = 1000  # more node markers than this would hide the line


def _axes(ax):
    if ax is None:
        import matplotlib.pyplot as plt

        _, ax = plt.subplots()
    return ax


def _one_run(solution):
    """``(t, q, p)`` of one run as NumPy arrays, q and p of shape ``(m, ...)`` (flat ``(m, d)``
    or e.g. ``(m, N, 3)``); a batched (sweep) solution is refused."""
    for name in ("t", "q", "p"):
        if not hasattr(solution, name):
            raise TypeError(f"solution must have fields t, q, p (a gj.Solution), got {type(solution).__name__}.")
    t, q, p = (np.asarray(x) for x in (solution.t, solution.q, solution.p))
    if t.ndim != 1 or q.ndim < 2 or q.shape != p.shape or q.shape[0] != t.shape[0]:
        raise ValueError(
            f"solution: one run expected (t of shape (m,), q and p of shape (m, d)), got t {t.shape}, "
            f"q {q.shape}; index a batched solution first."
        )
    return t, q, p


def _flat(x):
    return x.reshape(x.shape[0], -1)


def _values(fn, q, p):
    """``fn(q_n, p_n)`` for every saved state, shape ``(m, n_components)``."""
    values = np.asarray(jax.vmap(fn)(jnp.asarray(q), jnp.asarray(p)))
    return values.reshape(values.shape[0], -1)


def _change(values, relative):
    """max_i |I_n,i - I_0,i| (divided by max_i |I_0,i| if ``relative`` and that is not 0)."""
    change = np.max(np.abs(values - values[0]), axis=1)
    scale = np.max(np.abs(values[0]))
    return change / scale if relative and scale > 0 else change


def time_series(t, values, *, ax=None, label=None, ylabel=None, log=False):
    """Any quantity against time, e.g. H(t) as in [GBS, Figs. 4.1-4.7].

    Args:
        t: shape ``(m,)``.
        values: shape ``(m,)``.
        ylabel: the y-axis label.
        log: logarithmic y-axis; zeros are drawn at ``FLOOR`` (1e-17).
    Returns:
        the Axes.
    """
    ax = _axes(ax)
    t, values = np.asarray(t, float), np.asarray(values, float)
    if t.shape != values.shape or t.ndim != 1:
        raise ValueError(f"t and values must have the same shape (m,), got {t.shape} and {values.shape}.")
    if log:
        values = np.maximum(values, FLOOR)  # NaN (a failed run) stays NaN and is not drawn
        ax.set_yscale("log")
    ax.plot(t, values, label=label)
    ax.set_xlabel("$t$")
    if ylabel is not None:
        ax.set_ylabel(ylabel)
    if label is not None:
        ax.legend()
    return ax


def energy_error(solution, H, *, args=None, relative=True, ax=None, label=None):
    """|H(q_n, p_n) - H_0| (divided by |H_0| if ``relative``) against ``solution.t``, log y-axis.

    Exact conservation (a zero) is drawn at ``FLOOR`` = 1e-17 so that the log scale works.

    Args:
        solution: one run (``gj.Solution``: t of shape ``(m,)``, q and p of shape ``(m, d)``).
        H: ``H(q, p)``, or ``H(q, p, args)`` with ``args`` given.
        relative: divide by |H_0| (unless H_0 = 0).
    Returns:
        the Axes.
    """
    t, q, p = _one_run(solution)
    fn = H if args is None else (lambda q, p: H(q, p, args))
    ylabel = "$|H_n - H_0| / |H_0|$" if relative else "$|H_n - H_0|$"
    return time_series(t, _change(_values(fn, q, p), relative), ax=ax, label=label, ylabel=ylabel, log=True)


def invariant_error(solution, invariant, *, name="L", relative=True, ax=None, label=None):
    """|I(q_n, p_n) - I_0| (relative to |I_0|) against ``solution.t``, log y-axis, zeros at 1e-17.

    A vector invariant (e.g. L = q x p, eq. (73) of [GBS]) is measured by the largest
    component change, relative to the largest component of I_0.

    Args:
        solution: one run, as in ``energy_error``.
        invariant: ``I(q, p)``, a scalar or a vector.
        name: its symbol on the y-axis.
    Returns:
        the Axes.
    """
    t, q, p = _one_run(solution)
    I = f"{{{name}}}"  # braces: a name with a subscript (L_\zeta) takes _n too
    ylabel = f"$|{I}_n - {I}_0| / |{I}_0|$" if relative else f"$|{I}_n - {I}_0|$"
    return time_series(t, _change(_values(invariant, q, p), relative), ax=ax, label=label, ylabel=ylabel, log=True)


def _sampled_states(solution, samples_per_step):
    """``(q, p, markevery)``: with dense output (``getattr(solution, "dense", None) is not
    None``) every element's polynomial sampled ``samples_per_step`` times (evenly in time, as
    many samples as elements times ``samples_per_step``), else the saved states; ``markevery``
    puts the markers on the saved states."""
    t, q, p = _one_run(solution)
    if getattr(solution, "dense", None) is None:
        return q, p, 1
    n = samples_per_step
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"samples_per_step must be an integer >= 1, got {samples_per_step!r}.")
    elements = int(np.sum(np.isfinite(np.asarray(solution.dense.t)))) - 1  # a controller's buffers: inf past the end
    per_save = max(1, elements // max(len(t) - 1, 1))
    intervals = (len(t) - 1) * per_save * samples_per_step
    fine = np.linspace(t[0], t[-1], intervals + 1)
    q, p = solution.evaluate(jnp.asarray(fine, dtype=jnp.asarray(solution.t).dtype))
    return np.asarray(q), np.asarray(p), per_save * samples_per_step


def _trajectory(ax, x, y, markevery, label):
    nodes = (len(x) - 1) // markevery + 1
    marker = "." if nodes <= _MAX_MARKED_NODES else None
    ax.plot(x, y, marker=marker, markevery=markevery, markersize=4, label=label)
    if label is not None:
        ax.legend()


def orbit(solution, *, dims=(0, 1), ax=None, label=None, samples_per_step=8):
    """The configuration-space orbit, q[dims[0]] (x-axis) against q[dims[1]] (y-axis).

    With dense output (``integrate(..., dense=True)``; detected by
    ``getattr(solution, "dense", None) is not None``) the element polynomials are drawn,
    each sampled ``samples_per_step`` times (``solution.evaluate``); otherwise straight lines
    join the saved states. Markers sit on the saved states.

    Returns:
        the Axes (equal aspect ratio).
    """
    ax = _axes(ax)
    q, _, markevery = _sampled_states(solution, samples_per_step)
    q = _flat(q)
    i, j = dims
    if not (0 <= i < q.shape[1] and 0 <= j < q.shape[1]):
        raise ValueError(f"dims must index q of dimension {q.shape[1]}, got {dims}.")
    _trajectory(ax, q[:, i], q[:, j], markevery, label)
    ax.set_xlabel(f"$q_{{{i + 1}}}$")
    ax.set_ylabel(f"$q_{{{j + 1}}}$")
    ax.set_aspect("equal", adjustable="datalim")
    return ax


def phase_portrait(solution, *, index=0, ax=None, label=None, samples_per_step=8):
    """q_i (x-axis) against p_i (y-axis); dense output as in ``orbit``.

    Returns:
        the Axes.
    """
    ax = _axes(ax)
    q, p, markevery = _sampled_states(solution, samples_per_step)
    q, p = _flat(q), _flat(p)
    if not 0 <= index < q.shape[1]:
        raise ValueError(f"index must be in [0, {q.shape[1]}), got {index}.")
    _trajectory(ax, q[:, index], p[:, index], markevery, label)
    ax.set_xlabel(f"$q_{{{index + 1}}}$")
    ax.set_ylabel(f"$p_{{{index + 1}}}$")
    return ax


def coordinates(solution, x, y, *, ax=None, label=None, samples_per_step=8):
    """Any two coordinates of the flat state against each other, e.g. ``x=("q", 0)``,
    ``y=("p", 2)`` (0-based, as the columns ``q_0``, ``p_2`` of the command line's CSV);
    dense output as in ``orbit``.

    Returns:
        the Axes.
    """
    ax = _axes(ax)
    q, p, markevery = _sampled_states(solution, samples_per_step)
    states = {"q": _flat(q), "p": _flat(p)}
    columns = []
    for part, index in (x, y):
        if part not in states or not 0 <= index < states[part].shape[1]:
            raise ValueError(f"x and y must be ('q' or 'p', index < {q.shape[1]}), got {x} and {y}.")
        columns.append(states[part][:, index])
    _trajectory(ax, *columns, markevery, label)
    ax.set_xlabel(f"${x[0]}_{{{x[1]}}}$")
    ax.set_ylabel(f"${y[0]}_{{{y[1]}}}$")
    return ax


_AXES = "xyz"
_MAX_LABELLED_BODIES = 10  # a legend of more bodies would hide the paths


def plane(q):
    """The two coordinates (of D) in which the bodies' positions ``q`` ``(m, N, D)`` spread the
    most (largest range over the run), in increasing order: the plane to draw their paths in."""
    q = np.asarray(q, dtype=float)
    if q.shape[-1] <= 2:
        return 0, 1
    spread = np.nanmax(q, axis=(0, 1)) - np.nanmin(q, axis=(0, 1))
    return tuple(sorted(int(i) for i in np.argsort(-np.nan_to_num(spread, nan=-1.0), kind="stable")[:2]))


def bodies(solution, *, shape=None, dims=None, center=None, ax=None, samples_per_step=8):
    """The paths of N bodies in a plane: each body's position ``q[n]`` in D = 2 or 3 dimensions.

    Args:
        solution: one run (``gj.Solution``, with dense output drawn as in ``orbit``) or the
            positions alone, an array ``q``. Either of shape ``(m, N, D)``, or flat ``(m, N * D)``
            with ``shape=(N, D)``: body n's coordinates are ``q[:, n * D : (n + 1) * D]``.
        shape: ``(N, D)`` for a flat q; None (or the same) for q of shape ``(m, N, D)``.
        dims: the two coordinates drawn (x-axis, y-axis); default: the two of most spread
            (``plane``).
        center: the position of a fixed central body, length D, marked by a star; None: none.
    Returns:
        the Axes (equal aspect ratio): a line per body, a dot at its start, a legend of the
        bodies (up to 10).
    """
    ax = _axes(ax)
    if hasattr(solution, "q"):
        q, _, _ = _sampled_states(solution, samples_per_step)
    else:
        q = np.asarray(solution, dtype=float)
    if shape is not None and q.shape[1:] != tuple(shape):
        shape = tuple(int(n) for n in shape)
        if len(shape) != 2 or q.ndim != 2 or q.shape[1] != shape[0] * shape[1]:
            raise ValueError(f"shape (N, D) must split q of shape (m, d) into d = N * D, got shape {shape} "
                             f"for q of shape {q.shape}.")
        q = q.reshape(q.shape[0], *shape)
    if q.ndim != 3 or q.shape[2] not in (2, 3):
        raise ValueError(f"q must have shape (m, N, D) with D = 2 or 3 (or flat with shape=(N, D)), got {q.shape}.")
    n_bodies, D = q.shape[1:]
    i, j = plane(q) if dims is None else dims
    if not (0 <= i < D and 0 <= j < D and i != j):
        raise ValueError(f"dims must be two different coordinates of D = {D}, got {dims}.")
    labelled = n_bodies <= _MAX_LABELLED_BODIES
    for n in range(n_bodies):
        (line,) = ax.plot(q[:, n, i], q[:, n, j], lw=1.0, label=f"body {n + 1}" if labelled and n_bodies > 1 else None)
        ax.plot(q[:1, n, i], q[:1, n, j], "o", color=line.get_color(), markersize=4)
    if center is not None:
        center = np.asarray(center, dtype=float)
        if center.shape != (D,):
            raise ValueError(f"center must have shape ({D},), got {center.shape}.")
        ax.plot([center[i]], [center[j]], "*", color="black", markersize=12, label="central body")
    ax.set_xlabel(f"${_AXES[i]}$")
    ax.set_ylabel(f"${_AXES[j]}$")
    ax.set_aspect("equal", adjustable="datalim")
    if ax.get_legend_handles_labels()[1]:
        ax.legend(fontsize=7)
    return ax


def _unit_oscillator(q, p):
    return 0.5 * (p @ p + q @ q)  # omega = 1, so h = Omega


@jax.jit
def _amplification_matrices(method, hs):
    one = jnp.ones(1, hs.dtype)
    return jax.vmap(lambda h: amplification_matrix(_unit_oscillator, one, 0 * one, method=method, h=h))(hs)


def spectral_radii(method, omegas):
    """rho(A(Omega)) for H = p^2/2 + q^2/2 and h = Omega [GBS, eqs. (48)-(49)]; shape of ``omegas``.

    One compilation per method kind, degree and point count (``omegas`` is traced).
    """
    omegas = np.asarray(omegas, dtype=float)
    if omegas.ndim != 1 or not np.all(omegas > 0):
        raise ValueError(f"omegas must be a 1-D array of positive sampling frequencies, got {omegas}.")
    A = np.asarray(_amplification_matrices(method, jnp.asarray(omegas)))
    return np.abs(np.linalg.eigvals(A)).max(axis=-1)


def spectral_radius(methods, omegas, *, ax=None):
    """The spectral radius of the amplification matrix against Omega = h omega [GBS, Fig. 4.3].

    Args:
        methods: label -> method (e.g. ``gj.DG(1, gj.trapezoid())``).
        omegas: 1-D array of sampling frequencies Omega > 0 (log x-axis).
    Returns:
        the Axes.
    """
    ax = _axes(ax)
    for label, method in methods.items():
        ax.semilogx(np.asarray(omegas, float), spectral_radii(method, omegas), label=label)
    ax.set_xlabel(r"$\Omega = h\,\omega$")
    ax.set_ylabel(r"$\rho(\mathbf{A})$")
    ax.legend()
    return ax


def fitted_slope(hs, errors, floor=None):
    """Least-squares slope of log(error) against log(h) over the finite errors above ``floor``
    (above 0 if None); None when fewer than two points qualify."""
    hs, errors = np.asarray(hs, float), np.asarray(errors, float)
    keep = np.isfinite(errors) & (errors > (0.0 if floor is None else floor))
    if keep.sum() < 2:
        return None
    return float(np.polyfit(np.log(hs[keep]), np.log(errors[keep]), 1)[0])


def convergence(hs, errors, *, ax=None, floor=None):
    """Error against step size, log-log, one line per method, the fitted slope in the legend.

    Args:
        hs: step sizes, shape ``(n,)``.
        errors: label -> sequence of n errors; the slope is fitted over the errors above
            ``floor`` (round-off would flatten it) and shown as "label (slope 2.00)".
    Returns:
        the Axes.
    """
    ax = _axes(ax)
    hs = np.asarray(hs, float)
    for label, errs in errors.items():
        errs = np.asarray(errs, float)
        if errs.shape != hs.shape:
            raise ValueError(f"errors[{label!r}] needs one error per h ({hs.shape}), got shape {errs.shape}.")
        slope = fitted_slope(hs, errs, floor)
        text = f"{label} (slope {slope:.2f})" if slope is not None else f"{label} (no slope above floor)"
        ax.loglog(hs, np.maximum(errs, FLOOR), marker="o", label=text)
    ax.set_xlabel("$h$")
    ax.set_ylabel("error")
    ax.legend()
    return ax


def work_precision(runs, *, ax=None):
    """Error against run time, log-log: one line per method.

    Args:
        runs: label -> (run_times in seconds, errors), two sequences of equal length.
    Returns:
        the Axes.
    """
    ax = _axes(ax)
    for label, (times, errs) in runs.items():
        times, errs = np.asarray(times, float), np.asarray(errs, float)
        if times.shape != errs.shape:
            raise ValueError(f"runs[{label!r}]: run_times and errors differ in shape, {times.shape} and {errs.shape}.")
        ax.loglog(times, np.maximum(errs, FLOOR), marker="o", label=label)
    ax.set_xlabel("run time [s]")
    ax.set_ylabel("error")
    ax.legend()
    return ax


def _log_norm(values):
    """A LogNorm over the positive finite values (zeros shown at the lower end)."""
    from matplotlib.colors import LogNorm

    positive = values[np.isfinite(values) & (values > 0)]
    low = positive.min() if positive.size else FLOOR
    high = positive.max() if positive.size else 1.0
    return LogNorm(vmin=low, vmax=max(high, 10 * low))


def sweep_map(values, rows, columns, *, ax=None, title=None, log=True, colorbar=True):
    """A heat map of a 2-D array (e.g. energy error over rule x h), each cell's value printed.

    NaN cells (failed runs) are drawn in light grey and labelled "failed".

    Args:
        values: shape ``(len(rows), len(columns))``.
        rows, columns: tick labels.
        log: logarithmic colour scale (zeros at its lower end).
    Returns:
        the Axes.
    """
    import matplotlib

    ax = _axes(ax)
    values = np.asarray(values, dtype=float)
    if values.shape != (len(rows), len(columns)):
        raise ValueError(f"values must have shape (len(rows), len(columns)) = {(len(rows), len(columns))}, "
                         f"got {values.shape}.")
    norm = _log_norm(values) if log else matplotlib.colors.Normalize(np.nanmin(values), np.nanmax(values))
    shown = np.where(np.isnan(values) | (values > 0), values, norm.vmin) if log else values
    cmap = matplotlib.colormaps["viridis"].with_extremes(bad="lightgrey")
    image = ax.imshow(np.ma.masked_invalid(shown), cmap=cmap, norm=norm, aspect="auto")
    for (i, j), value in np.ndenumerate(values):
        if np.isnan(value):
            ax.text(j, i, "failed", ha="center", va="center", color="black", fontsize=8)
        else:
            dark = norm(shown[i, j]) < 0.5  # the low end of viridis is dark
            ax.text(j, i, f"{value:.1e}", ha="center", va="center", color="white" if dark else "black", fontsize=8)
    ax.set_xticks(range(len(columns)), [str(c) for c in columns])
    ax.set_yticks(range(len(rows)), [str(r) for r in rows])
    if title is not None:
        ax.set_title(title)
    if colorbar:
        ax.figure.colorbar(image, ax=ax)
    return ax
