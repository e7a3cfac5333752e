"""The float64 policy: geometry runs in float64 by construction, enabled locally, never by a global flag.

JAX computes in float32 unless 64-bit types are enabled, and an operation outside that mode silently
turns float64 arrays into float32 (7e-5 px of error in the exact projection). So every public geometry
function and method, and every user-facing pipeline function, is decorated with `float64`: called
directly, it runs with 64-bit types enabled whatever the global setting, its float inputs are promoted to
float64 and its outputs are float64. Traced inside a caller's own `jax.jit`/`grad` with 64-bit types
disabled, it refuses with a clear error instead of computing in float32. `as_float64` is what the geometry
types' `__init__`s (`Pose`, `Camera`, `Interface`) apply to their fields, so that they hold float64.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from .errors import JaxStereoError


def float64(fn: Callable) -> Callable:
    """Decorate `fn` so that it runs with 64-bit JAX types enabled, whatever the global setting.

    Already inside 64-bit mode (the global flag, or an enclosing decorated call), `fn` runs as is: the
    decorator costs one flag read. Outside it, `fn` runs under `jax.enable_x64(True)`; if any argument is
    a tracer (a caller's transformation traced in float32), `JaxStereoError` says how to enable 64 bits.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        if jax.config.jax_enable_x64:
            return fn(*args, **kwargs)
        if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves((args, kwargs))):
            raise JaxStereoError(
                f"{fn.__qualname__} was traced (jit, grad, vmap) with 64-bit types disabled: jaxstereo's geometry "
                "runs in float64 only. Trace it inside `with jax.enable_x64(True):`, decorate your function with "
                "`jaxstereo.float64`, or turn on JAX's jax_enable_x64 option in your own program"
            )
        with jax.enable_x64(True):
            return fn(*args, **kwargs)

    return wrapper


def as_float64(value):
    """`value` as a float64 JAX array (created in 64-bit mode); tracers and non-float arrays pass as they are."""
    if isinstance(value, jax.core.Tracer):
        return value
    array = np.asarray(value)
    if not np.issubdtype(array.dtype, np.floating) and not np.issubdtype(array.dtype, np.integer):
        return value
    with jax.enable_x64(True):
        return jnp.asarray(array, dtype=jnp.float64)
