"""The layers of docs/dev/architecture.md, checked on the source: every module under fuelid/ is parsed with `ast`
(imports at the top of a file and inside functions alike) and the module graph built from it must satisfy

- the layers import downwards only (foundation → dbc → logger → ident → fleet; sim beside, over the logger);
- the logger (fuelid.logger) imports nothing from the identification package (fuelid.ident);
- nothing below the command line imports the command line (fuelid.cli, fuelid.commands.*);
- no two modules import each other, directly or through a longer cycle (function-level imports included);
- the diagnosis package's modules import only those its docstring lists before them (it follows the loop);
- an import inside a function names one of the optional or heavy dependencies in LAZY_IMPORTS (never to dodge
  a cycle: those imports count in the cycle check too);
- no `except` catches ValueError next to the FuelidError family (fuelid/errors.py: one error policy).

And the built wheel puts one import name into site-packages: fuelid.
"""
from __future__ import annotations

import ast
import os
import shutil
import zipfile
from pathlib import Path

import pytest

import fuelid
import fuelid.ident.diagnosis

PACKAGE = Path(fuelid.__file__).resolve().parent  # the source tree, or site-packages after `pip install .`
ROOT = PACKAGE.parent
SOURCE = Path(__file__).resolve().parents[1]  # the checkout holding these tests and pyproject.toml

# What may be imported inside a function, and why: a third-party package of an optional extra (pyproject.toml)
# that a base install lacks or that is heavy to load where it is not used (the in-cab daemon, `fuelid --help`,
# readers); and the few fuelid modules that exist to wrap one of those, named with the package they carry.
LAZY_IMPORTS = {
    "asammdf": "optional extra [mf4]: MF4 files",
    "dask": "optional extra [fleet]: the refit cluster",
    "distributed": "optional extra [fleet] (dask): the refit cluster",
    "uvicorn": "optional extra [fleet]: the fleet server",
    "plotly": "heavy (several MB of plotly.js): only the HTML report needs it",
    "foxglove": "heavy to load: MCAP writers need the SDK, readers do not",
    "serial": "pyserial opens ports only: parsing and replaying meter captures do not need it",
    "scipy": "scipy.signal, scipy.io: kept off the in-cab estimator's path, loaded by the features using them",
    "pyarrow": "heavy to load: only the dataset CSV writer (`fuelid dataset -o x.csv`) needs it",
    "fuelid.fleet.app": "FastAPI (optional extra [fleet]): `fuelid serve` only",
    "fuelid.fleet.console": "FastAPI (optional extra [fleet]): `fuelid serve` only",
    "fuelid.fleet.auth": "SQLAlchemy (optional extra [fleet]): `fuelid token` offline only",
    "fuelid.fleet.db": "SQLAlchemy (optional extra [fleet]): `fuelid token` offline only",
    "fuelid.fleet.limits": "uvicorn (optional extra [fleet]): `fuelid serve` only",
    "fuelid.fleet.jobs": "Dask and the identification stack (numba, SciPy): on the workers, not the server",
    "fuelid.ident.rpem": "numba-compiled (seconds to load in the cab): with an estimator, not with ident.live",
    "fuelid.ident.kalman": "numba-compiled (as ident.rpem)",
    "fuelid.ident.enginemap": "SciPy (the map's fit): ident.live loads it with an engine model only",
    "fuelid.ident.effects": "SciPy and cantools (ident.enginemap, the DBC): ident.live loads it with an engine model only",
}


def lazy_allowed(target: str) -> bool:
    return target in LAZY_IMPORTS or target.split(".")[0] in LAZY_IMPORTS



def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def first_party(name: str, modules: set[str]) -> str:
    """The module `name` refers to: itself, or the package holding it (an attribute imported from a module)."""
    while name not in modules and "." in name:
        name = name.rsplit(".", 1)[0]
    return name


class Imports(ast.NodeVisitor):
    """Every import in a module as (imported name, line, inside a function?)."""

    def __init__(self, module: str, is_package: bool):
        self.module, self.is_package = module, is_package
        self.found: list[tuple[str, int, bool]] = []
        self._depth = 0

    def _function(self, node):
        self._depth += 1
        self.generic_visit(node)
        self._depth -= 1

    visit_FunctionDef = visit_AsyncFunctionDef = visit_Lambda = _function

    def visit_Import(self, node):
        for alias in node.names:
            self.found.append((alias.name, node.lineno, self._depth > 0))

    def visit_ImportFrom(self, node):
        if node.module == "__future__":
            return
        base = node.module or ""
        if node.level:  # relative: resolved against this module's package
            package = self.module.split(".")
            package = package if self.is_package else package[:-1]
            package = package[: len(package) - (node.level - 1)]
            base = ".".join(package + ([base] if base else []))
        for alias in node.names:
            self.found.append((f"{base}.{alias.name}", node.lineno, self._depth > 0))


