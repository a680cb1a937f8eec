"""galerkin_jax's benchmarks: ``python -m benchmarks`` lists them, ``python -m benchmarks NAME``
runs ``benchmarks/bench_NAME.py`` (its own options after the name)."""
