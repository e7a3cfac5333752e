"""Errors raised by jaxstereo for bad input (never from deep inside JAX).

Imports no JAX at import time: the command line imports this module first and starts reading its images
while JAX loads (about a second).
"""

from __future__ import annotations

import numpy as np


class JaxStereoError(ValueError):
    """Bad input to a jaxstereo function: the message names the parameter or file and what is wrong."""


def is_concrete(*values) -> bool:
    """True when no leaf of `values` is a JAX tracer (so its numbers can be checked in Python)."""
    import jax

    leaves = jax.tree_util.tree_leaves(values)
    return not any(isinstance(leaf, jax.core.Tracer) for leaf in leaves)


def check_shape(name: str, array, trailing: tuple[int, ...]) -> None:
    """Raise `JaxStereoError` unless `array` has shape `(..., *trailing)` with at least one batch axis.

    **Arguments:**

    - `name`: the parameter's name, used in the message.
    - `array`: the array to check.
    - `trailing`: the required trailing shape, e.g. `(3,)` for points.
    """
    shape = tuple(np.shape(array))
    n = len(trailing)
    if len(shape) < n + 1 or shape[len(shape) - n :] != trailing:
        want = "(N, " + ", ".join(str(d) for d in trailing) + ")"
        raise JaxStereoError(f"{name} must have shape {want}, got {shape}")
