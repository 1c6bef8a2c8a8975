"""The import graph of the three packages, read from the source: no module imports itself
through others inside a package, the packages import only downward
(experiments -> planners -> racing_env), and the generic solver reaches nothing of the
racing game (the rule of tests/test_ilq.py, followed through every import).

Every import statement counts: at module level, inside functions (deferred imports) and
under ``if TYPE_CHECKING:``. A deferred import hides a circle from Python's loader, not from
a reader. Lookups by name through ``importlib`` (a module ``__getattr__`` that keeps a moved
name reachable, the env's factory of planner opponents) are not import statements and are
not counted: they are how a module keeps a name that moved to a module built on it.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("racing_env", "planners", "experiments")
# what each package may import of the others (docs/design.md, "The three packages")
ALLOWED = {"racing_env": set(), "planners": {"racing_env"}, "experiments": {"racing_env", "planners"}}
# The generic solver knows only the game protocol (GameProblem): neither these modules nor
# anything they import reaches racing_env; a RaceGame gets to them through planners.race_problem.
GENERIC_SOLVER = ("planners.lq_game", "planners.lq_stackelberg", "planners.local_game", "planners.ilq",
                  "planners.ilq_batch", "planners.nash", "planners.game_problem")


def modules_of(root: Path, packages: tuple[str, ...]) -> dict[str, tuple[Path, bool]]:
    """``{dotted name: (file, is a package's __init__)}`` of every module of ``packages`` under ``root``."""
    modules = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            is_package = parts[-1] == "__init__"
            if is_package:
                parts = parts[:-1]
            modules[".".join(parts)] = (path, is_package)
    return modules


def imported_names(module: str, is_package: bool, tree: ast.AST) -> list[str]:
    """The dotted names every import statement of ``tree`` reaches: ``import a.b`` gives
    ``a.b``; ``from a import b`` gives ``a.b`` (a module, or a name whose owner :func:`import_graph`
    finds by trimming); relative imports are resolved against ``module``."""
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = module.split(".") if is_package else module.split(".")[:-1]
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            names += [f"{base}.{alias.name}" for alias in node.names]
    return names


def import_graph(root: Path = ROOT, packages: tuple[str, ...] = PACKAGES) -> dict[str, set[str]]:
    """``{module: the modules of packages it imports}``. A name imported from a module is an
    edge to that module (``from planners.agents import make_agent`` -> ``planners.agents``);
    the parent packages Python loads on the way are not edges."""
    modules = modules_of(root, packages)
    graph = {}
    for module, (path, is_package) in modules.items():
        targets = set()
        for name in imported_names(module, is_package, ast.parse(path.read_text(), filename=str(path))):
            while name and name not in modules:  # a name defined in a module -> that module
                name = name.rpartition(".")[0]
            if name and name != module:
                targets.add(name)
        graph[module] = targets
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import circles of ``graph``: its strongly connected components of more than one
    module (Tarjan), each sorted, in sorted order."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
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
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def _write(root: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)


def test_the_graph_sees_deferred_type_checking_and_relative_imports(tmp_path):
    _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/a.py": "def f():\n    from pkg.b import g\n",  # deferred
        "pkg/b.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg import c\n",
        "pkg/c.py": "from .a import f\nimport numpy\n",  # relative; outside the packages: no edge
        "pkg/d.py": "from pkg import a\n",
        "pkg/sub/__init__.py": "from . import e\n",
        "pkg/sub/e.py": "from .. import d\n",
    })
    graph = import_graph(tmp_path, ("pkg",))
    assert graph == {"pkg": set(), "pkg.a": {"pkg.b"}, "pkg.b": {"pkg.c"}, "pkg.c": {"pkg.a"}, "pkg.d": {"pkg.a"},
                     "pkg.sub": {"pkg.sub.e"}, "pkg.sub.e": {"pkg.d"}}
    assert circles(graph) == [["pkg.a", "pkg.b", "pkg.c"]]


def test_a_name_imported_from_a_package_is_an_edge_to_its_init(tmp_path):
    # pkg/__init__.py imports helper, which takes a name from the package: a circle through __init__
    _write(tmp_path, {"pkg/__init__.py": "from pkg.helper import thing\nNAME = 1\n",
                      "pkg/helper.py": "from pkg import NAME\nthing = NAME\n"})
    assert circles(import_graph(tmp_path, ("pkg",))) == [["pkg", "pkg.helper"]]


@pytest.mark.parametrize("package", PACKAGES)
def test_no_import_circle_inside_a_package(package):
    graph = import_graph()
    inside = {m: {t for t in targets if t.split(".")[0] == package}
              for m, targets in graph.items() if m.split(".")[0] == package}
    assert len(inside) > 5  # the package's modules were found
    assert circles(inside) == [], f"modules of {package} that import each other (docs/design.md says where shared pieces go)"


def test_no_import_circle_across_the_packages():
    assert circles(import_graph()) == []


def test_packages_import_only_downward():
    wrong = sorted((module, target) for module, targets in import_graph().items() for target in targets
                   if target.split(".")[0] != module.split(".")[0]
                   and target.split(".")[0] not in ALLOWED[module.split(".")[0]])
    assert wrong == []


def reachable(graph: dict[str, set[str]], start: str) -> set[str]:
    """Every module ``start`` imports, directly or through others."""
    seen, todo = set(), [start]
    while todo:
        for target in graph.get(todo.pop(), ()):
            if target not in seen:
                seen.add(target)
                todo.append(target)
    return seen


def test_the_generic_solver_reaches_nothing_of_the_racing_game():
    graph = import_graph()
    for module in GENERIC_SOLVER:
        assert module in graph, module
        assert not {m for m in reachable(graph, module) if m.split(".")[0] == "racing_env"}, module
    assert "racing_env.game" in reachable(graph, "planners.race_problem")  # the adapter is where it enters


def test_the_pieces_that_moved_down_keep_their_old_import_paths():
    from experiments import standings, tournament
    from experiments.rl import common, config, train
    from planners.agents import batched, batched_protocol

    assert tournament.wilson_interval is standings.wilson_interval
    assert tournament.won_race is standings.won_race
    for name in ("TrainConfig", "default_hyperparameters", "config_json", "TRAINING_STARTS", "LEARNERS",
                 "PPO_MIN_STEPS", "CONFIG", "EPISODES", "EVALUATIONS", "CHECKPOINTS"):
        assert getattr(train, name) is getattr(config, name), name
    for name in ("make_vector_env", "episode_fields", "record_evaluation", "evaluate_final", "finish_report",
                 "check_resumable", "drop_episodes_after", "next_multiple"):
        assert getattr(train, name) is getattr(common, name), name
    for name in ("BatchedOpponent", "DIAGNOSTIC_FIELDS", "empty_diagnostics"):
        assert getattr(batched, name) is getattr(batched_protocol, name), name
