"""The import contract between the layers, read from the source with ``ast``.

* controllers/ import only controllers, the standard library, numeric and solver packages, and
  hil's error and value types (hil.core.errors, hil.core.types);
* drivers/ and emulators/ import from hil only those two modules; drivers never import
  emulators;
* hil.core names no application (hil.bench, hil.servo, hil.cli) and no driver or emulator;
  only the command line imports hil.cli;
* the two applications stay apart in every layer: hil.bench and hil.servo, controllers.bench
  and controllers.servo, emulators.bench and emulators.drive do not import each other;
* no import cycles anywhere, imports inside functions and under TYPE_CHECKING included.

The checker is tested on small made-up trees first, so a rule that can never fail is caught.
"""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("hil", "drivers", "controllers", "emulators")
SHARED_TYPES = {"hil.core.errors", "hil.core.types"}
NUMERIC = {"numpy", "scipy", "cvxpy", "highspy", "daqp", "filterpy", "threadpoolctl"}
# each layer's bench part and servo part: neither imports the other
APPLICATIONS = (("hil.bench", "hil.servo"), ("controllers.bench", "controllers.servo"),
                ("emulators.bench", "emulators.drive"))


def module_files(root: Path) -> dict[str, Path]:
    """``{dotted module name: file}`` of every module of the project's packages."""
    modules = {}
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            modules[".".join(parts)] = path
    return modules


def imports_of(path: Path, module: str, known: Iterable[str]) -> set[str]:
    """Every module ``module`` imports, anywhere in the file. ``from a import b`` counts as
    ``a.b`` when that is a project module, else as ``a``."""
    known = set(known)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            for alias in node.names:
                candidate = f"{base}.{alias.name}"
                found.add(candidate if candidate in known else base)
    return found


def top(name: str) -> str:
    return name.split(".")[0]


def is_under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def violations(graph: dict[str, set[str]]) -> list[str]:
    """Every import that breaks a layer rule, as ``"a imports b: why"``."""
    stdlib = set(sys.stdlib_module_names)
    out = []
    for module, imported in sorted(graph.items()):
        layer = top(module)
        for name in sorted(imported):
            root = top(name)
            why = None
            if layer == "controllers":
                if root in PACKAGES and root != "controllers" and name not in SHARED_TYPES:
                    why = "controllers import only controllers and hil.core.errors/types"
                elif root not in PACKAGES and root not in stdlib and root not in NUMERIC:
                    why = f"controllers use only the standard library and {sorted(NUMERIC)}"
            elif layer in ("drivers", "emulators"):
                if root == "hil" and name not in SHARED_TYPES:
                    why = f"{layer} import from hil only hil.core.errors and hil.core.types"
                elif layer == "drivers" and root == "emulators":
                    why = "drivers never import emulators"
            elif is_under(module, "hil.core") and (root in ("drivers", "emulators") or any(
                    is_under(name, app) for app in ("hil.bench", "hil.servo", "hil.cli"))):
                why = "hil.core names no application, driver or emulator"
            if why is None and any(
                    (is_under(module, a) and is_under(name, b)) or
                    (is_under(module, b) and is_under(name, a)) for a, b in APPLICATIONS):
                why = "the bench and servo applications do not import each other"
            if why is None and is_under(name, "hil.cli") and not (
                    is_under(module, "hil.cli") or module == "hil.__main__"):
                why = "only the command line imports hil.cli"
            if why:
                out.append(f"{module} imports {name}: {why}")
    return out


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), plus self-imports."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in graph.get(node, ()):
            if nxt not in graph:
                continue
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1 or node in graph.get(node, ()):
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def import_graph(root: Path) -> dict[str, set[str]]:
    files = module_files(root)
    return {module: imports_of(path, module, files) - {module} if path.name != "__init__.py"
            else imports_of(path, module, files)
            for module, path in files.items()}


# -- the checker can fail ----------------------------------------------------------------------


def write_tree(root: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def test_checker_catches_wrong_way_imports(tmp_path):
    write_tree(tmp_path, {
        "hil/__init__.py": "", "hil/core/__init__.py": "", "hil/core/errors.py": "",
        "hil/core/loop.py": "def f():\n    from hil.bench import rig\n",
        "hil/bench/__init__.py": "", "hil/bench/rig.py": "import hil.servo.run\n",
        "hil/servo/__init__.py": "", "hil/servo/run.py": "",
        "controllers/__init__.py": "", "controllers/c.py": "import socket\nimport pymodbus\n"
                                                          "from hil.core.loop import X\n",
        "drivers/__init__.py": "", "drivers/d.py": "from emulators import e\n"
                                                 "from hil.core import errors\n",
        "emulators/__init__.py": "", "emulators/e.py": "from hil.core.loop import Task\n",
        "controllers/bench/__init__.py": "", "controllers/servo/__init__.py": "",
        "controllers/bench/eec.py": "from controllers.servo import mpc\n",
        "controllers/servo/mpc.py": "import numpy\n",
        "emulators/drive/__init__.py": "", "emulators/bench/__init__.py": "",
        "emulators/drive/node.py": "def f():\n    import emulators.bench.plant\n",
        "emulators/bench/plant.py": "",
    })
    found = "\n".join(violations(import_graph(tmp_path)))
    assert "hil.core.loop imports hil.bench.rig" in found          # inside a function
    assert "hil.bench.rig imports hil.servo.run" in found
    assert "controllers.c imports pymodbus" in found
    assert "controllers.c imports hil.core.loop" in found
    assert "drivers.d imports emulators.e: drivers never import emulators" in found
    assert "emulators.e imports hil.core.loop" in found
    assert "drivers.d imports hil.core.errors" not in found         # `from pkg import module`
    assert "controllers.c imports socket" not in found              # standard library
    assert "controllers.bench.eec imports controllers.servo.mpc" in found
    assert "emulators.drive.node imports emulators.bench.plant" in found


def test_checker_finds_cycles_through_functions(tmp_path):
    write_tree(tmp_path, {
        "hil/__init__.py": "", "hil/a.py": "from hil.b import x\n",
        "hil/b.py": "def g():\n    import hil.c\n", "hil/c.py": "from hil import a\n",
        "hil/d.py": "import hil.a\n",
    })
    assert cycles(import_graph(tmp_path)) == [["hil.a", "hil.b", "hil.c"]]


# -- the project keeps the contract ------------------------------------------------------------


def test_layers_import_only_what_the_contract_allows():
    assert violations(import_graph(ROOT)) == []


def test_no_import_cycles():
    assert cycles(import_graph(ROOT)) == []
