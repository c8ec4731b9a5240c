"""The layering of DESIGN.md: no import cycle between this project's modules."""

import ast
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
    assert {"bdf.field", "bdf.posterior", "bdf.tuning"} <= set(graph)
    assert "bdf.tuning" not in graph["bdf.field"] and "bdf.posterior" in graph["bdf.field"]
    assert find_cycle(graph) is None, " -> ".join(find_cycle(graph))


def test_the_cycle_finder_finds_a_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_packages_import_one_way():
    """bdf at the bottom; service and planner above it, neither importing the other nor
    clients; clients on top (DESIGN.md, Layout)."""
    allowed = {"bdf": {"bdf"}, "service": {"bdf", "service"}, "planner": {"bdf", "planner"}}
    for module, targets in imports().items():
        package = module.split(".")[0]
        if package in allowed:
            wrong = {t for t in targets if t.split(".")[0] not in allowed[package]}
            assert not wrong, f"{module} imports {sorted(wrong)}"
