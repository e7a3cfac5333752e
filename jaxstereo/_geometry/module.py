"""Immutable dataclasses that are JAX PyTrees: the base of the geometry's types (`Pose`, `Camera`, `Interface`,
`Rectification`, `Rig`, `Heightfield`).

A `Module` subclass is a dataclass of its annotated fields; its array fields are the PyTree's leaves (they pass
through `jax.jit`, `jax.vmap` and `jax.grad`, and equinox's `filter_jit` and `tree_at`), and the fields declared
`field(static=True)` ride along as the tree's static data (hashable: an image size, a mode). As with equinox's
`Module`, whose behaviour this keeps for these types: an `__init__` of the class's own (or the dataclass's) assigns
the fields, then each `__check_init__` along the class's bases is called (it validates and raises); after that the
instance is frozen. Rebuilding a tree (`jax.tree_util`'s unflatten) runs neither: its leaves may be tracers or
placeholders.

Why not equinox's own: importing equinox takes about 0.1 s of CPU (its neural-network layers, debugging and
internal tools come with it), which a fresh `jaxstereo reconstruct` paid for five classes of plain fields.
optimistix, which the bundle adjustment and the calibration use, still brings equinox with it there.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import jax
import numpy as np

_FROZEN = "_module_frozen"


def field(*, static: bool = False, **kwargs) -> Any:
    """A `Module` field: `dataclasses.field` with `static` (static PyTree data instead of a leaf)."""
    return dataclasses.field(metadata={**kwargs.pop("metadata", {}), "static": static}, **kwargs)


class Module:
    """Base of an immutable dataclass registered as a JAX PyTree (see the module's docstring)."""

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        own_init = "__init__" in cls.__dict__
        dataclasses.dataclass(init=not own_init, repr=False, eq=False)(cls)
        fields = dataclasses.fields(cls)
        cls._leaf_names = tuple(f.name for f in fields if not f.metadata.get("static", False))
        cls._static_names = tuple(f.name for f in fields if f.metadata.get("static", False))
        cls._checks = tuple(base.__dict__["__check_init__"] for base in cls.__mro__ if "__check_init__" in base.__dict__)
        cls.__init__ = _finishing(cls.__init__)
        jax.tree_util.register_pytree_with_keys(cls, _flatten_with_keys, functools.partial(_unflatten, cls),
                                                _flatten)

    def __setattr__(self, name: str, value) -> None:
        if self.__dict__.get(_FROZEN, False):
            raise dataclasses.FrozenInstanceError(f"cannot assign to field {name!r} of a {type(self).__name__}")
        object.__setattr__(self, name, value)

    def __eq__(self, other) -> bool:
        """Equal type, equal static data and equal leaves (arrays compared by value)."""
        if type(other) is not type(self):
            return NotImplemented
        mine, theirs = jax.tree_util.tree_flatten(self), jax.tree_util.tree_flatten(other)
        if mine[1] != theirs[1]:
            return False
        return all(_leaf_equal(a, b) for a, b in zip(mine[0], theirs[0]))

    __hash__ = None  # its arrays are not hashable (equinox's Module raises too)

    def __repr__(self) -> str:
        values = ", ".join(f"{f.name}={_short(getattr(self, f.name, None))}" for f in dataclasses.fields(self))
        return f"{type(self).__name__}({values})"


def replaced(module: Module, **changes) -> Module:
    """A copy of `module` with the fields `changes` given new values, as they are: neither `__init__` nor a check
    runs (equinox's `tree_at` on those fields)."""
    values = {name: getattr(module, name) for name in (*module._leaf_names, *module._static_names)}
    unknown = set(changes) - set(values)
    if unknown:
        raise TypeError(f"{type(module).__name__} has no field {sorted(unknown)}")
    return _built(type(module), {**values, **changes})


def _finishing(init: Callable) -> Callable:
    """`init` followed by the checks of the instance's class, then freezing it (the outermost
    `__init__` only: a subclass's that calls its base's finishes once)."""

    @functools.wraps(init)
    def __init__(self, *args, **kwargs):
        outermost = "_module_initialising" not in self.__dict__
        if outermost:
            self.__dict__["_module_initialising"] = True
        init(self, *args, **kwargs)
        if not outermost:
            return
        del self.__dict__["_module_initialising"]
        cls = type(self)
        missing = [name for name in (*cls._leaf_names, *cls._static_names) if name not in self.__dict__]
        if missing:
            raise TypeError(f"{cls.__name__}.__init__ left the fields {missing} unset")
        for check in cls._checks:
            check(self)
        self.__dict__[_FROZEN] = True

    return __init__


# A field its `__init__` has not set yet reads as None (an empty subtree): a decorated `__init__` (`float64`) looks
# for tracers among the leaves of its arguments, the instance being made among them.
def _flatten(module: Module):
    values = module.__dict__
    return [values.get(name) for name in module._leaf_names], tuple(values.get(name) for name in module._static_names)


def _flatten_with_keys(module: Module):
    values = module.__dict__
    leaves = [(jax.tree_util.GetAttrKey(name), values.get(name)) for name in module._leaf_names]
    return leaves, tuple(values.get(name) for name in module._static_names)


def _unflatten(cls, static, leaves) -> Module:
    return _built(cls, {**dict(zip(cls._leaf_names, leaves)), **dict(zip(cls._static_names, static))})


def _built(cls, values: dict) -> Module:
    module = object.__new__(cls)
    module.__dict__.update(values)
    module.__dict__[_FROZEN] = True
    return module


def _leaf_equal(a, b) -> bool:
    if a is b:
        return True
    if isinstance(a, jax.core.Tracer) or isinstance(b, jax.core.Tracer):
        return False
    try:
        a_arr, b_arr = np.asarray(a), np.asarray(b)
    except (TypeError, ValueError):
        return bool(a == b)
    if a_arr.dtype == object or b_arr.dtype == object:
        return bool(a == b)
    return a_arr.shape == b_arr.shape and bool(np.array_equal(a_arr, b_arr))


def _short(value) -> str:
    """A field's value in a repr: an array as its dtype and shape, anything else as its repr."""
    if hasattr(value, "shape") and hasattr(value, "dtype") and getattr(value, "ndim", 0) > 0:
        return f"{value.dtype}{list(value.shape)}"
    return repr(value)
