"""The float64 policy: geometry runs in float64, enabled locally, never by a global flag on import."""

from __future__ import annotations

import functools

import jax


def float64(fn):
    """Decorate `fn` so that it runs with 64-bit JAX types enabled, whatever the global setting.

    The library's user-facing pipeline functions use this; pure kernels stay dtype-agnostic so that
    they can be composed inside a caller's own `jax.jit`.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with jax.enable_x64(True):
            return fn(*args, **kwargs)

    return wrapper
