"""The package layering of docs/architecture.md, checked by parsing the source (nothing is imported).

Every ``import`` and ``from ... import`` of every module under ``microctl/`` counts: at module level,
inside functions and classes, and under ``if TYPE_CHECKING:``. A module may import only from its own
package or from a package on a lower layer, and the import graph has no circle. The size limits of
the style guide (a module at most 600 lines, a function at most 80 lines from its ``def`` line to its
last line) are checked here too.
"""

from __future__ import annotations

import ast
from functools import lru_cache
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "microctl"

#: Layer of each sub-package, lowest first (docs/architecture.md). A module imports only from its
#: own package or from a package on a strictly lower layer; packages on one layer are independent.
#: ``microctl`` itself (``__init__``, ``_version``, ``errors``) is the base every layer may use.
LAYERS: dict[str, int] = {
    "microctl": 0,
    "util": 1,
    "stage": 2, "gp": 2,
    "models": 3,
    "measurement": 4,
    "backends": 5, "control": 5,
    "experiments": 6, "diagnosis": 6,
    "testing": 7, "api": 7,
    "cli": 8,
}
#: Top-level modules that belong to a package's layer rather than the base.
TOP_LEVEL = {"microctl.__main__": "cli"}
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80


@lru_cache(maxsize=None)
def _modules() -> dict[str, Path]:
    """Dotted module name -> file, for every module of the package (``pkg/__init__.py`` is ``pkg``)."""
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


@lru_cache(maxsize=None)
def _tree(module: str) -> ast.Module:
    path = _modules()[module]
    return ast.parse(path.read_text(encoding="utf-8"), filename=str(path))


def _package_of(module: str) -> str:
    """The sub-package a module belongs to (``microctl`` for the base modules)."""
    if module in TOP_LEVEL:
        return TOP_LEVEL[module]
    parts = module.split(".")
    if len(parts) == 1 or (len(parts) == 2 and parts[1] not in LAYERS):
        return "microctl"
    return parts[1]


def _resolve(name: str) -> str | None:
    """The most specific module of the package that ``import name`` runs (None: not ours)."""
    parts = name.split(".")
    while parts:
        candidate = ".".join(parts)
        if candidate in _modules():
            return candidate
        parts.pop()
    return None


def _imports(module: str, tree: ast.Module | None = None, is_package: bool | None = None) -> list[tuple[int, str]]:
    """(line, imported module) for every import of the package's modules anywhere in ``module``
    (its parsed source ``tree``; default: the file's)."""
    if tree is None:
        tree, is_package = _tree(module), _modules()[module].name == "__init__.py"
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: resolved against the importing module's package
                anchor = module.split(".")
                anchor = anchor[: len(anchor) - node.level + (1 if is_package else 0)]
                base = ".".join(anchor + ([base] if base else []))
            # `from pkg import sub` imports pkg.sub when it is a module, else a name of pkg
            names = [f"{base}.{alias.name}" for alias in node.names] if base else []
        else:
            continue
        for name in names:
            target = _resolve(name)
            if target is not None and target != module:
                out.append((node.lineno, target))
    return out


def _graph() -> dict[str, set[str]]:
    return {m: {t for _, t in _imports(m)} for m in _modules()}


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _oversized_modules() -> list[str]:
    out = []
    for module, path in _modules().items():
        n = len(path.read_text(encoding="utf-8").splitlines())
        if n > MAX_MODULE_LINES:
            out.append(f"{path.relative_to(ROOT)} ({n} lines)")
    return out


def _oversized_functions() -> list[str]:
    out = []
    for module, path in _modules().items():
        for node in ast.walk(_tree(module)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    out.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({n} lines)")
    return sorted(out)


def test_every_package_has_a_layer():
    unknown = sorted({m.split(".")[1] for m in _modules() if len(m.split(".")) > 2} - set(LAYERS))
    assert not unknown, f"packages without a layer in LAYERS (and docs/architecture.md): {unknown}"


def test_imports_only_from_own_package_or_lower_layers():
    wrong = []
    for module in _modules():
        own = _package_of(module)
        for line, target in _imports(module):
            other = _package_of(target)
            if other != own and LAYERS[other] >= LAYERS[own]:
                wrong.append(f"{_modules()[module].relative_to(ROOT)}:{line} imports {target} "
                             f"({other}, layer {LAYERS[other]}; {own} is on layer {LAYERS[own]})")
    assert not wrong, "imports against the layering:\n" + "\n".join(wrong)


def test_no_import_circles():
    circles = _circles(_graph())
    assert not circles, "import circles:\n" + "\n".join(" <-> ".join(c) for c in circles)


def test_the_checks_see_what_they_must():
    """The parser finds imports inside functions and under TYPE_CHECKING, relative ones, and circles."""
    src = ("from __future__ import annotations\nfrom typing import TYPE_CHECKING\nimport numpy as np\n"
           "if TYPE_CHECKING:\n    from microctl.cli import main\n"
           "class A:\n    def f(self):\n        import microctl.stage.config\n        from .. import errors\n"
           "        from . import kernels, vhgpr as v\n")
    found = _imports("microctl.gp.vhgpr", ast.parse(src), is_package=False)
    assert found == [(5, "microctl.cli"), (8, "microctl.stage.config"), (9, "microctl.errors"),
                     (10, "microctl.gp.kernels")], found  # vhgpr itself is not an import of vhgpr
    assert _imports("microctl.gp", ast.parse("from . import kernels\n"), is_package=True) == [(1, "microctl.gp.kernels")]
    assert _resolve("microctl.stage.config.load_stage_config") == "microctl.stage.config"
    assert _resolve("numpy") is None
    assert _package_of("microctl.errors") == "microctl" and _package_of("microctl.gp.vhgpr") == "gp"
    assert _circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _circles({"a": {"b"}, "b": set()}) == []


def test_modules_at_most_600_lines():
    over = _oversized_modules()
    assert not over, f"modules over {MAX_MODULE_LINES} lines:\n" + "\n".join(over)


def test_functions_at_most_80_lines():
    over = _oversized_functions()
    assert not over, f"functions over {MAX_FUNCTION_LINES} lines:\n" + "\n".join(over)


def _is_slow(decorators: list[ast.expr]) -> bool:
    return any(ast.unparse(d) == "pytest.mark.slow" for d in decorators)


def test_every_test_folder_keeps_a_fast_test():
    """``pytest -m "not slow"`` (README's fast loop) still runs a test of every package's folder."""
    folders: dict[Path, bool] = {}
    for path in sorted((ROOT / "tests").rglob("test_*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        module_slow = any(isinstance(n, ast.Assign) and any(getattr(t, "id", "") == "pytestmark" for t in n.targets)
                          and "pytest.mark.slow" in ast.unparse(n.value) for n in tree.body)
        fast = not module_slow and any(isinstance(n, ast.FunctionDef) and n.name.startswith("test_")
                                       and not _is_slow(n.decorator_list) for n in tree.body)
        folders[path.parent] = folders.get(path.parent, False) or fast
    assert len(folders) > 1 and all(folders.values()), [str(f.relative_to(ROOT)) for f, ok in folders.items() if not ok]
