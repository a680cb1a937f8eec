"""A progress bar driven from inside the compiled scan.

``report(done, total, stride)`` is traced into the element loop: every ``stride`` elements a
``jax.debug.callback`` hands the count to the host, which draws a tqdm bar (the ``progress``
extra) or, without tqdm, a line on stderr every tenth. The count is not batched (it depends
on nothing a vmap maps over), so a vmapped run or a sweep reports once per element, not
once per member. The bar is created by the first tick and closed by the last, so it works
however the call is wrapped (jit, vmap); a count that goes backwards starts a new bar.
"""

import sys

import jax

_bar = None


class _Lines:
    """The fallback without tqdm: one line on stderr per tenth of the run."""

    def __init__(self, total):
        self.total, self.n, self._tenth = total, 0, -1

    def update(self, count):
        self.n += count
        tenth = 10 * self.n // self.total
        if tenth > self._tenth:
            self._tenth = tenth
            print(f"galerkin_jax: {self.n} of {self.total} elements ({10 * tenth} %)", file=sys.stderr, flush=True)

    def close(self):
        pass


def _new_bar(total):
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return _Lines(total)
    return tqdm(total=total, unit="element", desc="galerkin_jax", unit_scale=True, leave=False)


def _update(done, total):
    global _bar
    done, total = int(done), int(total)
    if _bar is None or _bar.total != total or done < _bar.n:
        if _bar is not None:
            _bar.close()
        _bar = _new_bar(total)
    _bar.update(done - _bar.n)
    if done >= total:
        _bar.close()
        _bar = None


def report(done, total, stride):
    """Tick the bar when ``done`` (elements finished, traced int) is a multiple of ``stride``
    or the last; ``total`` and ``stride`` are static ints."""
    jax.lax.cond((done % stride == 0) | (done == total),
                 lambda: jax.debug.callback(_update, done, total), lambda: None)


def stride(total):
    """Elements between ticks: 50 ticks per run, enough to watch, few enough that the compiled
    loop does not wait on the host."""
    return max(1, total // 50)
