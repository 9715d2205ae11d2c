"""The packages' layering, read from every import statement (function-level ones included).

``perception`` <- ``controllers`` <- ``rover_env``; inside ``rover_env`` the subpackages import
downward only: config -> sim -> rendering -> sensors -> task -> envs -> tools. Inside
``perception``: models -> the algorithms (odometry, kinematics, fusion; none imports another)
-> the estimator (the package's top-level modules: the interface, the rig, the observation
table, the built-in estimator) -> logs.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("perception", "controllers", "rover_env")
#: rover_env's subpackages, lowest layer first.
LAYERS = ("config", "sim", "rendering", "sensors", "task", "envs", "tools")
#: What rover_env's top level may hold besides its subpackages.
TOP_LEVEL = {"__init__.py"}
#: perception's layers, lowest first; the algorithms share a rank and import none of each other.
#: ``estimator`` is the package's top level (its modules and its ``__init__``).
PERCEPTION_RANK = {"models": 0, "odometry": 1, "kinematics": 1, "fusion": 1, "estimator": 2, "logs": 3}
#: The modules of perception's top level (the estimator layer).
PERCEPTION_TOP = {"__init__.py", "estimator.py", "rig.py", "observation.py", "rover_estimator.py"}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports_of(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in ``path``, at any depth of the code."""
    tree = ast.parse(path.read_text(), filename=str(path))
    here = _module_name(path).split(".")
    package = here if path.name == "__init__.py" else here[:-1]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            out.append((node.lineno, module))
            # ``from package import submodule`` imports the submodule too
            out += [(node.lineno, f"{module}.{a.name}") for a in node.names if a.name != "*"]
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) in (
            "import_module",
            "__import__",
        ):
            if node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str):
                out.append((node.lineno, node.args[0].value))
    return out


def _sources(package: str) -> list[Path]:
    files = sorted((ROOT / package).rglob("*.py"))
    assert files, f"no sources under {package}/"
    return files


def _top(module: str) -> str:
    return module.split(".")[0]


def _layer(module: str) -> str | None:
    """The rover_env subpackage a module belongs to (None: rover_env's top level)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "rover_env" and parts[1] in LAYERS else None


def test_the_import_reader_sees_function_level_and_relative_imports(tmp_path):
    pkg = ROOT / "rover_env" / "sim"
    probe = pkg / "_probe_for_test.py"
    probe.write_text("def f():\n    from ..tools import cli\n    import pybullet\n")
    try:
        found = {m for _, m in imports_of(probe)}
    finally:
        probe.unlink()
    assert {"rover_env.tools", "rover_env.tools.cli", "pybullet"} <= found


@pytest.mark.parametrize(
    ("package", "forbidden"),
    [
        ("perception", {"rover_env", "controllers", "pybullet", "pybullet_utils", "gymnasium", "gym"}),
        ("controllers", {"rover_env", "pybullet", "pybullet_utils"}),
    ],
)
def test_lower_packages_do_not_import_higher_ones(package, forbidden):
    bad = [
        f"{p.relative_to(ROOT)}:{line} imports {m}"
        for p in _sources(package)
        for line, m in imports_of(p)
        if _top(m) in forbidden
    ]
    assert not bad, "\n".join(bad)


def test_rover_env_subpackages_import_downward_only():
    rank = {name: i for i, name in enumerate(LAYERS)}
    bad, edges = [], set()
    for p in _sources("rover_env"):
        src = _layer(_module_name(p))
        for line, m in imports_of(p):
            dst = _layer(m)
            if src is None or dst is None or dst == src:
                continue
            edges.add((src, dst))
            if rank[dst] > rank[src]:
                bad.append(f"{p.relative_to(ROOT)}:{line} ({src}) imports {m} ({dst}), a higher layer")
    assert not bad, "\n".join(bad)
    # and so no cycle between them; checked on its own in case the order above is ever relaxed
    graph: dict[str, set[str]] = {}
    for a, b in edges:
        graph.setdefault(a, set()).add(b)

    def reaches(a: str, b: str, seen: set[str]) -> bool:
        return any(n == b or (n not in seen and reaches(n, b, seen | {n})) for n in graph.get(a, ()))

    cycles = sorted(a for a in graph if reaches(a, a, {a}))
    assert not cycles, f"import cycles through {cycles}"


def test_rover_env_top_level_holds_only_entry_modules():
    top = {p.name for p in (ROOT / "rover_env").glob("*.py")}
    assert top <= TOP_LEVEL, f"modules at rover_env's top level: {sorted(top - TOP_LEVEL)}; give each a layer"
    subpackages = {p.parent.name for p in (ROOT / "rover_env").glob("*/__init__.py")}
    assert subpackages == set(LAYERS), f"subpackages {sorted(subpackages)}, layers {LAYERS}"


def _perception_layer(module: str) -> str | None:
    """The perception layer a module belongs to (None: not perception)."""
    parts = module.split(".")
    if parts[0] != "perception":
        return None
    return parts[1] if len(parts) > 1 and parts[1] in PERCEPTION_RANK else "estimator"


def test_perception_layers_import_downward_only():
    bad = []
    for p in _sources("perception"):
        src = _perception_layer(_module_name(p))
        assert src is not None
        for line, m in imports_of(p):
            dst = _perception_layer(m)
            if dst is None or dst == src:
                continue
            if PERCEPTION_RANK[dst] >= PERCEPTION_RANK[src]:
                bad.append(f"{p.relative_to(ROOT)}:{line} ({src}) imports {m} ({dst}): not a lower layer")
    assert not bad, "\n".join(bad)


def test_perception_top_level_holds_only_the_estimator_layer():
    top = {p.name for p in (ROOT / "perception").glob("*.py")}
    assert top <= PERCEPTION_TOP, f"modules at perception's top level: {sorted(top - PERCEPTION_TOP)}"
    subpackages = {p.parent.name for p in (ROOT / "perception").glob("*/__init__.py")}
    assert subpackages == set(PERCEPTION_RANK) - {"estimator"}, subpackages


def test_the_public_names_users_import_are_kept():
    import perception
    import perception.estimator
    import perception.rig

    for name in perception.__all__:
        assert hasattr(perception, name), name
    assert perception.RoverEstimator.__module__ == "perception.rover_estimator"
    assert {"Estimator", "ESTIMATE_FIELDS", "check_estimate"} <= set(vars(perception.estimator))
    assert {"Rig", "SensorSpec", "SensorMessage"} <= set(vars(perception.rig))


@pytest.mark.parametrize("package", ["rover_env", "perception"])
def test_no_module_cycles_inside_a_package(package):
    """Module-level cycles hide in function-level imports; there are none left."""
    modules = {_module_name(p): p for p in _sources(package)}
    graph = {
        m: {d for _, d in imports_of(p) if d in modules and d != m and not modules[d].name == "__init__.py"}
        for m, p in modules.items()
    }
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for m in graph:
        if m not in index:
            visit(m)
    assert not cycles, f"module import cycles: {cycles}"
