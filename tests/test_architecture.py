"""Layering of the package: no module imports a module of an outer layer.

Every module of ``jaxvisco/`` is parsed with `ast` (nothing is imported); relative
imports are resolved to absolute module names; imports inside functions count too.
A module's layer follows from its path: the first name below ``jaxvisco`` (a top-level
module or subpackage) decides. Imports within a layer are allowed.
"""

import ast
import pathlib

import pytest

PKG = pathlib.Path(__file__).resolve().parents[1] / "jaxvisco"

# First name below `jaxvisco` -> layer, inner to outer.
LAYERS = {
    "_config": 0, "_validation": 0, "_export": 0,
    "_fem": 1,
    "_materials": 2,
    "_scene": 3, "_time_functions": 3, "time_functions": 3, "scenes": 3,
    "_time_element": 4,
    "_solver": 5,
    "_integrate": 6,
    "_io": 7,
    "_scenefile": 8, "_tools": 8,
    "cli": 9,
}
# jaxvisco/__init__.py imports (nearly) everything: it may import every layer but the
# command line, and only the command line may import it.
ROOT = 8.5
LAYER_NAMES = {0: "infrastructure", 1: "fem", 2: "materials", 3: "model", 4: "time elements", 5: "solver",
               6: "integration", 7: "io", 8: "scene files/tools", ROOT: "package root", 9: "cli"}

# Upward imports that moving modules cannot remove (each a function-level import, so no
# import cycle at load time). Removing one needs a design change; the test below fails
# once an entry no longer occurs, so that this list only shrinks.
KNOWN_UPWARD = {
    # The public `Scene.from_file` delegates to the scene-file parser, which builds the
    # scene and the run settings (integrator, solver, schedule) and so sits above them.
    ("jaxvisco._scene", "jaxvisco._scenefile._scenefile"),
}


def _module_name(path):
    parts = list(path.relative_to(PKG.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


MODULES = {_module_name(p): p for p in sorted(PKG.rglob("*.py")) if "__pycache__" not in p.parts}


def _layer(module):
    parts = module.split(".")
    assert parts[0] == "jaxvisco", module
    if len(parts) == 1:
        return ROOT
    return LAYERS.get(parts[1])


def _imports(module, path):
    """Absolute names of the jaxvisco modules that `module` imports."""
    is_package = path.name == "__init__.py"
    package = module if is_package else module.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                assert base, f"{module}: relative import beyond the package"
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module
            for a in node.names:  # `from pkg import submodule` imports that submodule
                sub = f"{source}.{a.name}"
                out.add(sub if sub in MODULES else source)
    return {m for m in out if m == "jaxvisco" or m.startswith("jaxvisco.")}


def _fmt(layer):
    return f"{layer:g} {LAYER_NAMES[layer]}"


def _upward():
    found = []
    for module, path in MODULES.items():
        a = _layer(module)
        for target in sorted(_imports(module, path)):
            b = _layer(target)
            if a is not None and b is not None and b > a:
                found.append((module, target, a, b))
    return found


def test_every_module_has_a_layer():
    assert "jaxvisco._scene" in MODULES and "jaxvisco.cli" in MODULES  # the walk found the package
    missing = sorted(m for m in MODULES if _layer(m) is None)
    assert not missing, "modules without a layer (add them to LAYERS in tests/test_architecture.py): " + ", ".join(
        missing)


def test_imports_resolve_to_modules():
    """Every jaxvisco import names an existing module or package (so none slips past the
    layer check by a misresolved name)."""
    bad = sorted(f"{m} -> {t}" for m, p in MODULES.items() for t in _imports(m, p) if t not in MODULES)
    assert not bad, "unresolved imports:\n  " + "\n  ".join(bad)


def test_no_upward_imports():
    bad = [f"{m} -> {t} (layer {_fmt(a)} -> layer {_fmt(b)})" for m, t, a, b in _upward()
           if (m, t) not in KNOWN_UPWARD]
    assert not bad, "modules importing an outer layer:\n  " + "\n  ".join(bad)


@pytest.mark.parametrize("edge", sorted(KNOWN_UPWARD), ids=lambda e: f"{e[0]}->{e[1]}")
def test_known_upward_imports_still_exist(edge):
    assert edge in {(m, t) for m, t, _, _ in _upward()}, f"{edge} no longer occurs: remove it from KNOWN_UPWARD"


def test_only_cli_imports_cli():
    bad = sorted(f"{m} -> {t}" for m, p in MODULES.items() if not (m == "jaxvisco.cli" or m.startswith("jaxvisco.cli."))
                 for t in _imports(m, p) if t == "jaxvisco.cli" or t.startswith("jaxvisco.cli."))
    assert not bad, "modules outside jaxvisco/cli/ importing it:\n  " + "\n  ".join(bad)


def test_every_equinox_class_is_abstract_or_final():
    """equinox's convention: a Module class is either abstract (named Abstract*, never
    instantiated) or final (never subclassed); behaviour is shared by abstract bases,
    never by overriding a concrete class."""
    import importlib
    import inspect

    import equinox as eqx

    classes = set()
    for name in MODULES:
        if name == "jaxvisco.cli" or name.startswith("jaxvisco.cli."):
            continue
        module = importlib.import_module(name)
        classes |= {c for _, c in inspect.getmembers(module, inspect.isclass)
                    if issubclass(c, eqx.Module) and c.__module__.startswith("jaxvisco")}
    assert len(classes) > 20  # the walk found them
    subclassed = sorted(c.__qualname__ for c in classes if c.__subclasses__() and not c.__name__.startswith("Abstract"))
    assert not subclassed, "concrete equinox classes with subclasses: " + ", ".join(subclassed)
    unused = sorted(c.__qualname__ for c in classes if c.__name__.startswith("Abstract") and not c.__subclasses__())
    assert not unused, "abstract equinox classes without a subclass: " + ", ".join(unused)
