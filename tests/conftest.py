import importlib
import pkgutil

import numpy as np
import pytest
from jaxtyping import install_import_hook

# Every function of the package is checked against its annotations (jaxtyping shapes and dtypes through
# beartype) while the suite runs: the hook must be in place when each module is imported. The package
# imports its modules lazily, so every one of them is imported here, under the hook (not `__main__`, which
# runs the command line).
with install_import_hook("jaxstereo", "typecheck.checker"):
    import jaxstereo

    for module in pkgutil.walk_packages(jaxstereo.__path__, "jaxstereo."):
        if not module.name.endswith("__main__"):
            importlib.import_module(module.name)

# No global `jax_enable_x64` here: the library runs its geometry in float64 by construction, so the suite
# exercises what a user gets with JAX's default settings (`tests/geometry/test_precision.py` checks it).


@pytest.fixture(scope="session", autouse=True)
def command_caches(tmp_path_factory):
    """The command line's disk caches (compiled programs, rig tables, match plans) in a folder of this run's, not
    the user's ~/.cache: the suite starts cold, as on a fresh machine, and leaves nothing behind. The commands the
    tests run, in this process or in a child, share it (a test may set its own)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("JAXSTEREO_CACHE_DIR", str(tmp_path_factory.mktemp("command-caches")))
        yield


@pytest.fixture
def rng():
    return np.random.default_rng(20261121)


@pytest.fixture
def x64():
    """64-bit JAX types for one test, as a user who transforms the geometry kernels (jit, grad, vmap) or does
    float64 arithmetic on JAX arrays must enable them; the library's own calls need no such thing."""
    import jax

    with jax.enable_x64(True):
        yield


@pytest.fixture
def unchecked():
    """The package without the suite's type checker, as users run it: for tests of the library's own
    messages on bad input, which the checker would otherwise pre-empt with its own."""
    import jaxtyping

    jaxtyping.config.update("jaxtyping_disable", True)
    try:
        yield
    finally:
        jaxtyping.config.update("jaxtyping_disable", False)
