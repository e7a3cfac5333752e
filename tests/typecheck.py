"""The runtime type checker the test suite applies to the whole package (see `conftest.py`).

beartype with the PEP 484 numeric tower (an `int` is accepted where a `float` is annotated, as Python's
typing promises), through jaxtyping so that array shapes and dtypes are checked too.
"""

from beartype import BeartypeConf, beartype

checker = beartype(conf=BeartypeConf(is_pep484_tower=True))
