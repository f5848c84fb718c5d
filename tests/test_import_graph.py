"""The house inside the packages, checked on the source: no import circle, no private name imported from
another module, every folder marker named in its home module only, and functions a reader can hold in
mind. The allowlists record what is left; they may only shrink (a new entry fails here).

Import circles count every import: module level, function level and under ``TYPE_CHECKING`` (a circle
that only runs late is still a circle a reader has to untangle). A private module with public names
(``optics/_kernels.py``, scikit-image's convention) is fine: only names with a leading underscore count.
"""

from __future__ import annotations

import ast

import pytest

from test_layering import PACKAGE_ROOT, _module_name, _source_files

#: Import circles left (sets of modules); may only shrink.
ALLOWED_CIRCLES: list[set[str]] = []
#: Private names imported from another module, ``"importer <- module: name"``; may only shrink.
ALLOWED_PRIVATE_IMPORTS: set[str] = set()
#: Folder markers (file or folder names that say what kind of folder a path is) -> their home module:
#: only there (and in the writers that import it from there) is the name spelled out.
MARKER_HOMES = {
    "manifest.json": "polarface.capture.manifest",
    "derived.zarr": "polarface.capture.manifest",
    "simulation.json": "polarface.simulate.layout",
    "ground_truth": "polarface.simulate.layout",
    "mesh_rest.obj": "polarface.simulate.layout",
    "imported.json": "polarface.pipeline.inputs.imported",
    "result.json": "polarface.results.layout",
    "geometry.json": "polarface.results.layout",
    "tracking.json": "polarface.results.layout",
}
#: The longest function, in lines (decorators excluded).
MAX_FUNCTION_LINES = 100


def _parsed() -> dict[str, tuple[ast.Module, bool]]:
    return {_module_name(path): (ast.parse(path.read_text(encoding="utf-8")), path.name == "__init__.py")
            for path in _source_files()}


def _resolved(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    parts = (module if is_package else module.rsplit(".", 1)[0]).split(".")
    base = parts[: len(parts) - node.level + 1]
    return ".".join([*base, node.module] if node.module else base)


def _owner(name: str, modules: set[str]) -> str:
    """The module ``name`` (a module or a name inside one) belongs to."""
    while name not in modules and "." in name:
        name = name.rsplit(".", 1)[0]
    return name


def import_graph(parsed: dict[str, tuple[ast.Module, bool]]) -> tuple[dict[str, set[str]], list[str]]:
    """Module -> the polarface modules it imports (anywhere in its text), and the private imports
    (``"importer <- module: name"``) of names with a leading underscore from another module."""
    modules = set(parsed)
    edges: dict[str, set[str]] = {module: set() for module in modules}
    private = []
    for module, (tree, is_package) in parsed.items():
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                targets = [_owner(alias.name, modules) for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                source = _resolved(module, is_package, node)
                targets = []
                for alias in node.names:
                    submodule = f"{source}.{alias.name}"
                    if submodule in modules:
                        targets.append(submodule)
                        continue
                    owner = _owner(source, modules)
                    targets.append(owner)
                    if alias.name.startswith("_") and not alias.name.startswith("__") and owner in modules:
                        private.append(f"{module} <- {owner}: {alias.name}")
            else:
                continue
            edges[module] |= {t for t in targets if t in modules and t != module}
    return edges, sorted(private)


def circles(edges: dict[str, set[str]]) -> list[set[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[set[str]] = []
    for root in sorted(edges):
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = set()
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.add(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(component)
    return found


def marker_literals(tree: ast.Module, module: str) -> list[str]:
    """Folder markers spelled out in ``module`` outside their home: a marker string joined onto a path
    (``root / "manifest.json"``) or assigned to a name (``X = "manifest.json"``). Other uses (a JSON key
    ``"ground_truth"``, a docstring) are not folder markers."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div):
            candidates = [node.left, node.right]
        elif isinstance(node, ast.Assign | ast.AnnAssign) and node.value is not None:
            candidates = [node.value]
        else:
            continue
        for value in candidates:
            if isinstance(value, ast.Constant) and value.value in MARKER_HOMES:
                if MARKER_HOMES[value.value] != module:
                    found.append(f"{module}:{value.lineno} spells {value.value!r} "
                                 f"(its home is {MARKER_HOMES[value.value]})")
    return found


def long_functions(tree: ast.Module, module: str) -> list[str]:
    return [f"{module}:{node.lineno} {node.name} has {node.end_lineno - node.lineno + 1} lines"
            for node in ast.walk(tree)
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
            and node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES]


@pytest.fixture(scope="module")
def parsed():
    return _parsed()


def test_no_import_circle(parsed):
    edges, _ = import_graph(parsed)
    left = circles(edges)
    new = [sorted(c) for c in left if c not in ALLOWED_CIRCLES]
    assert not new, f"import circles (split by concept, configuration at the bottom): {new}"
    gone = [sorted(c) for c in ALLOWED_CIRCLES if c not in left]
    assert not gone, f"circles no longer there: remove them from ALLOWED_CIRCLES: {gone}"


def test_no_private_name_imported_from_another_module(parsed):
    _, private = import_graph(parsed)
    new = sorted(set(private) - ALLOWED_PRIVATE_IMPORTS)
    assert not new, "private names imported from another module (give them a seam):\n" + "\n".join(new)
    gone = sorted(ALLOWED_PRIVATE_IMPORTS - set(private))
    assert not gone, f"no longer imported: remove them from ALLOWED_PRIVATE_IMPORTS: {gone}"


def test_folder_markers_live_in_their_home_modules(parsed):
    for home in set(MARKER_HOMES.values()):
        assert home in parsed, f"marker home {home} is not a module"
    found = [line for module, (tree, _) in parsed.items() for line in marker_literals(tree, module)]
    assert not found, "folder markers outside their home modules:\n" + "\n".join(found)


def test_no_function_over_the_limit(parsed):
    found = [line for module, (tree, _) in parsed.items() for line in long_functions(tree, module)]
    assert not found, "functions to split into steps a reader can hold in mind:\n" + "\n".join(found)


def test_the_checks_find_what_they_look_for():
    parsed = {
        "polarface.a": (ast.parse("from polarface.b import _hidden\n"
                                  "def f():\n    import polarface.c\n"), False),
        "polarface.b": (ast.parse("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                  "    from polarface.a import x\n"), False),
        "polarface.c": (ast.parse("from polarface import d\n"), False),
        "polarface.d": (ast.parse("import polarface.a\n"), False),
    }
    edges, private = import_graph(parsed)
    assert private == ["polarface.a <- polarface.b: _hidden"]
    assert [sorted(c) for c in circles(edges)] == [[f"polarface.{name}" for name in "abcd"]]
    tree = ast.parse('M = "manifest.json"\np = root / "ground_truth"\nkey = {"ground_truth": 1}\n')
    assert len(marker_literals(tree, "polarface.x")) == 2
    assert not marker_literals(tree, "polarface.simulate.layout")[1:]  # its home spells ground_truth
    body = "\n".join(["def long():"] + ["    pass"] * MAX_FUNCTION_LINES)
    assert len(long_functions(ast.parse(body), "polarface.x")) == 1
    assert PACKAGE_ROOT.is_dir()
