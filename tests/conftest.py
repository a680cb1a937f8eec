import jax
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")  # no silent broadcasting


@pytest.fixture(scope="module", autouse=True)
def _free_compiled_programs():
    """Drop JAX's compiled programs after each test module. XLA's CPU backend maps a few
    hundred memory regions per compiled program (measured ~400 for one integrate), so a
    worker that keeps a few hundred programs reaches the kernel's vm.max_map_count (65530 by
    default) and crashes inside the next compilation."""
    yield
    import gc

    jax.clear_caches()
    gc.collect()


@pytest.fixture(scope="session")
def reproduced(tmp_path_factory):
    """``reproduce.reproduce(folder, quick=True)``, computed once per test run: Table 5.1 and
    the figures are shared by ``test_reproduce.py`` and ``test_table51.py``. Under
    pytest-xdist the first worker to ask computes it and the others load its pickle (the
    workers' temporary folders share a parent that is new in every run; a lock orders them)."""
    import fcntl
    import os
    import pickle

    from galerkin_jax import reproduce

    if "PYTEST_XDIST_WORKER" not in os.environ:
        return reproduce.reproduce(tmp_path_factory.mktemp("reproduce"), quick=True)
    root = tmp_path_factory.getbasetemp().parent
    with open(root / "reproduce.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        cached = root / "reproduce.pickle"
        if cached.exists():
            return pickle.loads(cached.read_bytes())
        result = reproduce.reproduce(root / "reproduce", quick=True)
        cached.write_bytes(pickle.dumps(result))
        return result
