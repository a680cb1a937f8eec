"""JAX's persistent compilation cache, turned on for a user's process (``use_compilation_cache``)."""

import os

import jax

CACHE_VARIABLE = "GALERKIN_JAX_CACHE"


def compile_cache_folder(environ=os.environ):
    """The default folder of compiled programs: ``$GALERKIN_JAX_CACHE`` (set but empty: none),
    else ``$XDG_CACHE_HOME/galerkin_jax/xla`` or ``~/.cache/galerkin_jax/xla``."""
    if CACHE_VARIABLE in environ:
        return environ[CACHE_VARIABLE] or None
    base = environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "galerkin_jax", "xla")


def use_compilation_cache(folder=None):
    """Keep every program JAX compiles in ``folder`` (default ``compile_cache_folder()``), so
    that a later process with the same functions, shapes and options loads it instead of
    compiling it again. This sets two of JAX's global options for the whole process (importing
    the library sets none): ``jax_compilation_cache_dir`` and
    ``jax_persistent_cache_min_compile_time_secs`` = 0 (JAX's default caches only programs
    that took a second or more). A program differs where a static argument does: another
    ``H`` function object (a lambda defined anew in each process is the same program if its
    code and closure are), another method degree, ``n_steps`` or ``max_steps``.

    Args:
        folder: the folder of the compiled programs; default None, ``compile_cache_folder()``:
            ``$GALERKIN_JAX_CACHE``, else ``$XDG_CACHE_HOME/galerkin_jax/xla`` or
            ``~/.cache/galerkin_jax/xla``.

    Returns:
        the folder, or None where ``$GALERKIN_JAX_CACHE`` is set but empty (no cache).
    """
    folder = compile_cache_folder() if folder is None else os.fspath(folder)
    if folder:
        jax.config.update("jax_compilation_cache_dir", folder)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return folder
