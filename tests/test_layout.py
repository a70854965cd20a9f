"""The import graph keeps docs/design.md's rules: two stacks on one shared floor, the experiment on a floor of its own
above both, every arrow pointing down a floor, no import circle.

Every ``import`` of the project's own modules counts, at module level and inside functions alike (a lazy import is
still a dependency). ``from pkg import name`` is an edge to ``pkg.name`` when that is a module, else to ``pkg``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("mpchair", "detector", "reproduction")
#: The experiment (make reproduce, the accuracy study, the device check): one package on one floor above both stacks.
#: It may import anything of either stack; neither stack imports it.
EXPERIMENT = "reproduction"

#: The floor of every top-level folder / file of both stacks, and of the experiment: a module may import its own folder
#: and any lower floor, never a higher one nor another folder of its own floor. Keep in step with docs/design.md
#: ("Floors").
FLOORS: dict[str, int] = {
    # the package roots hold only ``__version__`` and a docstring (anyone may read them), and mpchair's root sets the
    # BLAS pin before numpy loads (ROOT_PIN: the one arrow up from floor -1, to a stdlib-only module of the floor)
    "mpchair": -1,
    "detector": -1,
    # the shared floor, imported by both stacks
    "mpchair.core": 0,
    "mpchair.paper": 0,  # the paper's published figures (data only, imports nothing)
    "mpchair.kitti": 1,
    "mpchair.geometry": 2,  # camera conversions read kitti's Calib / Labels
    "mpchair.recording": 3,
    # the mpchair stack
    "mpchair.data": 4,  # mpcat40.tsv (package data, no code)
    "mpchair.matterport": 4,
    "mpchair.synth": 5,
    "mpchair.scan": 5,
    "mpchair.labels": 6,
    "mpchair.dataset": 7,
    "mpchair.stream": 8,
    "mpchair.analysis": 8,
    "mpchair.commands": 9,
    "mpchair.cli": 10,
    # the detector stack (on top of the shared floor)
    "detector.config": 4,
    "detector.pretrained": 4,  # packaged weights by name (index + files; read by checkpoint)
    "detector.device": 4,
    "detector.ops": 4,  # rotated IoU / NMS, and the GEMM of both models (ops.gemm: the sparse convs call it too)
    "detector.sparse": 5,
    "detector.data": 5,
    "detector.eval": 5,
    "detector.models": 6,
    "detector.checkpoint": 7,
    "detector.infer": 8,
    "detector.opcount": 8,
    "detector.viz": 8,
    "detector.deploy": 8,  # exported graphs and their runtimes (read by bench, commands)
    "detector.bench": 9,
    "detector.train": 9,
    "detector.stream": 9,
    "detector.commands": 10,
    "detector.cli": 11,
    "detector.__main__": 12,
    # the experiment floor, above both stacks (it drives their command lines: the device check runs detector.cli's
    # main in its own process to read the run's peak memory)
    EXPERIMENT: 13,
}
SHARED_FLOOR = ("mpchair.core", "mpchair.geometry", "mpchair.kitti", "mpchair.paper", "mpchair.recording")


def module_files() -> dict[str, Path]:
    """Dotted module name → file, for every module of the three packages."""
    out = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            out[name] = path
    return out


def imports_of(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The project modules ``name`` imports anywhere in its file."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                found.add(sub if sub in modules else target)
    return {m for m in found if m.split(".")[0] in PACKAGES}


def resolve(module: str, modules: dict[str, Path]) -> str:
    while module not in modules and "." in module:
        module = module.rpartition(".")[0]
    return module


def floor_key(module: str) -> str:
    """The FLOORS entry a module belongs to: its top-level folder or file (``detector.bench.timing`` →
    ``detector.bench``); every module of the experiment belongs to its one floor."""
    if module.split(".")[0] == EXPERIMENT:
        return EXPERIMENT
    return ".".join(module.split(".")[:2])


def import_graph() -> dict[str, set[str]]:
    modules = module_files()
    return {name: {resolve(m, modules) for m in imports_of(name, path, modules)} - {name}
            for name, path in modules.items()}


GRAPH = import_graph()


def test_every_folder_has_a_floor():
    """A new top-level folder or file must be placed on a floor here and in docs/design.md."""
    missing = sorted({floor_key(m) for m in GRAPH} - set(FLOORS))
    assert not missing, f"add to FLOORS (and docs/design.md): {missing}"


def test_mpchair_never_imports_detector():
    bad = sorted((a, b) for a, targets in GRAPH.items() if a.startswith("mpchair") for b in targets
                 if b.startswith("detector"))
    assert not bad, bad


def test_detector_imports_only_the_shared_floor_of_mpchair():
    bad = sorted((a, b) for a, targets in GRAPH.items() if a.startswith("detector") for b in targets
                 if b.startswith("mpchair") and not b.startswith(SHARED_FLOOR))
    assert not bad, bad


def test_neither_stack_imports_the_experiment():
    """The experiment drives both stacks; nothing of either stack (their CLIs included) may reach back up into it."""
    bad = sorted((a, b) for a, targets in GRAPH.items() if not a.startswith(EXPERIMENT) for b in targets
                 if b.split(".")[0] == EXPERIMENT)
    assert not bad, bad
    assert any(b.startswith("detector.") for b in GRAPH["reproduction.steps"])  # the graph sees the experiment's arrows


def test_the_experiment_finds_the_checkout_in_one_place():
    """Only ``reproduction.checkout`` locates the clone (from the package's own location); no other module of the
    experiment walks up from its ``__file__``."""
    files = module_files()
    bad = [name for name, path in files.items() if name.startswith(EXPERIMENT) and name != "reproduction.checkout"
           and ("__file__" in (text := path.read_text(encoding="utf-8")) or "parents[" in text)]
    assert not bad, bad


def test_core_imports_nothing_above_it():
    bad = sorted((a, b) for a, targets in GRAPH.items() if a.startswith("mpchair.core") for b in targets
                 if not b.startswith("mpchair.core"))
    assert not bad, bad


#: The package root's one import: the OpenBLAS kernel pin, which must run before anything imports numpy.
ROOT_PIN = ("mpchair", "mpchair.core.blas")


def test_every_arrow_points_down_a_floor():
    """A module imports its own folder or a lower floor; two folders of one floor never import each other."""
    bad = []
    # the pin the package root imports runs before numpy loads: it imports nothing of ours but the stdlib-only reader
    # of the CPU flags, which imports nothing of ours
    assert GRAPH["mpchair.core.blas"] <= {"mpchair.core.cpu"} and GRAPH["mpchair.core.cpu"] <= set(), \
        "the pin the package root imports must import nothing of ours (but mpchair.core.cpu)"
    for a, targets in GRAPH.items():
        ka = floor_key(a)
        for b in targets:
            if (a, b) == ROOT_PIN:
                continue
            kb = floor_key(b)
            if ka not in FLOORS or kb not in FLOORS:
                continue  # test_every_folder_has_a_floor names it
            if kb != ka and FLOORS[kb] >= FLOORS[ka]:
                bad.append(f"{a} (floor {FLOORS[ka]}) -> {b} (floor {FLOORS[kb]})")
    assert not bad, "\n".join(sorted(bad))


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's components of more than one module (iterative: no recursion limit)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def test_no_import_circle():
    assert strongly_connected(GRAPH) == []


@pytest.mark.parametrize("graph, circles", [
    ({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}, [["a", "b", "c"]]),
    ({"a": {"b"}, "b": set(), "c": {"b"}}, []),
])
def test_the_circle_finder_finds_circles(graph, circles):
    """The checker itself can fail: a planted circle is found, a tree is not."""
    assert strongly_connected(graph) == circles


def test_the_graph_sees_lazy_and_submodule_imports():
    """Function-level imports count, and ``from pkg import submodule`` points at the submodule."""
    assert "mpchair.synth.furniture" in GRAPH["mpchair.synth.house"]
    assert "mpchair.synth" not in GRAPH["mpchair.synth.house"]
    assert any(b.startswith("mpchair.analysis") for b in GRAPH["mpchair.commands.stats"])  # imported inside main()


def test_the_experiments_tools_are_front_ends():
    """``tools/`` scripts of the experiment hold no code of their own: a docstring, one import of the package's
    ``main`` and the exit."""
    fronts = {p.name: p.read_text(encoding="utf-8") for p in sorted((ROOT / "tools").glob("*.py"))
              if "from reproduction" in p.read_text(encoding="utf-8")}
    assert set(fronts) >= {"reproduce.py", "reproduce_stream.py", "accuracy_study.py", "device_check.py",
                           "doc_pictures.py"}, fronts
    for name, text in fronts.items():
        body = [ln for ln in text.splitlines() if ln.strip() and not ln.startswith('"""')]
        assert len(body) == 2 and body[0].startswith("from reproduction.") and body[0].endswith(" import main") \
            and body[1] == "raise SystemExit(main())", (name, body)


def test_tools_are_front_ends_that_do_not_edit_sys_path():
    """``tools/*.py`` run from the installed package (``.venv`` holds it in editable mode); none edits ``sys.path``."""
    bad = [p.name for p in sorted((ROOT / "tools").glob("*.py")) if "sys.path" in p.read_text(encoding="utf-8")]
    assert not bad, bad
