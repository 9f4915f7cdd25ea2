"""The package's structure: no import circle, no re-exported names, each module says its one job."""
import ast
import functools

from conftest import ROOT

PACKAGE = ROOT / "dfxcorr"


@functools.cache
def modules() -> dict[str, ast.Module]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = ast.parse(path.read_text(), str(path))
    return out


def imported(name: str, tree: ast.Module, known: set[str]) -> set[str]:
    """The package's modules that ``name`` imports anywhere in its text (type-only and deferred imports too)."""
    package = (name if (PACKAGE / "/".join(name.split(".")[1:]) / "__init__.py").exists() or name == "dfxcorr"
               else name.rsplit(".", 1)[0])
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name in known}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*up, *([base] if base else [])])
            for a in node.names:
                full = f"{base}.{a.name}"
                found.add(full if full in known else base)
    return {m for m in found if m in known and m != name}


def graph() -> dict[str, set[str]]:
    trees = modules()
    known = set(trees)
    return {name: imported(name, tree, known) for name, tree in trees.items()}


def cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """One import circle of ``edges``, or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> list[str] | None:
        state[n] = 1
        stack.append(n)
        for m in sorted(edges[n]):
            # a package's own __init__ importing its submodules is how a package is assembled, not a circle
            if n.startswith(m + "."):
                continue
            if state.get(m) == 1:
                return stack[stack.index(m):] + [m]
            if m not in state and (found := visit(m)) is not None:
                return found
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(edges):
        if n not in state and (found := visit(n)) is not None:
            return found
    return None


def test_the_import_graph_has_no_circle():
    assert cycle(graph()) is None, " -> ".join(cycle(graph()) or [])


def test_the_circle_finder_finds_a_circle():
    assert cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert cycle({"a": {"b"}, "b": set()}) is None


def test_every_module_says_its_job():
    missing = [name for name, tree in modules().items() if not ast.get_docstring(tree)]
    assert not missing, missing


def test_no_module_re_exports_an_imported_name():
    # a package's __init__ assembles it from its submodules; any other module lists only what it defines
    found = {}
    for name, tree in modules().items():
        if (PACKAGE / "/".join(name.split(".")[1:]) / "__init__.py").exists():
            continue
        defined, listed = set(), []
        for node in tree.body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                defined.add(node.name)
            elif isinstance(node, (ast.Assign, ast.AnnAssign)):
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                defined |= {n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)}
                if any(isinstance(t, ast.Name) and t.id == "__all__" for t in targets):
                    listed = [e.value for e in node.value.elts]
        if foreign := [n for n in listed if n not in defined]:
            found[name] = foreign
    assert not found, found
