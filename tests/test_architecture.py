"""The architecture of ``fem3d/``: no import circles, the layering of its parts, size limits.

Every module under ``fem3d/`` is parsed with :mod:`ast` (nothing is imported). Its imports make
the module import graph: ``import a.b``, ``from a import b`` (an edge to the submodule ``a.b``
when ``b`` is one, else to ``a``), relative imports, and ``importlib.import_module("a.b")``
with a literal name (or an f-string's literal start); imports inside functions count like
those at module level (they are the ones that hid the circles before). An import of
``fem3d.a.b`` from outside ``fem3d.a`` also runs the package ``fem3d/a/__init__.py`` first,
so it is an edge to ``fem3d.a`` as well. Imports under ``if TYPE_CHECKING:`` do not run and
are exempt from every rule here.

Three checks, each naming the module, the line, the imported module and the rule broken:

1. no import circle between modules (:func:`import_cycles`);
2. the layering :data:`LAYERS`: a module of one part of fem3d imports from another part only
   when the table allows it (:func:`layering_violations`);
3. sizes: no function or method over :data:`MAX_FUNCTION_LINES` lines and no module over
   :data:`MAX_MODULE_LINES` lines, except the entries of :data:`SIZE_ALLOWED`, each with its
   reason (:func:`size_violations`).

The tests at the end feed the checker planted packages, so it is seen to fail.
"""

from __future__ import annotations

import ast
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = "fem3d"

#: Anything at all (the entry points).
ANYTHING = "*"

_BELOW_RUN = ("errors", "kernels", "io", "mesh", "physics", "solve", "scene")

#: The parts of fem3d (top-level subpackages and modules) from the lowest up, and the other
#: parts each may import (its own part always). A part missing here fails the test: add it.
LAYERS: dict[str, tuple[str, ...] | str] = {
    "errors": (),
    "kernels": ("errors",),
    "io": ("errors",),
    "mesh": ("errors", "io", "kernels"),
    "physics": ("errors", "kernels", "mesh", "io"),
    "solve": ("errors", "kernels", "physics"),
    "scene": ("errors", "io", "mesh", "kernels", "physics", "solve"),
    "diff": ("errors", "kernels", "physics", "solve", "scene"),  # adjoint gradients
    "simulation": _BELOW_RUN,  # anything but app
    # one simulation on MPI ranks (PETSc): a Simulation with a distributed System
    "parallel": (*_BELOW_RUN, "simulation"),
    "app": ANYTHING,
    "__main__": ANYTHING,  # ``python -m fem3d``: runs the command line
}

#: Modules that are not files under fem3d/ but belong to a part: the generated NumPy kernels
#: (``generated/numpy``, installed as ``fem3d._generated``) and the C extension.
PART_ALIASES: dict[str, str] = {"fem3d._generated": "kernels", "fem3d._ckernels": "kernels"}

#: ``fem3d/__init__.py`` imports at module level only from these parts; inside functions (the
#: lazy ``__getattr__`` exposing public names such as ``fem3d.Scene``) from any.
ROOT_EAGER: tuple[str, ...] = ("errors",)

MAX_FUNCTION_LINES = 120
MAX_MODULE_LINES = 900

#: Exceptions to the size limits: ``"fem3d/x/y.py"`` (a module) or ``"fem3d/x/y.py::Class.f"``
#: (a function or method by qualified name) -> the one-line reason it stays larger. An entry
#: that is no longer over its limit fails the test too, so the list only shrinks.
SIZE_ALLOWED: dict[str, str] = {}


@dataclass(frozen=True)
class Edge:
    """One import: ``importer`` (a module under the package) imports ``target``."""

    importer: str
    path: str
    line: int
    target: str
    lazy: bool  # inside a function
    via: str = ""  # "" or why the edge exists besides the import itself
    names: tuple[str, ...] = ()  # the names of ``from package import names``

    def where(self) -> str:
        kind = "function-level import" if self.lazy else "import"
        via = f", {self.via}" if self.via else ""
        return f"{self.path}:{self.line} ({kind} of {self.target}{via})"


@dataclass
class Module:
    name: str
    path: str  # relative to the checked root, with "/"
    tree: ast.Module
    n_lines: int
    edges: list[Edge] = field(default_factory=list)


