"""What the command line tool writes: trajectories (NPZ, CSV), PNG plots and sweep tables."""

import csv
import os
import re

import numpy as np


def relative_change(values, initial):
    """max_i |I_n - I_0|_i / max_i |I_0|_i per saved state (absolute where I_0 = 0), NaN after a failure.

    Args:
        values: shape ``(m,)`` or ``(m, ...)``; ``initial``: the first entry.
    Returns:
        shape ``(m,)``.
    """
    values = np.asarray(values, dtype=float).reshape(len(values), -1)
    scale = np.max(np.abs(np.asarray(initial, dtype=float)))
    return np.max(np.abs(values - values[0]), axis=1) / (scale if scale > 0 else 1.0)


def size_text(path):
    """The file size in words, e.g. ``48.2 kB``."""
    size = os.path.getsize(path)
    return f"{size} B" if size < 1000 else f"{size / 1000:.1f} kB" if size < 10**6 else f"{size / 10**6:.1f} MB"


def write_trajectory(path, columns, meta):
    """Write the saved states: NPZ (``path`` ends in .npz) or CSV (``# name: value`` lines,
    a header line, then one row per saved state: ``pandas.read_csv(path, comment="#")``).

    Args:
        columns: name -> array with a leading axis m (``t``, ``q``, ``p``, ``energy``, ...).
        meta: name -> str or number (scene, method, h, status...), NPZ entries or CSV comments.
    Returns:
        ``path``.
    """
    if path.endswith(".npz"):
        np.savez(path, **columns, **{k: np.asarray(v) for k, v in meta.items()})
        return path
    names, blocks = [], []
    for name, value in columns.items():
        value = np.asarray(value).reshape(len(value), -1)
        names += [name] if value.shape[1] == 1 else [f"{name}_{i}" for i in range(value.shape[1])]
        blocks.append(value.astype(float))
    with open(path, "w") as f:
        f.write("".join(f"# {k}: {v}\n" for k, v in meta.items()) + ",".join(names) + "\n")
        np.savetxt(f, np.concatenate(blocks, axis=1), delimiter=",", fmt="%.17g")
    return path


def _figure(width=7.0, height=4.0, ncols=1):
    import matplotlib.pyplot as plt

    return plt.subplots(1, ncols, figsize=(width, height), constrained_layout=True)


def _save(fig, path):
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def parse_coordinate(text):
    """``"q0"``, ``"q_0"`` or ``"p12"`` -> ``("q", 0)`` ...; None if ``text`` names no coordinate."""
    match = re.fullmatch(r"\s*([qp])_?(\d+)\s*", text.lower())
    return None if match is None else (match.group(1), int(match.group(2)))


def choose_view(shape, q, pair=None):
    """What the run's second plot draws: ``("pair", (x, y))`` for the coordinates the user
    named (``--plot q0,q1``); else ``("bodies", (N, D))`` for states of shape (N, 2) or (N, 3),
    or flat states of d = 2 or 3 (one body); else ``("phase", i)``, q_i against p_i for the
    coordinate that varies most over the run.

    Args:
        shape: the scene's state shape, e.g. ``(3, 2)`` or ``(d,)``.
        q: the saved positions, shape ``(m, d)`` or ``(m, *shape)``.
    """
    if pair is not None:
        return "pair", tuple(pair)
    if len(shape) == 2 and shape[1] in (2, 3):
        return "bodies", tuple(shape)
    if len(shape) == 1 and shape[0] in (2, 3):
        return "bodies", (1, shape[0])
    q = np.asarray(q, dtype=float).reshape(len(q), -1)
    spread = np.nan_to_num(np.nanmax(q, axis=0) - np.nanmin(q, axis=0), nan=-1.0) if np.isfinite(q).any() else [0]
    return "phase", int(np.argmax(spread))


