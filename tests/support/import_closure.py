"""Which third-party modules a role's code imports anywhere, and whether they import here.

Reads the source of an installed package (say ``collector``) and of every module of this project
it reaches (``bgt_core.zenoh_config``, ...), collects the top-level names of all imports,
including those inside functions (``from cryptography import x509`` in a TLS check runs only
when a TLS config is checked), and imports each one that is neither the standard library nor
this project. Imports guarded by ``except ImportError`` are optional and those under
``if TYPE_CHECKING:`` never run: neither is counted.

Standard library only: it runs as a script in a fresh venv that holds one extra of the project,

    python import_closure.py collector

and prints one JSON object: the package's folder and, per missing name, the module that
imports it and the error. Exit status 1 when something is missing.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import json
import sys
from collections.abc import Iterator
from pathlib import Path

PROJECT = ("sensor_agent", "collector", "annotator", "bgt_core", "deploy")
OPTIONAL = {"ImportError", "ModuleNotFoundError"}


def _module_file(root: Path, name: str) -> Path | None:
    p = root.joinpath(*name.split("."))
    for f in (p / "__init__.py", p.with_suffix(".py")):
        if f.is_file():
            return f
    return None


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _not_run_lines(tree: ast.AST) -> set[int]:
    """Line numbers of imports that may fail or never run: inside a ``try`` that catches
    ImportError, or under ``if TYPE_CHECKING:`` (for the type checker only)."""
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            body = node.body
        elif isinstance(node, ast.Try):
            caught: set[str] = set()
            for h in node.handlers:
                types = h.type.elts if isinstance(h.type, ast.Tuple) else [h.type]
                caught |= {t.id for t in types if isinstance(t, ast.Name)}
            body = node.body if caught & OPTIONAL else []
        else:
            continue
        for stmt in body:
            lines.update(range(stmt.lineno, (stmt.end_lineno or stmt.lineno) + 1))
    return lines


def _imports(path: Path, module: str) -> Iterator[str]:
    """Dotted names imported by one source file (relative imports resolved), skipped ones left
    out; ``from a import b`` yields ``a`` and ``a.b`` (b may be a submodule)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    skipped = _not_run_lines(tree)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for node in ast.walk(tree):
        if getattr(node, "lineno", None) in skipped:
            continue
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = parts[: len(parts) - (node.level - 1)]
                source = ".".join([*base, node.module] if node.module else base)
            else:
                source = node.module or ""
            yield source
            yield from (f"{source}.{a.name}" for a in node.names if a.name != "*")


def third_party_imports(root: Path, package: str, exclude: tuple[str, ...] = ()) -> dict[str, str]:
    """Top-level third-party name -> the first project module found importing it, over every
    module of ``package`` under ``root`` and the project modules they import, but none under
    ``exclude`` (a sub-package that is a role of its own, with its own extra)."""
    top_dir = root / package.replace(".", "/")
    todo = [
        ".".join(f.relative_to(root).with_suffix("").parts).removesuffix(".__init__")
        for f in sorted(top_dir.rglob("*.py"))
    ]
    todo = [m for m in todo if not any(m == x or m.startswith(x + ".") for x in exclude)]
    seen: set[str] = set()
    found: dict[str, str] = {}
    while todo:
        module = todo.pop()
        if module in seen:
            continue
        seen.add(module)
        path = _module_file(root, module)
        if path is None:  # a name imported from a module, not a module itself
            continue
        for name in _imports(path, module):
            top = name.partition(".")[0]
            if top in PROJECT:
                if not any(name == x or name.startswith(x + ".") for x in exclude):
                    todo.append(name)
            elif top and top not in sys.stdlib_module_names:
                found.setdefault(top, module)
    return found


def missing_imports(package: str, exclude: tuple[str, ...] = ()) -> tuple[Path, dict[str, str]]:
    """The installed ``package``'s folder, and each third-party name its code imports that does
    not import here: name -> 'importing module: error'."""
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise SystemExit(f"{package} is not installed here")
    folder = Path(next(iter(spec.submodule_search_locations)))
    root = folder.parents[package.count(".")]
    missing = {}
    for name, importer in sorted(third_party_imports(root, package, exclude).items()):
        try:
            importlib.import_module(name)
        except Exception as e:  # noqa: BLE001 - any failure to import is the finding
            missing[name] = f"{importer}: {type(e).__name__}: {e}"
    return folder, missing


def main() -> int:
    # PACKAGE [-EXCLUDED ...]: e.g. "collector -collector.web" (the console is the web role)
    folder, missing = missing_imports(sys.argv[1], tuple(a.removeprefix("-") for a in sys.argv[2:]))
    print(json.dumps({"package_dir": str(folder), "missing": missing}))
    return 1 if missing else 0


if __name__ == "__main__":
    sys.exit(main())
