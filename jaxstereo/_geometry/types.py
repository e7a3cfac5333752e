"""Type aliases of the public API's annotations (jaxtyping array shapes; checked with beartype in the tests).

Scalars accept Python numbers and 0-d arrays; vectors accept arrays of the given length or sequences.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Union

from jaxtyping import ArrayLike, Float

PathLike = Union[str, os.PathLike]
Scalar = Union[float, Float[ArrayLike, ""]]
Vector2 = Union[Float[ArrayLike, "2"], Sequence[float]]
Vector3 = Union[Float[ArrayLike, "3"], Sequence[float]]
Matrix3 = Union[Float[ArrayLike, "3 3"], Sequence[Sequence[float]]]
Coefficients = Union[Float[ArrayLike, "..."], Sequence[float]]