def plot_run(stem, solution, H, args, invariants, title, view, center=None):
    """The energy (and invariant) error against time, and the second plot ``view``
    (``choose_view``): the bodies' paths (``plot.bodies``, the central body marked), the
    named coordinates (``plot.coordinates``) or a phase portrait (``plot.phase_portrait``).

    Returns:
        the two PNG paths.
    """
    from . import plot

    fig, ax = _figure()
    plot.energy_error(solution, H, args=args, ax=ax, label="H")
    for name, invariant in invariants.items():
        plot.invariant_error(solution, invariant, name=name, ax=ax, label=name)
    ax.set_ylabel("relative change |I(t) - I(0)| / |I(0)|")
    ax.set_title(f"energy H and invariants: {title}", fontsize=9)
    ax.legend()
    energy_png = _save(fig, f"{stem}_energy.png")
    fig, ax = _figure(5.0, 5.0)
    kind, value = view
    if kind == "bodies":
        plot.bodies(solution, shape=value, center=center, ax=ax)
        suffix = "orbit" if value[0] == 1 else "bodies"
    elif kind == "pair":
        plot.coordinates(solution, *value, ax=ax)
        suffix = "".join(f"{part}{index}" for part, index in value)
    else:
        plot.phase_portrait(solution, index=value, ax=ax)
        ax.set_xlabel(f"$q_{{{value}}}$ (the coordinate that varies most)")
        ax.set_ylabel(f"$p_{{{value}}}$")
        suffix = "phase"
    ax.set_title(title, fontsize=9)
    return [energy_png, _save(fig, f"{stem}_{suffix}.png")]


def markdown(header, rows, formats=None):
    """A markdown table; floats in ``formats[column]`` (default ``.2e``), NaN as ``-``."""
    formats = formats or {}
    cells = [[_cell(v, formats.get(name, ".2e")) for name, v in zip(header, row)] for row in rows]
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join("---" for _ in header) + " |"]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in cells])


def _cell(value, spec):
    if isinstance(value, float):
        return "-" if np.isnan(value) else format(value, spec)
    return str(value)


def write_table(stem, header, rows, notes="", formats=None):
    """``stem.md`` (the markdown table and ``notes``) and ``stem.csv``; returns both paths."""
    with open(f"{stem}.md", "w") as f:
        f.write(markdown(header, rows, formats) + "\n" + (f"\n{notes}\n" if notes else ""))
    with open(f"{stem}.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows([[repr(v) if isinstance(v, float) else v for v in row] for row in rows])
    return [f"{stem}.md", f"{stem}.csv"]


def plot_sweep(stem, energy, final, methods, hs, title, floor):
    """The energy error over method x h as a heat map (``plot.sweep_map``), and the errors
    against h with their fitted slopes (``plot.convergence``): energy, and the final error.

    Args:
        energy, final: shape ``(len(methods), len(hs))``; ``final`` may be None.
        floor: errors below it (round-off) are left out of the slopes.
    Returns:
        the PNG paths.
    """
    from . import plot

    fig, ax = _figure(2.5 + 1.1 * len(hs), 1.5 + 0.45 * len(methods))
    plot.sweep_map(energy, methods, [f"h = {h:g}" for h in hs], ax=ax, title=f"max relative energy error: {title}")
    ax.title.set_fontsize(9)
    paths = [_save(fig, f"{stem}_energy_map.png")]
    panels = [("max relative energy error", energy)]
    if final is not None:
        panels.append(("error at t = n_steps h (n_steps fixed: order p gives slope p + 1)", final))
    fig, axes = _figure(6.0 * len(panels), 4.5, len(panels))
    for ax, (name, errors) in zip(np.atleast_1d(axes), panels):
        plot.convergence(hs, dict(zip(methods, errors)), ax=ax, floor=floor)
        ax.set_title(f"{name}\n{title}", fontsize=9)
        ax.legend(fontsize=7)
    return paths + [_save(fig, f"{stem}_error_vs_h.png")]
