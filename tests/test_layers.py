"""The layers of docs/code.md, enforced: every import of every module of the installed package (read
with ``ast``: at module level and inside functions) goes to the module's own layer or to one that
its layer may import; and no module imports itself back through others.

Run as a script, it prints the graph of a checkout's top-level folders (edges, and a cycle if
there is one), e.g. before and after a change of layout:

    python tests/test_layers.py [ROOT]          # ROOT: a checkout (default: this one)
"""

from __future__ import annotations

import ast
import importlib.util
import pkgutil
import sys
import tomllib
from pathlib import Path

#: Each layer and the module prefixes in it; a module belongs to the layer of its longest matching
#: prefix (``spherebench.eval`` itself is the metrics' package: it re-exports them).
LAYERS = {
    "core": ("spherebench",),
    "data": ("spherebench.datasets",),
    "method": ("spherebench.method",),
    "metrics": ("spherebench.eval", "spherebench.eval.metrics"),
    "baselines": ("spherebench.baselines",),
    "bench": ("spherebench.eval.bench",),
    "drivers": ("spherebench.scripts", "spherebench.scripts.cli"),
}
#: The layers each layer may import besides its own. ``spherebench.scripts.cli`` loads the drivers by name
#: (importlib) only when their subcommand runs: no import statement, so no edge.
MAY_IMPORT = {
    "core": (),
    "data": ("core",),
    "method": ("core",),
    "metrics": ("core",),
    "baselines": ("core", "data", "metrics"),
    "bench": ("core", "data", "method", "metrics", "baselines"),
    "drivers": ("core", "data", "method", "metrics", "baselines", "bench"),
}
#: The repository's top-level folders that hold packages (the rest of ``spherebench.*`` lives in
#: spherebench/, the core's folder), and the subfolders that are layers of their own.
FOLDERS = ("datasets", "method", "baselines", "eval", "scripts")
LAYER_SUBFOLDERS = {"eval": ("metrics", "bench")}
ROOT = Path(__file__).resolve().parents[1]


def layer_of(module: str) -> str | None:
    """The layer of a dotted module name (None: outside the package)."""
    best = None
    for layer, prefixes in LAYERS.items():
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and (best is None or len(p) > len(best[1])):
                best = (layer, p)
    return best[0] if best else None


def folder_of(module: str, packages: set[str]) -> str:
    """The folder of the checkout that holds a ``spherebench`` module: a top-level one, or one of
    its subfolders that is a layer (``eval/metrics``, ``eval/bench``; a module of that name is not
    one). packages: the names that are packages."""
    parts = module.split(".")
    if len(parts) < 2 or parts[1] not in FOLDERS:
        return "spherebench"
    sub = ".".join(parts[:3])
    if len(parts) > 2 and parts[2] in LAYER_SUBFOLDERS.get(parts[1], ()) and sub in packages:
        return f"{parts[1]}/{parts[2]}"
    return parts[1]


def folders(modules: dict[str, tuple[Path, bool]]):
    """folder_of for these modules ({name: (source file, is a package)})."""
    packages = {name for name, (_, is_package) in modules.items() if is_package}
    return lambda module: folder_of(module, packages)


def module_imports(path: Path, module: str, is_package: bool, known: set[str]) -> list[tuple[str, int]]:
    """(imported module, line) for every import in a module's source that names a ``spherebench``
    module, wherever it stands (functions and classes included). ``from P import x`` counts as an
    import of P.x when that is a module in ``known``, else of P."""
    found = []
    package = module if is_package else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the module's package, up level - 1
                anchor = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{anchor}.{base}" if base else anchor
            for a in node.names:
                sub = f"{base}.{a.name}"
                found.append((sub if sub in known else base, node.lineno))
        elif isinstance(node, ast.Call) and _imports_by_name(node):
            named = _literal_head(node.args[0]).rstrip(".")  # f"spherebench.scripts.{name}" -> the package
            if named:
                found.append((named, node.lineno))
    return [(m, line) for m, line in found if m == "spherebench" or m.startswith("spherebench.")]


def _imports_by_name(call: ast.Call) -> bool:
    """A call of importlib.import_module or __import__ with an argument: an import that no import
    statement shows."""
    f = call.func
    name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
    return name in ("import_module", "__import__") and bool(call.args)


