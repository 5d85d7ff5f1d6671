import gc
import os
import shutil
import tempfile

import jax
import jax.random as jr
import numpy as np
import pytest


# Inverters in tests (and the CLI and notebook processes they start) solve on a 64 x 64
# model grid, about half the time of the default 96 x 96 on Mid: the tests check the
# machinery; the accuracy of the default grid is `benchmarks/invert_accuracy.py`, plus one
# test here that unsets this (test_inversion.py, small twisted contact).
os.environ.setdefault("MOIREJAX_MODEL_GRID", "64")

# One persistent compilation cache for the whole run: the pytest process, its xdist workers
# and the CLI and notebook processes the tests start (all inherit the variable, set once by
# the first process to import this file). The demo, the workflow tests and the notebooks
# compile many of the same programs; each pays once. A cache of the user's own is kept.
_OWN_CACHE = None
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    _OWN_CACHE = os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="moirejax-test-jax-cache-")
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
# Every program, not only those that take a second to compile (JAX's default): a workflow
# compiles a few hundred small ones (the eager arithmetic of building an inverter, a
# calibration's set-up), which each test and process building the same objects would
# otherwise compile again.
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
jax.config.update(
    "jax_persistent_cache_min_compile_time_secs", float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"])
)
# The test workers read and write the same cache: a test module's programs are dropped at
# its end (`_release_compiled_programs`), and the next module that compiles the same
# inversion loads it instead of compiling it again. Workers were once kept out of it after
# aborts inside XLA that turned out to be the memory-map exhaustion that fixture prevents;
# with both, a full run's largest worker held 24,583 memory maps (the kernel allows 65,530).
# An entry read while another process is still writing it fails to decompress, and JAX
# then warns and compiles.

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_numpy_rank_promotion", "raise")


def pytest_unconfigure(config):
    if _OWN_CACHE is not None:
        shutil.rmtree(_OWN_CACHE, ignore_errors=True)


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_programs():
    """Drop every compiled program at the end of each test module.

    XLA's CPU backend maps each compiled program into memory in a few pieces, and a worker
    that runs half the suite compiles thousands of programs: without this its map count
    reaches the kernel's `vm.max_map_count` (65530 by default) near the end of the run, and
    the next compilation aborts the worker. Programs shared across modules are few, so the
    recompilation this costs is small.
    """
    yield
    jax.clear_caches()
    gc.collect()


@pytest.fixture
def getkey():
    """Return a function that hands out fresh PRNG keys, deterministic per test."""
    key = jr.PRNGKey(0)

    def _getkey():
        nonlocal key
        key, subkey = jr.split(key)
        return subkey

    return _getkey


@pytest.fixture
def float32():
    """Run the test in JAX's default single precision, as users' workflows do.

    The suite enables float64 for its finite-difference and identity checks; the end-to-end
    workflow tests check the product as it runs out of the box, which is also 1.4x faster.
    """
    with jax.enable_x64(False):
        yield


@pytest.fixture
def moire_bands_only(monkeypatch):
    """Invert on the moiré bands alone (`MOIREJAX_CARRIERS=0`, inherited by the processes a
    test starts), for end-to-end runs that check files, reports and plots rather than accuracy
    on frames of another renderer: each model evaluation costs about two thirds. The carriers'
    own tests, the peer frames and the inversion tests keep the default."""
    monkeypatch.setenv("MOIREJAX_CARRIERS", "0")


@pytest.fixture(scope="module")
def vision_device():
    """A Mid unit with a small camera (256², a 16 mm field) for vision-mode tests."""
    import moirejax as mj

    return mj.preset("mid", height=256, width=256)


@pytest.fixture(scope="module")
def see_through(vision_device):
    """Restoration of the vision unit's frames from four frames of its empty view."""
    import moirejax as mj
    from moirejax.live import SeeThrough

    reference = np.asarray(mj.empty_scene_reference(jr.PRNGKey(1), vision_device, frames=4))
    return SeeThrough(reference, black_level=float(vision_device.optics.offset))
