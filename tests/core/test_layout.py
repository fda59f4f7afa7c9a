"""The core's layout: it stays pure (never imports viser or the app, STYLE.md) and its modules
talk to each other only through public names (no ``from .x import _helper`` across modules)."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

import pregrasp_core

CORE = Path(__file__).resolve().parents[2] / "pregrasp_core"


def _sources() -> list[Path]:
    """Every Python file of the package, sub-packages included."""
    return sorted(CORE.rglob("*.py"))


def _module_name(path: Path) -> str:
    """Dotted name of a source file of the package (``pregrasp_core.hand.model``)."""
    parts = ["pregrasp_core", *path.relative_to(CORE).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _resolve(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    """The absolute module name a ``from ... import`` in ``module`` reads from."""
    if node.level == 0:
        return node.module or ""
    package = module.split(".") if is_package else module.split(".")[:-1]
    base = package[: len(package) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def private_imports(source: str, module: str, is_package: bool = False) -> list[str]:
    """``module:line name from other`` for every private name the code ``source`` of ``module``
    imports from another core module (relative or absolute import)."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.ImportFrom):
            continue
        other = _resolve(module, is_package, node)
        if other.split(".")[0] != "pregrasp_core" or other == module:
            continue
        for alias in node.names:
            if alias.name.startswith("_") and not alias.name.startswith("__"):
                out.append(f"{module}:{node.lineno} imports {alias.name} from {other}")
    return out


def test_the_package_has_modules_to_check():
    names = {_module_name(p) for p in _sources()}
    assert {"pregrasp_core", "pregrasp_core.decomposition", "pregrasp_core.facemask"} <= names


def test_core_sources_never_import_viser_or_app():
    offenders = {
        _module_name(p): sorted(_imported_modules(p) & {"viser", "app"}) for p in _sources()
    }
    assert {k: v for k, v in offenders.items() if v} == {}


def test_no_private_name_is_imported_across_core_modules():
    offenders = [
        line
        for p in _sources()
        for line in private_imports(p.read_text(), _module_name(p), p.name == "__init__.py")
    ]
    assert offenders == []


def test_the_private_import_check_finds_relative_and_absolute_imports():
    """The check above is not vacuous: private helpers imported from a sibling (relative, from
    the package above, absolute) are found; public names and the module's own are not."""
    src = (
        "from __future__ import annotations\n"
        "from .geometry import _hidden, as_points\n"
        "from ..box import _corner\n"
        "from pregrasp_core.hand.model import _link\n"
        "from pregrasp_core.hand.closing import _own\n"
        "from . import errors\n"
        "from numpy import _core\n"
    )
    found = private_imports(src, "pregrasp_core.hand.closing")
    assert [f.split(" imports ")[1] for f in found] == [
        "_hidden from pregrasp_core.hand.geometry",
        "_corner from pregrasp_core.box",
        "_link from pregrasp_core.hand.model",
    ]
    assert private_imports("from .box import _x\n", "pregrasp_core", is_package=True) == [
        "pregrasp_core:1 imports _x from pregrasp_core.box"
    ]


def test_importing_every_core_module_loads_no_viser():
    mods = sorted(_module_name(p) for p in _sources() if p.name != "__init__.py")
    code = (
        "import importlib, sys\n"
        f"for m in {mods!r}: importlib.import_module(m)\n"
        "bad = [m for m in sys.modules if m == 'viser' or m.startswith(('viser.', 'app.'))]\n"
        "print(bad); sys.exit(1 if bad else 0)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_init_re_exports_public_names_of_the_stage_modules():
    import importlib

    assert len(pregrasp_core.__all__) == len(set(pregrasp_core.__all__)) > 20
    lazy = set(pregrasp_core._LAZY)
    assert lazy < set(pregrasp_core.__all__)
    assert {n for n in pregrasp_core.__all__ if n not in lazy} == {
        n for n in pregrasp_core.__all__ if n.endswith("Error")
    }
    for name in pregrasp_core.__all__:
        assert not name.startswith("_")
        value = getattr(pregrasp_core, name)
        home = importlib.import_module(value.__module__)
        assert home.__name__.startswith("pregrasp_core."), name
        assert getattr(home, name) is value, name
    with pytest.raises(AttributeError, match="no attribute '_refit'"):
        pregrasp_core._refit  # noqa: B018


def test_importing_the_errors_loads_no_stage():
    """The CLI imports ``pregrasp_core.errors`` first: that must not load scipy or the stages."""
    code = (
        "import sys, pregrasp_core.errors\n"
        "heavy = [m for m in ('scipy', 'pregrasp_core.mvbb', 'pregrasp_core.pipeline')"
        " if m in sys.modules]\n"
        "print(heavy); sys.exit(1 if heavy else 0)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def any_in_public_signatures(source: str) -> list[str]:
    """``name: annotation`` of every public function or method (module level and public
    classes) whose parameters or return annotation mention ``Any``."""
    found = []

    def check(fn: ast.FunctionDef | ast.AsyncFunctionDef, owner: str) -> None:
        if fn.name.startswith("_") and fn.name != "__init__":
            return
        args = [*fn.args.posonlyargs, *fn.args.args, *fn.args.kwonlyargs]
        args += [a for a in (fn.args.vararg, fn.args.kwarg) if a is not None]
        notes = [a.annotation for a in args if a.annotation is not None]
        notes += [fn.returns] if fn.returns is not None else []
        for note in notes:
            text = ast.unparse(note)
            if re.search(r"\bAny\b", text):
                found.append(f"{owner}{fn.name}: {text}")

    for node in ast.parse(source).body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            check(node, "")
        elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
            for item in node.body:
                if isinstance(item, ast.FunctionDef | ast.AsyncFunctionDef):
                    check(item, f"{node.name}.")
    return found


def test_no_any_in_public_signatures_of_the_core():
    bad = {
        _module_name(p): hits
        for p in _sources()
        if (hits := any_in_public_signatures(p.read_text(encoding="utf-8")))
    }
    assert bad == {}


def test_the_any_check_finds_parameters_and_returns():
    src = (
        "from typing import Any\n"
        "def f(x: Any) -> int: ...\n"
        "def g(x: int) -> dict[str, Any]: ...\n"
        "def _h(x: Any) -> Any: ...\n"
        "class C:\n    def m(self, y: list[Any]) -> None: ...\n"
        "def ok(x: 'Anything') -> int: ...\n"
    )
    assert any_in_public_signatures(src) == [
        "f: Any",
        "g: dict[str, Any]",
        "C.m: list[Any]",
    ]