def _literal_head(node: ast.expr) -> str:
    """The text a string argument starts with, as far as it is literal (an f-string's leading text)."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value
    if isinstance(node, ast.JoinedStr):
        head = ""
        for part in node.values:
            if not (isinstance(part, ast.Constant) and isinstance(part.value, str)):
                break
            head += part.value
        return head
    return ""


def import_edges(modules: dict[str, tuple[Path, bool]]) -> list[tuple[str, str, int]]:
    """(importer, imported, line) of every import between the given modules ({name: (source file,
    is a package)})."""
    known = set(modules)
    return list(dict.fromkeys((name, target, line) for name, (path, is_package) in sorted(modules.items())
                              for target, line in module_imports(path, name, is_package, known) if target != name))


def violations(edges) -> list[str]:
    """One line per edge against the declared layers: the importer, its line, what it imports."""
    out = []
    for importer, imported, line in edges:
        src, dst = layer_of(importer), layer_of(imported)
        if src is None or dst is None:
            out.append(f"{importer}:{line} imports {imported}: a module in no layer (add it to LAYERS)")
        elif dst != src and dst not in MAY_IMPORT[src]:
            allowed = ", ".join(MAY_IMPORT[src]) or "nothing else"
            out.append(f"{importer}:{line} imports {imported} ({src} -> {dst}; {src} may import {allowed})")
    return out


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """A cycle of a directed graph ({node: successors}) as [a, b, ..., a], or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node):
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        state[node] = 2
        path.pop()
        return None

    for node in sorted(graph):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return None


def graph_of(edges, key=lambda m: m) -> dict[str, set[str]]:
    """The edges' graph with each module mapped by ``key`` (e.g. to its folder), self-loops left out."""
    graph: dict[str, set[str]] = {}
    for a, b, _ in edges:
        ka, kb = key(a), key(b)
        if ka != kb:
            graph.setdefault(ka, set()).add(kb)
    return graph


def installed_modules() -> dict[str, tuple[Path, bool]]:
    """Every module of the installed ``spherebench`` package: {name: (source file, is a package)}.
    Its subpackages are looked up by name (an editable install maps each folder to its own path)."""
    modules = {}
    todo = ["spherebench", *(f"spherebench.{f}" for f in FOLDERS)]
    while todo:
        spec = importlib.util.find_spec(todo.pop())
        modules[spec.name] = (Path(spec.origin), True)
        for info in pkgutil.iter_modules(spec.submodule_search_locations, spec.name + "."):
            if info.ispkg:
                todo.append(info.name)
            elif info.name not in modules:
                modules[info.name] = (Path(importlib.util.find_spec(info.name).origin), False)
    return modules


def checkout_modules(root: Path) -> dict[str, tuple[Path, bool]]:
    """Every module of a checkout, from its pyproject.toml's packages and package-dir (any layout)."""
    tool = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]
    dirs = tool.get("package-dir", {})
    modules = {}
    for package in tool["packages"]:
        mapped = max((p for p in dirs if package == p or package.startswith(p + ".")), key=len, default=None)
        rest = package[len(mapped):].lstrip(".").split(".") if mapped else package.split(".")
        folder = root.joinpath(dirs[mapped] if mapped else "", *[r for r in rest if r])
        for f in sorted(folder.glob("*.py")):
            name = package if f.name == "__init__.py" else f"{package}.{f.stem}"
            modules[name] = (f, f.name == "__init__.py")
    return modules


def folder_report(modules: dict[str, tuple[Path, bool]]) -> str:
    """The folder graph of these modules: each edge, their count and a cycle (or none)."""
    folder = folders(modules)
    graph = graph_of(import_edges(modules), folder)
    edges = sorted((a, b) for a, succ in graph.items() for b in succ)
    pairs = {frozenset(e) for e in edges}
    n = len({folder(m) for m in modules})
    cycle = find_cycle(graph)
    return "\n".join([f"{a} -> {b}" for a, b in edges] + [
        f"{len(edges)} edges between {n} folders ({len(pairs)} of {n * (n - 1) // 2} pairs joined)",
        "cycle: " + (" -> ".join(cycle) if cycle else "none")])


# ---- the tests

def test_every_import_keeps_to_the_layers():
    bad = violations(import_edges(installed_modules()))
    assert not bad, "imports against the layers of docs/code.md:\n" + "\n".join(bad)


def test_no_module_imports_itself_back():
    cycle = find_cycle(graph_of(import_edges(installed_modules())))
    assert cycle is None, "an import cycle: " + " -> ".join(cycle)


def test_the_folders_form_a_dag():
    modules = installed_modules()
    cycle = find_cycle(graph_of(import_edges(modules), folders(modules)))
    assert cycle is None, "the folders import in a cycle: " + " -> ".join(cycle)


def test_the_declared_layers_form_a_dag():
    assert find_cycle({k: set(v) for k, v in MAY_IMPORT.items()}) is None
    assert set(MAY_IMPORT) == set(LAYERS) and all(set(v) <= set(LAYERS) for v in MAY_IMPORT.values())


