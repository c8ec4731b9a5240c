"""The layering of docs/ARCHITECTURE.md: no import cycle between this project's modules."""

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("bdf", "service", "planner", "clients")


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports() -> dict[str, set[str]]:
    """Module -> the project modules it imports, anywhere in its body."""
    modules = {module_name(p): p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}
    graph = {}
    for name, path in modules.items():
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                continue
            found |= {t for t in targets if t in modules and t != name}
        graph[name] = found - {name.rpartition(".")[0]}  # a package's __init__ is not a cycle
    return graph


def find_cycle(graph):
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == "open":
                return [*stack[stack.index(nxt) :], nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        stack.pop()
        state[node] = "done"
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def test_no_module_imports_itself_through_others():
    graph = imports()
    assert {"bdf.field", "bdf.posterior", "bdf.hyperparameters"} <= set(graph)
    assert "bdf.hyperparameters" not in graph["bdf.field"] and "bdf.posterior" in graph["bdf.field"]
    assert find_cycle(graph) is None, " -> ".join(find_cycle(graph))


def test_the_cycle_finder_finds_a_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_packages_import_one_way():
    """bdf at the bottom; service and planner above it, neither importing the other nor
    clients; clients on top (docs/ARCHITECTURE.md, Layers)."""
    allowed = {"bdf": {"bdf"}, "service": {"bdf", "service"}, "planner": {"bdf", "planner"}}
    for module, targets in imports().items():
        package = module.split(".")[0]
        if package in allowed:
            wrong = {t for t in targets if t.split(".")[0] not in allowed[package]}
            assert not wrong, f"{module} imports {sorted(wrong)}"


def closure(graph: dict[str, set[str]], start: str) -> set[str]:
    """The project modules ``start`` imports, directly or through others."""
    seen, todo = set(), [start]
    while todo:
        for nxt in graph[todo.pop()] - seen:
            seen.add(nxt)
            todo.append(nxt)
    return seen


def numba_importers() -> set[str]:
    """The project modules whose code imports numba."""
    out = set()
    for pkg in PACKAGES:
        for path in (ROOT / pkg).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
                if isinstance(node, ast.ImportFrom) and node.module:
                    names = [node.module]
                if any(n.split(".")[0] == "numba" for n in names):
                    out.add(module_name(path))
    return out


def test_the_sdk_imports_no_numerics_of_the_library():
    """The SDK (and the wire names it shares with the service) reach no module of bdf and
    none that imports numba, so that ``import clients.sdk`` stays light."""
    graph = imports()
    assert {"bdf.sparse.supernodal", "bdf.features"} <= numba_importers()
    reached = closure(graph, "clients.sdk") | {"clients.sdk"}
    assert "service.wire" in reached
    assert not {m for m in reached if m.split(".")[0] == "bdf"}, sorted(reached)
    assert not reached & numba_importers(), sorted(reached & numba_importers())


def test_importing_the_sdk_loads_neither_numba_nor_scipy():
    """The same, by the interpreter: what ``import clients.sdk`` leaves in sys.modules."""
    heavy = "('numba', 'scipy', 'bdf', 'pyproj')"
    code = f"import sys, clients.sdk; print(sorted(m for m in {heavy} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_the_region_schema_loads_neither_numba_nor_scipy():
    """``RegionSpec`` is a schema with its geometry: a client, a planner or a validation of a
    request's spec does not load the numerics (the model factory is ``bdf.region.map``'s)."""
    code = "import sys, bdf.region.spec; print(sorted(m for m in ('numba', 'scipy') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_the_library_wings_import_one_way():
    """bdf.sparse is the algebra under the model: it imports only the lattice and the kernel
    besides itself. bdf.region is the top of the library: no other bdf module imports it."""
    for module, targets in imports().items():
        if module.startswith("bdf.sparse"):
            wrong = {t for t in targets if not t.startswith("bdf.sparse")} - {"bdf.grid", "bdf.kernel"}
            assert not wrong, f"{module} imports {sorted(wrong)}"
        elif module.startswith("bdf") and not module.startswith("bdf.region"):
            assert not {t for t in targets if t.startswith("bdf.region")}, module


def test_the_library_imports_only_its_declared_dependencies():
    """bdf's third-party imports are pyproject's core dependencies (llvmlite comes with
    numba); what the clients, the service and the planner need is in their extras."""
    import tomllib

    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    allowed = {d.split(">")[0].split("=")[0].split("[")[0].strip() for d in declared} | {"llvmlite"}
    used = set()
    for path in (ROOT / "bdf").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                used |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                used.add(node.module.split(".")[0])
    third_party = used - set(sys.stdlib_module_names) - {"bdf"}
    assert third_party == allowed, (sorted(third_party), sorted(allowed))
