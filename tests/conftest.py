import jax
import numpy as np
import pytest

# Tests run in float64, like the library's pipeline functions; the library itself never flips this flag.
jax.config.update("jax_enable_x64", True)


@pytest.fixture
def rng():
    return np.random.default_rng(20261121)