def test_every_module_is_walked():
    modules = installed_modules()
    assert set(modules) == set(checkout_modules(ROOT))  # the installed package is this checkout's
    assert {"spherebench.scripts.cli", "spherebench.datasets.inout", "spherebench.method.detector",
            "spherebench.eval.metrics.coco_eval", "spherebench.eval.bench.registry",
            "spherebench.baselines.circlenet.infer", "spherebench.scripts.detect"} <= set(modules)
    assert layer_of("spherebench.eval") == "metrics" and layer_of("spherebench.eval.bench.runner") == "bench"
    assert layer_of("spherebench.scripts.cli") == "drivers" and layer_of("spherebench.camera") == "core"


#: The most lines a module of the package holds (the detector's stage modules included): one job each.
MAX_MODULE_LINES = 700


def test_every_module_keeps_to_one_job_in_at_most_700_lines():
    long = {name: n for name, (path, _) in installed_modules().items()
            if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


def test_the_package_imports_no_driver_by_name():
    """The dispatcher of the command lives with the drivers: below them, no module names
    ``spherebench.scripts`` in an import, an ``importlib`` call or any string (the core once loaded
    the drivers by name)."""
    named = []
    for name, (path, _) in installed_modules().items():
        if layer_of(name) == "drivers":
            continue
        tree = ast.parse(path.read_text(), str(path))
        named += [f"{name}:{node.lineno}" for node in ast.walk(tree)
                  if isinstance(node, ast.Constant) and isinstance(node.value, str)
                  and node.value.startswith("spherebench.scripts")]
    assert not named, "modules below the drivers that name them: " + ", ".join(named)


def test_every_driver_is_a_subcommand_or_a_make_target():
    from spherebench.scripts import cli
    drivers = {name.rpartition(".")[2] for name in installed_modules() if name.startswith("spherebench.scripts.")}
    subcommands = {module for _, module, _ in cli.COMMANDS}
    makefile = (ROOT / "Makefile").read_text()
    targets = {d for d in drivers if f"-m spherebench.scripts.{d}" in makefile}
    assert drivers - {"cli"} == subcommands | targets and not subcommands & targets


def test_a_bad_edge_is_named(tmp_path):
    """The check can fail: an import up the layers, inside a function of a temporary module, is
    found and named with its line."""
    bad = tmp_path / "fake.py"
    bad.write_text("import numpy\nfrom spherebench.camera import Intrinsics\n\n\ndef f():\n"
                   "    from spherebench.method import detect\n    return detect\n\n\n"
                   "def g(name):\n    return importlib.import_module(f'spherebench.scripts.{name}')\n")
    modules = {"spherebench.datasets.fake": (bad, False), "spherebench.method": (tmp_path / "none.py", True)}
    edges = [(importer, target, line) for importer, (path, pkg) in modules.items() if path.is_file()
             for target, line in module_imports(path, importer, pkg, set(modules))]
    assert edges == [("spherebench.datasets.fake", "spherebench.camera", 2),
                     ("spherebench.datasets.fake", "spherebench.method", 6),
                     ("spherebench.datasets.fake", "spherebench.scripts", 11)]
    assert violations(edges) == ["spherebench.datasets.fake:6 imports spherebench.method (data -> method; data may "
                                 "import core)",
                                 "spherebench.datasets.fake:11 imports spherebench.scripts (data -> drivers; data may "
                                 "import core)"]
    assert violations([("spherebench.baselines.hough", "spherebench.eval.bench.report", 3)]) == [
        "spherebench.baselines.hough:3 imports spherebench.eval.bench.report (baselines -> bench; baselines may "
        "import core, data, metrics)"]
    assert violations([("spherebench.baselines.hough", "spherebench.eval.metrics.coco_eval", 3)]) == []


def test_relative_imports_and_cycles_are_read(tmp_path):
    src = tmp_path / "m.py"
    src.write_text("from . import sibling\nfrom ..camera import Intrinsics\n")
    known = {"spherebench.eval.sibling", "spherebench.camera"}
    assert module_imports(src, "spherebench.eval.m", False, known) == [("spherebench.eval.sibling", 1),
                                                                      ("spherebench.camera", 2)]
    assert folder_of("spherebench.eval.bench.registry", {"spherebench.eval.bench"}) == "eval/bench"
    assert folder_of("spherebench.eval.bench", set()) == "eval"  # a module of that name, in eval/
    assert folder_of("spherebench.baselines.circlenet.infer", set()) == "baselines"
    assert folder_of("spherebench.scripts.cli", set()) == "scripts" and folder_of("spherebench.caches", set()) == "spherebench"
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}}) is None


if __name__ == "__main__":
    print(folder_report(checkout_modules(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT)))