def collect(paths: dict[str, Path], trees: dict[str, ast.Module]):
    """{module: [(imported module, line, in function)]}: first-party names resolved to modules, third-party
    names to their top-level package."""
    modules = set(paths)
    graph = {}
    for module, path in paths.items():
        visitor = Imports(module, path.name == "__init__.py")
        visitor.visit(trees[module])
        edges = []
        for name, line, lazy in visitor.found:
            target = first_party(name, modules) if name.split(".")[0] == "fuelid" else name.split(".")[0]
            if target != module:
                edges.append((target, line, lazy))
        graph[module] = edges
    return graph


PATHS = {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}
TREES = {module: ast.parse(path.read_text(), str(path)) for module, path in PATHS.items()}
GRAPH = collect(PATHS, TREES)


def edges(lazy: bool | None = None):
    for module, targets in GRAPH.items():
        for target, line, in_function in targets:
            if lazy is None or in_function == lazy:
                yield module, target, line


def is_cli(module: str) -> bool:
    return module == "fuelid.cli" or module == "fuelid.commands" or module.startswith("fuelid.commands.")


def where(module: str, target: str, line: int) -> str:
    return f"{module} -> {target} ({module.replace('.', '/')}.py:{line})"


def test_the_graph_covers_the_package():
    assert {"fuelid", "fuelid.cli", "fuelid.logger.daemon", "fuelid.ident.live", "fuelid.fleet.jobs"} <= set(GRAPH)
    assert "fuelid.errors" in {t for t, _, _ in GRAPH["fuelid.cli"]}  # a known edge is seen
    unplaced = [m for m in GRAPH if not layer(m) and not is_cli(m)]
    assert not unplaced, f"modules in no layer (add them to FOUNDATION or LAYERS): {unplaced}"


def test_logger_imports_nothing_from_ident():
    bad = [where(m, t, line) for m, t, line in edges()
           if m.startswith("fuelid.logger") and (t == "fuelid.ident" or t.startswith("fuelid.ident."))]
    assert not bad, "the logger must not import the identification package; pass it in (logger.daemon.Estimator):\n" \
        + "\n".join(bad)


# Each layer (docs/dev/architecture.md) and the layers it may import; the command line on top may import them all.
FOUNDATION = {"fuelid", "fuelid.blas", "fuelid.errors", "fuelid.output", "fuelid.parallel", "fuelid.paths",
              "fuelid.progress"}
LAYERS = {
    "foundation": set(),
    "dbc": {"foundation"},
    "logger": {"foundation", "dbc"},
    "ident": {"foundation", "dbc", "logger"},
    "fleet": {"foundation", "dbc", "logger", "ident"},
    "sim": {"foundation", "dbc", "logger"},  # beside the stack: makes recordings, never reads models
}


def layer(module: str) -> str | None:
    """The layer of a fuelid module; None for the command line and for third-party names."""
    if module in FOUNDATION:
        return "foundation"
    parts = module.split(".")
    return parts[1] if parts[0] == "fuelid" and len(parts) > 1 and parts[1] in LAYERS else None


def test_layers_point_one_way():
    bad = [where(m, t, line) for m, t, line in edges()
           if layer(m) and layer(t) and layer(t) != layer(m) and layer(t) not in LAYERS[layer(m)]]
    assert not bad, ("an import reaches up or across the layers (foundation → dbc → logger → ident → fleet; sim "
                     "beside): pass the upper part in instead:\n" + "\n".join(bad))


DIAGNOSIS = "fuelid.ident.diagnosis"


def diagnosis_order() -> list[str]:
    """The diagnosis package's modules in the order its docstring lists them (a name, then two spaces or more)."""
    listing = fuelid.ident.diagnosis.__doc__.split("before it:", 1)[1]
    return [f"{DIAGNOSIS}.{line.split()[0]}" for line in listing.splitlines()
            if line.startswith("    ") and not line.startswith("     ") and "  " in line.strip()]