def module_name(rel: Path) -> str:
    """``fem3d/a/b.py`` -> ``fem3d.a.b``; ``fem3d/a/__init__.py`` -> ``fem3d.a``."""
    parts = rel.with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _type_checking_nodes(tree: ast.Module) -> set[int]:
    """ids of the nodes under ``if TYPE_CHECKING:`` (not its ``else``)."""
    skip: set[int] = set()
    for node in ast.walk(tree):
        test = getattr(node, "test", None)
        if isinstance(node, ast.If) and (  # TYPE_CHECKING or typing.TYPE_CHECKING, not "not ..."
                getattr(test, "id", None) == "TYPE_CHECKING" or
                getattr(test, "attr", None) == "TYPE_CHECKING"):
            for stmt in node.body:
                skip.update(id(n) for n in ast.walk(stmt))
    return skip


def _import_module_literal(node: ast.Call) -> str | None:
    """The module named by ``importlib.import_module("a.b")`` / ``(f"a.b.{x}")``, or None."""
    func = node.func
    name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
    if name != "import_module" or not node.args:
        return None
    arg = node.args[0]
    if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
        return arg.value
    if isinstance(arg, ast.JoinedStr) and arg.values and isinstance(arg.values[0], ast.Constant):
        return str(arg.values[0].value).rstrip(".") or None
    return None


def _imports(tree: ast.Module) -> list[tuple[ast.AST, bool]]:
    """Import statements and ``import_module`` calls with whether each is inside a function."""
    skip = _type_checking_nodes(tree)
    found: list[tuple[ast.AST, bool]] = []

    def visit(node: ast.AST, lazy: bool) -> None:
        if id(node) in skip:
            return
        if isinstance(node, ast.Import | ast.ImportFrom) or (
                isinstance(node, ast.Call) and _import_module_literal(node)):
            found.append((node, lazy))
        inner = lazy or isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)
        for child in ast.iter_child_nodes(node):
            visit(child, inner)

    visit(tree, False)
    return found


