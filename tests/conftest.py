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
