"""The layout's rules, checked on the source: one direction between the packages, no import
circle, no private name used across modules, no module over 600 lines."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("analysis", "driver", "service")
MAX_LINES = 600


def _modules() -> dict[str, Path]:
    out = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


MODULES = _modules()


def _imports(name: str, path: Path) -> list[tuple[str, str | None, int]]:
    """(module imported, name taken from it or None, line) for every import in a module; relative
    imports resolved."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(alias.name, None, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            for alias in node.names:
                if f"{module}.{alias.name}" in MODULES:   # `from package import module`
                    found.append((f"{module}.{alias.name}", None, node.lineno))
                else:
                    found.append((module, alias.name, node.lineno))
    return found


def _type_checking_lines(path: Path) -> set[int]:
    tree = ast.parse(path.read_text())
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for sub in ast.walk(node):
                if hasattr(sub, "lineno"):
                    lines.add(sub.lineno)
    return lines


def test_packages_depend_one_way():
    bad = []
    for name, path in MODULES.items():
        top = name.split(".")[0]
        for module, _, line in _imports(name, path):
            other = module.split(".")[0]
            if top in ("analysis", "driver") and other in PACKAGES and other != top:
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {module}")
    assert not bad, "analysis and driver use neither other package:\n" + "\n".join(bad)


def test_no_private_name_is_imported_across_modules():
    bad = []
    for name, path in MODULES.items():
        for module, imported, line in _imports(name, path):
            private = (imported or "").startswith("_") or any(p.startswith("_") and p != "__init__"
                                                               for p in module.split("."))
            if module in MODULES and module != name and private:
                bad.append(f"{path.relative_to(ROOT)}:{line} takes {module}.{imported}")
    assert not bad, "\n".join(bad)


def test_no_import_circle():
    graph: dict[str, set[str]] = {}
    for name, path in MODULES.items():
        skip = _type_checking_lines(path)
        graph[name] = {m for m, _, line in _imports(name, path) if m in MODULES and m != name and line not in skip}
    # A package's __init__ is run by importing any of its modules: an edge to a package is fine,
    # but a circle through one is not.
    seen: dict[str, int] = {}
    stack: list[str] = []
    circles = []

    def visit(node: str) -> None:
        seen[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if seen.get(nxt) == 1:
                circles.append(" -> ".join(stack[stack.index(nxt):] + [nxt]))
            elif nxt not in seen:
                visit(nxt)
        stack.pop()
        seen[node] = 2

    for node in sorted(graph):
        if node not in seen:
            visit(node)
    assert not circles, "\n".join(circles)


@pytest.mark.parametrize("name", sorted(MODULES))
def test_module_is_not_too_long(name):
    lines = MODULES[name].read_text().count("\n")
    assert lines <= MAX_LINES, f"{MODULES[name].relative_to(ROOT)} has {lines} lines; split it where its jobs divide"


def test_every_subpackage_says_what_it_holds():
    for init in sorted((ROOT / "analysis").glob("*/__init__.py")):
        doc = ast.get_docstring(ast.parse(init.read_text())) or ""
        assert len(doc) > 80 and "TODO" not in doc, f"{init.relative_to(ROOT)}: say what the folder holds"