class Package:
    """The modules of a package directory and their import edges.

    Parameters
    ----------
    root : Path
        The directory holding the package directory.
    package : str
        The package's name (its directory under ``root``).
    """

    def __init__(self, root: Path, package: str = PACKAGE) -> None:
        self.package = package
        self.modules: dict[str, Module] = {}
        for path in sorted((root / package).rglob("*.py")):
            rel = path.relative_to(root)
            if "_generated" in rel.parts:  # a build copy of generated/numpy, not the source
                continue
            text = path.read_text()
            tree = ast.parse(text, filename=str(rel))
            name = module_name(rel)
            self.modules[name] = Module(name, rel.as_posix(), tree, len(text.splitlines()))
        for mod in self.modules.values():
            mod.edges = self._edges(mod)
        #: Names the package's ``__init__`` binds at module level (not lazily).
        self.root_names: set[str] = set()
        if package in self.modules:
            for stmt in self.modules[package].tree.body:
                if isinstance(stmt, ast.Import | ast.ImportFrom):
                    self.root_names |= {(a.asname or a.name).partition(".")[0]
                                        for a in stmt.names}
                elif isinstance(stmt, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                    self.root_names.add(stmt.name)
                elif isinstance(stmt, ast.Assign | ast.AnnAssign):
                    targets = stmt.targets if isinstance(stmt, ast.Assign) else [stmt.target]
                    self.root_names |= {n.id for t in targets for n in ast.walk(t)
                                        if isinstance(n, ast.Name)}

    def _base(self, mod: Module, node: ast.ImportFrom) -> str:
        if not node.level:
            return node.module or ""
        pkg = mod.name if mod.path.endswith("__init__.py") else mod.name.rpartition(".")[0]
        for _ in range(node.level - 1):
            pkg = pkg.rpartition(".")[0]
        return f"{pkg}.{node.module}" if node.module else pkg

    def resolve(self, name: str) -> str | None:
        """The module of this package (or a :data:`PART_ALIASES` name) that ``name`` is or
        lies in; None outside the package."""
        if name != self.package and not name.startswith(self.package + "."):
            return None
        while name:
            if name in self.modules:
                return name
            for alias in PART_ALIASES:
                if name == alias or name.startswith(alias + "."):
                    return alias
            name = name.rpartition(".")[0]
        return None

    def _edges(self, mod: Module) -> list[Edge]:
        edges: list[Edge] = []

        def add(target_name: str, line: int, lazy: bool, names: tuple[str, ...] = ()) -> None:
            target = self.resolve(target_name)
            if target is None or target == mod.name:
                return
            edges.append(Edge(mod.name, mod.path, line, target, lazy, names=names))
            # fem3d.a.b from outside fem3d.a runs fem3d/a/__init__.py first (not fem3d's own
            # __init__, which every module of the package runs)
            parts = target.split(".")
            for k in range(2, len(parts)):
                pkg = ".".join(parts[:k])
                if pkg in self.modules and not mod.name.startswith(pkg + ".") and pkg != mod.name:
                    edges.append(Edge(mod.name, mod.path, line, pkg, lazy,
                                      f"whose package runs first on importing {target}"))

        for node, lazy in _imports(mod.tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    add(alias.name, node.lineno, lazy)
            elif isinstance(node, ast.ImportFrom):
                base = self._base(mod, node)
                for alias in node.names:
                    sub = f"{base}.{alias.name}"
                    if sub in self.modules:
                        add(sub, node.lineno, lazy)
                    else:
                        add(base, node.lineno, lazy, (alias.name,))
            else:
                add(_import_module_literal(node), node.lineno, lazy)
        return edges

    def part(self, module: str) -> str:
        """The part of the package a module belongs to: ``fem3d.a.b`` -> ``"a"``, the package
        itself -> ``""``."""
        if module in PART_ALIASES:
            return PART_ALIASES[module]
        return module.split(".")[1] if "." in module else ""


# ------------------------------------------------------------------------------- the checks


def import_cycles(pkg: Package) -> list[str]:
    """One line per import circle (strongly connected set of modules): a shortest cycle
    through its first module, every edge with its file and line."""
    graph: dict[str, dict[str, Edge]] = {m: {} for m in pkg.modules}
    for mod in pkg.modules.values():
        for e in mod.edges:
            if e.target in graph:
                graph[mod.name].setdefault(e.target, e)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def strongconnect(v: str) -> None:  # Tarjan, iterative over each vertex's successors
        work = [(v, iter(sorted(graph[v])))]
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        while work:
            node, successors = work[-1]
            for w in successors:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                    break
                if w in on_stack:
                    low[node] = min(low[node], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == node:
                            break
                    if len(comp) > 1:
                        components.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            strongconnect(v)

    lines = []
    for comp in components:
        members, start = set(comp), comp[0]
        prev: dict[str, str] = {}
        queue = deque([start])
        while queue:  # breadth first: the shortest way back to start
            v = queue.popleft()
            if start in graph[v]:
                break
            for w in sorted(graph[v]):
                if w in members and w not in prev and w != start:
                    prev[w] = v
                    queue.append(w)
        path = [v]
        while path[-1] != start:
            path.append(prev[path[-1]])
        path.reverse()
        path.append(start)
        steps = [f"{a} -> {b} at {graph[a][b].where()}"
                 for a, b in zip(path, path[1:], strict=False)]
        lines.append(f"import circle {' -> '.join(path)} ({len(comp)} modules in it: "
                     f"{', '.join(comp)}):\n    " + "\n    ".join(steps))
    return lines


def layering_violations(pkg: Package, layers: dict = LAYERS) -> list[str]:
    """One line per import that the layering table does not allow."""
    problems = []
    for mod in pkg.modules.values():
        part = pkg.part(mod.name)
        if part and part not in layers:
            problems.append(f"{mod.path}: part {part!r} of {pkg.package} is not in the "
                            "layering table LAYERS (tests/test_architecture.py): add it")
            continue
        for e in mod.edges:
            target_part = pkg.part(e.target)
            if target_part == part or e.via:  # (a package is in the part of its submodules)
                continue
            if not part:  # the package's own __init__
                if e.lazy or target_part in ROOT_EAGER:
                    continue
                rule = (f"{pkg.package}/__init__.py imports at module level only from "
                        f"{', '.join(ROOT_EAGER)} (expose the rest lazily in __getattr__)")
            elif not target_part:
                lazy_names = sorted(set(e.names) - pkg.root_names)
                if layers[part] == ANYTHING or not lazy_names:
                    continue
                rule = (f"'{part}' imports {', '.join(lazy_names)} from the {pkg.package} "
                        "package itself, whose lazy names may come from any part: import from "
                        "the defining module")
            else:
                allowed = layers[part]
                if allowed == ANYTHING or target_part in allowed:
                    continue
                rule = (f"'{part}' may import only "
                        f"{', '.join(allowed) if allowed else 'nothing else'}, not "
                        f"'{target_part}'")
            problems.append(f"{e.where()} in {mod.name}: {rule}")
    return problems


def _functions(tree: ast.Module):
    """(qualified name, node) of every function and method, nested ones included."""
    def walk(node: ast.AST, prefix: str):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                name = f"{prefix}{child.name}"
                if not isinstance(child, ast.ClassDef):
                    yield name, child
                yield from walk(child, name + ".")
            else:
                yield from walk(child, prefix)

    yield from walk(tree, "")


def size_violations(pkg: Package, allowed: dict[str, str] = SIZE_ALLOWED,
                    max_function: int = MAX_FUNCTION_LINES,
                    max_module: int = MAX_MODULE_LINES) -> list[str]:
    """One line per function or module over its limit and not allowed, and per allowance
    that is no longer needed."""
    problems, used = [], set()
    for mod in pkg.modules.values():
        if mod.n_lines > max_module:
            if mod.path in allowed:
                used.add(mod.path)
            else:
                problems.append(f"{mod.path}: module of {mod.n_lines} lines (limit {max_module})")
        for qualname, node in _functions(mod.tree):
            n = node.end_lineno - node.lineno + 1
            if n <= max_function:
                continue
            key = f"{mod.path}::{qualname}"
            if key in allowed:
                used.add(key)
            else:
                problems.append(f"{mod.path}:{node.lineno}: function {qualname} of {n} lines "
                                f"(limit {max_function})")
    for key in sorted(set(allowed) - used):
        problems.append(f"SIZE_ALLOWED entry {key!r} is not over its limit (or is gone): "
                        "remove it")
    return problems


# ------------------------------------------------------------------------ fem3d itself


@pytest.fixture(scope="module")
def fem3d_package() -> Package:
    return Package(ROOT, PACKAGE)


def test_no_import_cycles(fem3d_package):
    cycles = import_cycles(fem3d_package)
    assert not cycles, f"{len(cycles)} import circle(s):\n" + "\n".join(cycles)


def test_parts_import_only_lower_layers(fem3d_package):
    problems = layering_violations(fem3d_package)
    assert not problems, f"{len(problems)} import(s) break the layering:\n" + "\n".join(problems)


def test_functions_and_modules_within_size(fem3d_package):
    problems = size_violations(fem3d_package)
    assert not problems, f"{len(problems)} size problem(s):\n" + "\n".join(problems)


def test_layering_table_is_consistent():
    known = set(LAYERS)
    for part, allowed in LAYERS.items():
        if allowed != ANYTHING:
            assert part not in allowed, f"{part} lists itself"
            assert set(allowed) <= known, f"{part} allows unknown {set(allowed) - known}"
    assert set(PART_ALIASES.values()) <= known
    assert set(ROOT_EAGER) <= known
    assert all(reason.strip() for reason in SIZE_ALLOWED.values())


# ------------------------------------------------------------- the checker on planted code


def _plant(tmp_path: Path, files: dict[str, str]) -> Package:
    for rel, text in files.items():
        path = tmp_path / "fem3d" / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    for d in sorted({p.parent for p in (tmp_path / "fem3d").rglob("*.py")}):
        (d / "__init__.py").touch()
    return Package(tmp_path, "fem3d")


def test_checker_finds_a_planted_cycle_hidden_in_a_function(tmp_path):
    pkg = _plant(tmp_path, {
        "kernels/dispatch.py": "from fem3d.kernels import schedule\n",
        "kernels/schedule.py": "def f():\n    from .dispatch import g\n    return g\n",
        "io/files.py": "import fem3d.errors\n",
        "errors.py": "",
    })
    cycles = import_cycles(pkg)
    assert len(cycles) == 1
    assert "fem3d.kernels.dispatch -> fem3d.kernels.schedule -> fem3d.kernels.dispatch" in \
        cycles[0]
    assert "fem3d/kernels/schedule.py:2 (function-level import of fem3d.kernels.dispatch)" in \
        cycles[0]
    assert "fem3d/kernels/dispatch.py:1 (import of fem3d.kernels.schedule)" in cycles[0]


def test_checker_finds_a_cycle_through_a_package_init(tmp_path):
    pkg = _plant(tmp_path, {
        "scene/__init__.py": "from fem3d.scene.build import build\n",
        "scene/build.py": "from fem3d.mesh.tet import tetrahedralize\n",
        "scene/spec.py": "",
        "mesh/tet.py": "from fem3d.scene.spec import Spec\n",
    })
    cycles = import_cycles(pkg)
    assert len(cycles) == 1 and "fem3d.mesh.tet -> fem3d.scene" in cycles[0]
    assert "whose package runs first on importing fem3d.scene.spec" in cycles[0]


def test_checker_finds_planted_forbidden_imports(tmp_path):
    pkg = _plant(tmp_path, {
        "errors.py": "",
        "app/cli.py": "from fem3d.solve import newton\n",
        "solve/newton.py": "from ..errors import Fem3dError\nfrom ..physics import terms\n",
        "physics/terms.py": "import numpy\n\n\ndef f():\n    from fem3d.app.cli import main\n",
        "physics/mats.py": "import importlib\n"
                           "m = importlib.import_module(f'fem3d._generated.{1}')\n",
        "kernels/dispatch.py": "from fem3d.scene import spec\n",
        "scene/spec.py": "import typing\nif typing.TYPE_CHECKING:\n"
                         "    from fem3d.app import cli\nelse:\n    from fem3d import errors\n",
        "mesh/io.py": "from fem3d import Scene\n",
        "io/rundir.py": "from fem3d import Fem3dError, __version__\n",
        "widgets.py": "",
        "__init__.py": "from fem3d.errors import Fem3dError\nfrom fem3d.solve import newton\n"
                       "__version__ = '0'\n\n\n"
                       "def __getattr__(name):\n    from fem3d.scene.spec import Scene\n",
    })
    problems = layering_violations(pkg)
    text = "\n".join(problems)
    assert ("fem3d/physics/terms.py:5 (function-level import of fem3d.app.cli) in "
            "fem3d.physics.terms: 'physics' may import only errors, kernels, mesh, io, not "
            "'app'") in text
    assert ("fem3d/kernels/dispatch.py:1 (import of fem3d.scene.spec) in fem3d.kernels.dispatch:"
            " 'kernels' may import only errors, not 'scene'") in text
    assert "fem3d/mesh/io.py:1 (import of fem3d) in fem3d.mesh.io: 'mesh' imports Scene from " \
        "the fem3d package itself" in text
    assert "fem3d/widgets.py: part 'widgets' of fem3d is not in the layering table" in text
    assert "fem3d/__init__.py:2 (import of fem3d.solve.newton)" in text
    assert "fem3d/__init__.py imports at module level only from errors" in text
    # allowed: app anything; solve -> errors, physics; the generated kernels count as kernels
    # (physics may import them); TYPE_CHECKING; the root's lazy __getattr__; the
    # root's eagerly bound names
    assert not [p for p in problems if p.startswith(("fem3d/app/", "fem3d/solve/",
                                                     "fem3d/physics/mats.py", "fem3d/io/",
                                                     "fem3d/scene/",
                                                     "fem3d/__init__.py:7"))]
    assert len(problems) == 5, text
    cycles = import_cycles(pkg)  # the forbidden physics -> app closes a circle, too
    assert len(cycles) == 1 and "fem3d.physics.terms -> fem3d.app.cli at" in cycles[0]


def test_checker_finds_planted_oversize_and_stale_allowances(tmp_path):
    body = "".join(f"    x{i} = {i}\n" for i in range(6))
    pkg = _plant(tmp_path, {
        "solve/big.py": f"class A:\n    def step(self):\n{body.replace('    ', '        ')}"
                        f"\n\ndef small():\n    pass\n",
        "solve/ok.py": f"def fine():\n{body}",
    })
    allowed = {"fem3d/solve/ok.py::fine": "planted", "fem3d/solve/ok.py": "planted"}
    problems = size_violations(pkg, allowed, max_function=5, max_module=8)
    assert problems[0] == "fem3d/solve/big.py: module of 12 lines (limit 8)"
    assert problems[1] == "fem3d/solve/big.py:2: function A.step of 7 lines (limit 5)"
    assert problems[2].startswith("SIZE_ALLOWED entry 'fem3d/solve/ok.py' is not over its limit")
    assert len(problems) == 3, problems