def test_the_diagnosis_modules_follow_the_loop():
    order = diagnosis_order()
    assert set(order) == {m for m in GRAPH if m.startswith(DIAGNOSIS + ".")}, "list every module in the docstring"
    bad = [where(m, t, line) for m, t, line in edges() if m in order and t in order and order.index(t) >= order.index(m)]
    assert not bad, f"a diagnosis module imports one listed after it ({DIAGNOSIS} docstring):\n" + "\n".join(bad)


def test_nothing_below_the_cli_imports_the_cli():
    bad = [where(m, t, line) for m, t, line in edges() if is_cli(t) and not is_cli(m)]
    assert not bad, "only fuelid.cli and fuelid.commands.* may import the command line:\n" + "\n".join(bad)


def test_imports_inside_functions_are_only_optional_or_heavy_dependencies():
    bad = [where(m, t, line) for m, t, line in edges(lazy=True)
           if not lazy_allowed(t)]
    assert not bad, ("an import inside a function is only for an optional or heavy dependency "
                     f"({', '.join(sorted(LAZY_IMPORTS))}); move these to the top of the file:\n" + "\n".join(bad))


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
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


def test_cycles_finds_direct_and_longer_cycles():
    assert cycles({"a": {"b"}, "b": {"a"}, "c": {"a"}}) == [["a", "b"]]
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": {"c"}}) == []


def test_no_import_cycles():
    graph: dict[str, set[str]] = {m: set() for m in GRAPH}
    for m, t, _ in edges():
        # a package's own __init__ importing from it is no cycle; neither is a pending ident edge, until merged
        if t in GRAPH and not m.startswith(t + "."):
            graph[m].add(t)
    found = cycles(graph)
    detail = ["  " + " <-> ".join(c) + ": " + "; ".join(where(m, t, line) for m, t, line in edges()
                                                         if m in c and t in c) for c in found]
    assert not found, "modules that import each other (directly or in a cycle):\n" + "\n".join(detail)


def error_family() -> set[str]:
    """Names of FuelidError and every class deriving from it in the package."""
    family, grew = {"FuelidError"}, True
    while grew:
        grew = False
        for tree in TREES.values():
            for node in ast.walk(tree):
                if isinstance(node, ast.ClassDef) and node.name not in family and any(
                        getattr(b, "id", getattr(b, "attr", None)) in family for b in node.bases):
                    family.add(node.name)
                    grew = True
    return family


def test_domain_errors_are_caught_as_one_family():
    """Code handling a user's error catches the FuelidError family; ValueError next to it means something below
    still raises ValueError for a domain error (raise fuelid.errors.InputError there instead)."""
    family = error_family()
    assert {"InputError", "JobError", "UploadError"} <= family
    bad = []
    for module, tree in TREES.items():
        for node in ast.walk(tree):
            if isinstance(node, ast.ExceptHandler) and isinstance(node.type, ast.Tuple):
                names = {getattr(e, "id", getattr(e, "attr", None)) for e in node.type.elts}
                if "ValueError" in names and names & family:
                    bad.append(f"{module.replace('.', '/')}.py:{node.lineno}")
    assert not bad, "except (FuelidError, ValueError): make the code below raise the family:\n" + "\n".join(bad)


def test_the_wheel_installs_one_import_name(tmp_path):
    """top_level.txt of the built wheel: fuelid alone (nothing else of ours in site-packages)."""
    if not (SOURCE / "pyproject.toml").exists():
        pytest.skip("the tests run outside a source checkout: no pyproject.toml to build")
    build = pytest.importorskip("setuptools.build_meta")
    src, out = tmp_path / "src", tmp_path / "dist"  # a copy: building writes build/ and *.egg-info next to it
    shutil.copytree(SOURCE / "fuelid", src / "fuelid", ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(SOURCE / name, src)
    out.mkdir()
    cwd = Path.cwd()
    os.chdir(src)
    try:
        name = build.build_wheel(str(out))
    finally:
        os.chdir(cwd)
    with zipfile.ZipFile(out / name) as wheel:
        top = [n for n in wheel.namelist() if n.endswith(".dist-info/top_level.txt")]
        assert wheel.read(top[0]).decode().split() == ["fuelid"]
        roots = {n.split("/")[0] for n in wheel.namelist() if not n.split("/")[0].endswith(".dist-info")}
    assert roots == {"fuelid"}
