"""The import contract between the layers, read from the source with ``ast``.

The repository keeps the user's layout (``hil/``, ``drivers/``, ``controllers/``,
``emulators/``); the installed package is ``hil`` alone, the three folders being
``hil.drivers``, ``hil.controllers`` and ``hil.emulators`` (links in the checkout).

* the kernel (hil.errors, hil.contracts) sits at the bottom: it imports nothing else of hil;
* hil.protocols (the wire's tables) imports only the kernel, the standard library and python-can;
* hil.controllers imports only itself, the kernel, the standard library and the numeric and
  solver packages;
* hil.drivers and hil.emulators import from the rest of hil only the kernel and
  hil.protocols (emulators may also use controllers' models); drivers never import emulators;
* each library owns its errors: in hil.controllers, hil.drivers and hil.emulators only the
  library's own ``errors`` module imports hil.errors;
* nothing imports the checkout's folders by their top-level names (``drivers``...), which the
  installed package does not have;
* hil.core names no application (hil.bench, hil.servo, hil.cli) and no driver or emulator;
  only the command line imports hil.cli;
* the two applications stay apart in every layer: hil.bench and hil.servo, their controllers,
  and their emulators do not import each other;
* no import cycles anywhere, imports inside functions and under TYPE_CHECKING included.

The checker is tested on small made-up trees first, so a rule that can never fail is caught.
"""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# checkout folder -> the package it is once installed
PACKAGES = {"hil": "hil", "drivers": "hil.drivers", "controllers": "hil.controllers",
            "emulators": "hil.emulators"}
KERNEL = {"hil.errors", "hil.contracts"}
LIBRARIES = ("hil.controllers", "hil.drivers", "hil.emulators")
NUMERIC = {"numpy", "scipy", "cvxpy", "highspy", "daqp", "filterpy", "threadpoolctl"}
# each layer's bench part and servo part: neither imports the other
APPLICATIONS = (("hil.bench", "hil.servo"), ("hil.controllers.bench", "hil.controllers.servo"),
                ("hil.emulators.bench", "hil.emulators.drive"))


def module_files(root: Path) -> dict[str, Path]:
    """``{dotted module name: file}`` of every module, by its installed name (the links in
    ``hil/`` to the checkout's folders are not walked twice)."""
    modules = {}
    for folder, package in PACKAGES.items():
        base = root / folder
        for path in sorted(base.rglob("*.py")):
            relative = path.relative_to(base)
            if folder == "hil" and relative.parts[0] in PACKAGES:
                continue
            parts = [*package.split("."), *relative.with_suffix("").parts]
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


def library_of(name: str) -> str | None:
    return next((lib for lib in LIBRARIES if is_under(name, lib)), None)


def layer_rule(module: str, name: str) -> str | None:
    """Why ``module`` may not import ``name`` by the layer rules, or None."""
    stdlib = set(sys.stdlib_module_names)
    root = top(name)
    ours = root == "hil"
    if root in PACKAGES and not ours:
        return f"import hil.{name}: the installed package has no top-level {root!r}"
    if module in KERNEL:
        return "the kernel imports nothing else of hil" if ours and name not in KERNEL else None
    if is_under(module, "hil.protocols"):
        if ours and name not in KERNEL and not is_under(name, "hil.protocols"):
            return "hil.protocols imports only the kernel and itself"
        if not ours and root not in stdlib and root != "can":
            return "hil.protocols uses only the standard library and python-can"
        return None
    library = library_of(module)
    if library is not None and is_under(name, "hil.errors") and module != f"{library}.errors":
        return f"{library}'s errors are its own (its errors module alone subclasses hil's)"
    if library == "hil.controllers":
        if ours and name not in KERNEL and not is_under(name, library):
            return "controllers import only controllers and the kernel"
        if not ours and root not in stdlib and root not in NUMERIC:
            return f"controllers use only the standard library and {sorted(NUMERIC)}"
    elif library in ("hil.drivers", "hil.emulators"):
        allowed = [library, "hil.protocols", *KERNEL]
        if library == "hil.emulators":
            allowed.append("hil.controllers")
        if ours and not any(is_under(name, a) for a in allowed):
            if library == "hil.drivers" and is_under(name, "hil.emulators"):
                return "drivers never import emulators"
            return f"{library} imports from hil only {', '.join(sorted(allowed))}"
    elif is_under(module, "hil.core") and any(
            is_under(name, other) for other in
            ("hil.bench", "hil.servo", "hil.cli", "hil.drivers", "hil.emulators")):
        return "hil.core names no application, driver or emulator"
    return None


