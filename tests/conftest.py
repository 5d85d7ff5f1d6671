import os

import jax
import jax.random as jr
import pytest


# Inverters in tests (and the CLI and notebook processes they start) solve on a 64 x 64
# model grid, about half the time of the default 96 x 96 on Mid: the tests check the
# machinery; the accuracy of the default grid is `benchmarks/invert_accuracy.py`, plus one
# test here that unsets this (test_inversion.py, small twisted contact).
os.environ.setdefault("MOIREJAX_MODEL_GRID", "64")

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_numpy_rank_promotion", "raise")


@pytest.fixture
def getkey():
    """Return a function that hands out fresh PRNG keys, deterministic per test."""
    key = jr.PRNGKey(0)

    def _getkey():
        nonlocal key
        key, subkey = jr.split(key)
        return subkey

    return _getkey
