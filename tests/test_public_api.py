"""The public API: what `jaxstereo/__init__.py` exports, every parameter and result annotated."""

import inspect

import jaxstereo as js


def _public_callables():
    for name in sorted(n for n in dir(js) if not n.startswith("_")):
        obj = getattr(js, name)
        if inspect.isclass(obj):
            if issubclass(obj, Exception):
                continue
            for attr, member in vars(obj).items():
                if attr.startswith("_") and attr != "__init__":
                    continue
                member = member.fget if isinstance(member, property) else getattr(member, "__func__", member)
                if inspect.isfunction(member) and member.__module__.startswith("jaxstereo"):
                    yield f"{name}.{attr}", member
        elif inspect.isfunction(obj) and obj.__module__.startswith("jaxstereo"):
            yield name, obj


def test_every_public_function_is_annotated():
    missing = []
    for qualname, fn in _public_callables():
        signature = inspect.signature(inspect.unwrap(fn))
        for parameter in signature.parameters.values():
            if parameter.name not in ("self", "cls") and parameter.annotation is inspect.Parameter.empty:
                missing.append(f"{qualname}({parameter.name})")
        if not qualname.endswith("__init__") and signature.return_annotation is inspect.Signature.empty:
            missing.append(f"{qualname} -> ?")
    assert not missing, missing


def test_the_public_api_is_large_and_from_the_stage_packages():
    modules = {fn.__module__.split(".")[1] for _, fn in _public_callables()}
    assert modules == {"_geometry", "_calibration", "_stereo", "_surface", "_synthetic", "_app"}
    assert sum(1 for _ in _public_callables()) > 100


def test_the_lazy_name_table_and_the_type_checkers_imports_agree():
    """`__init__.py` names each public name twice: in `_PUBLIC` (what `jaxstereo.X` imports on first use) and
    in its `TYPE_CHECKING` block (what editors and type checkers read). They must not drift apart."""
    import ast
    from pathlib import Path

    tree = ast.parse(Path(js.__file__).read_text())
    block = next(node for node in tree.body if isinstance(node, ast.If) and getattr(node.test, "id", "") == "TYPE_CHECKING")
    static = {(node.module, alias.name) for node in block.body if isinstance(node, ast.ImportFrom) for alias in node.names}
    lazy = {(module, name) for module, names in js._PUBLIC.items() for name in names}
    assert static == lazy
    assert sorted(js.__all__) == sorted(name for _, name in lazy)