def violations(graph: dict[str, set[str]]) -> list[str]:
    """Every import that breaks a layer rule, as ``"a imports b: why"``."""
    out = []
    for module, imported in sorted(graph.items()):
        for name in sorted(imported):
            why = layer_rule(module, name)
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
        "hil/__init__.py": "", "hil/core/__init__.py": "", "hil/errors.py": "",
        "hil/contracts.py": "from hil.errors import HilError\nfrom hil.core import loop\n",
        "hil/core/loop.py": "def f():\n    from hil.bench import rig\n",
        "hil/bench/__init__.py": "", "hil/bench/rig.py": "import hil.servo.run\n",
        "hil/servo/__init__.py": "", "hil/servo/run.py": "from drivers import d\n",
        "hil/protocols/__init__.py": "", "hil/protocols/cia.py": "import can\nimport numpy\n"
                                                                "from hil.drivers import d\n",
        "controllers/__init__.py": "", "controllers/errors.py": "from hil.errors import HilError\n",
        "controllers/c.py": "import socket\nimport pymodbus\nfrom hil.core.loop import X\n"
                            "from hil.errors import UsageError\n"
                            "from hil.controllers.errors import E\n",
        "drivers/__init__.py": "", "drivers/d.py": "from hil.emulators import e\n"
                                                 "from hil.protocols import cia\n"
                                                 "from hil import contracts\n",
        "emulators/__init__.py": "", "emulators/e.py": "from hil.core.loop import Task\n"
                                                     "from hil.controllers import c\n",
        "controllers/bench/__init__.py": "", "controllers/servo/__init__.py": "",
        "controllers/bench/eec.py": "from hil.controllers.servo import mpc\n",
        "controllers/servo/mpc.py": "import numpy\n",
        "emulators/drive/__init__.py": "", "emulators/bench/__init__.py": "",
        "emulators/drive/node.py": "def f():\n    import hil.emulators.bench.plant\n",
        "emulators/bench/plant.py": "",
    })
    graph = import_graph(tmp_path)
    assert "hil.drivers.d" in graph and "drivers.d" not in graph    # installed names
    found = "\n".join(violations(graph))
    assert "hil.contracts imports hil.core.loop: the kernel" in found
    assert "hil.contracts imports hil.errors" not in found
    assert "hil.core.loop imports hil.bench.rig" in found          # inside a function
    assert "hil.bench.rig imports hil.servo.run" in found
    assert "hil.servo.run imports drivers: import hil.drivers" in found
    assert "hil.protocols.cia imports numpy" in found
    assert "hil.protocols.cia imports hil.drivers.d" in found
    assert "hil.protocols.cia imports can" not in found
    assert "hil.controllers.c imports pymodbus" in found
    assert "hil.controllers.c imports hil.core.loop" in found
    assert "hil.controllers.c imports hil.errors: hil.controllers's errors are its own" in found
    assert "hil.controllers.errors imports hil.errors" not in found
    assert "hil.controllers.c imports hil.controllers.errors" not in found
    assert "hil.drivers.d imports hil.emulators.e: drivers never import emulators" in found
    assert "hil.drivers.d imports hil.protocols.cia" not in found
    assert "hil.drivers.d imports hil.contracts" not in found       # `from pkg import module`
    assert "hil.emulators.e imports hil.core.loop" in found
    assert "hil.emulators.e imports hil.controllers.c" not in found  # a model is data
    assert "hil.controllers.c imports socket" not in found          # standard library
    assert "hil.controllers.bench.eec imports hil.controllers.servo.mpc" in found
    assert "hil.emulators.drive.node imports hil.emulators.bench.plant" in found


def test_checker_walks_the_links_once(tmp_path):
    write_tree(tmp_path, {"hil/__init__.py": "", "drivers/__init__.py": "",
                          "drivers/d.py": "import hil\n"})
    (tmp_path / "hil" / "drivers").symlink_to("../drivers")
    assert sorted(import_graph(tmp_path)) == ["hil", "hil.drivers", "hil.drivers.d"]


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
