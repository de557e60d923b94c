"""The layers of docs/architecture.md "Module map", enforced by walking the imports.

- every row of the page's layer table: ``LAYERS`` puts each module of robotd/, drivers/ and calib/
  in the layer its row names, ``RULES`` says what each layer may import (its own layer, whole
  layers, single modules of others, libraries), and the page's table and ``LAYERS`` must agree;
- core (geometry, stereo, msgs, statecheck, frontend, outliers, slam, ...): numpy, scipy, OpenCV and numba only;
- pipeline (pipeline, relocalise, config_params, config, ...): the core, no I/O (but the config's loader);
- the daemon never imports the research package, not even indirectly;
- no import cycles among the modules of robotd, drivers and calib;
- each hardware library has one importer.
"""

from __future__ import annotations

import ast
from pathlib import Path

from tests.support.paths import REPO

PACKAGES = ("robotd", "drivers", "calib")

# docs/architecture.md's layer table, row by row: which modules (a file, or a package with a
# trailing slash) belong to which layer. The one place the test says it; the page must agree
# (test_the_doc_table_and_the_layers_agree).
LAYERS: dict[str, tuple[str, ...]] = {
    "core": (
        "robotd/__init__.py",  # the package itself: its docstring and __version__
        "robotd/msgs.py",
        "robotd/errors.py",
        "robotd/choices.py",
        "robotd/geometry.py",
        "robotd/stereo.py",
        "robotd/statecheck.py",
        "robotd/timing.py",
        "robotd/jit.py",
        "robotd/outliers.py",
        "robotd/_outlier_kernels.py",
        "robotd/frontend/",
        "robotd/slam/",
    ),
    "pipeline": (
        "robotd/pipeline.py",
        "robotd/relocalise.py",
        "robotd/stall.py",
        "robotd/odometry.py",
        "robotd/config_params.py",
        "robotd/config.py",
        "robotd/config_bounds.py",
    ),
    "formats": (
        "robotd/queues.py",
        "robotd/autopilot.py",
        "robotd/codec.py",
        "robotd/persist.py",
        "robotd/record.py",
        "robotd/mcap_scan.py",
        "robotd/foxglove_pb.py",
    ),
    "drivers": ("drivers/",),
    "service": ("robotd/daemon/", "robotd/outputs/", "robotd/device_urls.py"),
    "tools": (
        "robotd/cli.py",
        "robotd/__main__.py",
        "robotd/doctor.py",
        "robotd/journal.py",
        "robotd/replay.py",
        "robotd/echo.py",
        "robotd/fleet.py",
        "robotd/progress.py",
        "robotd/batch/",
        "calib/",
    ),
    "research": ("robotd/research/",),
}
CORE = list(LAYERS["core"])
PIPELINE = list(LAYERS["pipeline"])
ALLOWED_THIRD_PARTY = {"numpy", "scipy", "cv2", "numba"}
STDLIB_OK = {
    "__future__",
    "dataclasses",
    "typing",
    "math",
    "logging",
    "time",
    "collections",
    "functools",
    "itertools",
    "enum",
    "abc",
    "warnings",
    "os",
    "collections.abc",
    "concurrent",  # compute parallelism (both images detected at once), not I/O
}
# the I/O libraries that must stay in drivers/, the outputs and the daemon
FORBIDDEN = {"zenoh", "serial", "pymavlink", "depthai", "socket", "mcap", "threading", "subprocess", "matplotlib"}


def _files(entries: list[str]) -> list[Path]:
    files: list[Path] = []
    for c in entries:
        p = REPO / c
        files += sorted(p.rglob("*.py")) if p.is_dir() else ([p] if p.exists() else [])
    return files


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path) -> list[str]:
    """Absolute names of everything ``path`` imports (``from a import b`` gives ``a`` and ``a.b``)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    pkg = _module_name(path) if path.name == "__init__.py" else _module_name(path).rpartition(".")[0]
    names: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")[: len(pkg.split(".")) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            names.append(mod)
            names += [f"{mod}.{a.name}" for a in node.names]
    return names


def _graph() -> dict[str, set[str]]:
    """Module -> the project modules it imports (resolved to the longest known module name)."""
    files = [f for pkg in PACKAGES for f in sorted((REPO / pkg).rglob("*.py"))]
    mods = {_module_name(f): f for f in files}
    graph: dict[str, set[str]] = {}
    for m, f in mods.items():
        deps: set[str] = set()
        for name in _imports(f):
            parts = name.split(".")
            for k in range(len(parts), 0, -1):
                cand = ".".join(parts[:k])
                if cand in mods:
                    if cand != m:
                        deps.add(cand)
                    break
        graph[m] = deps
    return graph


def _within(module: str, prefixes: tuple[str, ...]) -> bool:
    """``module`` is one of ``prefixes`` or inside one of them (``robotd.slam.ekf`` in ``robotd.slam``)."""
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def _check_layer(files: list[Path], allowed_project: tuple[str, ...], more_stdlib: set[str] = set()) -> list[str]:
    bad: list[str] = []
    for f in files:
        for name in _imports(f):
            top = name.split(".")[0]
            rel = f.relative_to(REPO)
            if top in FORBIDDEN:
                bad.append(f"{rel} imports {name}")
            elif top in PACKAGES:
                # a bare package name is the ``from robotd import x`` half; ``robotd.x`` is checked
                if name not in PACKAGES and not _within(name, allowed_project):
                    bad.append(f"{rel} imports {name}")
            elif top not in ALLOWED_THIRD_PARTY and top not in STDLIB_OK | more_stdlib:
                bad.append(f"{rel} imports {name}")
    return bad


def _dotted(entry: str) -> str:
    """``robotd/slam/`` -> ``robotd.slam``, ``robotd/msgs.py`` -> ``robotd.msgs``, ``robotd/__init__.py`` -> ``robotd``."""
    return entry.removesuffix("/").removesuffix("/__init__.py").removesuffix(".py").replace("/", ".")


# the package's own name is no prefix here: ``robotd`` would let in every module of robotd
CORE_MODULES = tuple(_dotted(c) for c in CORE if not c.endswith("__init__.py"))
# what config.py's loader needs to read the TOML file: the pipeline's one file access
CONFIG_LOADER_LIBRARIES = {"pathlib", "tomllib", "re", "types"}


def test_core_imports_only_numeric_libraries() -> None:
    files = _files(CORE)
    assert len(files) > 20, "core files not found"
    bad = _check_layer(files, CORE_MODULES)
    assert not bad, "core modules import I/O or unexpected modules:\n" + "\n".join(bad)


def test_pipeline_imports_the_core_and_the_config_only() -> None:
    files = _files(PIPELINE)
    assert len(files) == len(PIPELINE)
    pipeline_modules = tuple(_dotted(p) for p in PIPELINE)
    bad = _check_layer([f for f in files if f.name != "config.py"], (*CORE_MODULES, *pipeline_modules))
    bad += _check_layer(
        [f for f in files if f.name == "config.py"], (*CORE_MODULES, *pipeline_modules), CONFIG_LOADER_LIBRARIES
    )
    assert not bad, "the pipeline imports I/O or modules outside the core:\n" + "\n".join(bad)


def test_the_daemon_never_imports_research_code() -> None:
    graph = _graph()
    seen: set[str] = set()
    todo = [m for m in graph if m == "robotd.daemon" or m.startswith(("robotd.daemon.", "robotd.outputs"))]
    assert todo, "daemon modules not found"
    while todo:
        m = todo.pop()
        if m in seen:
            continue
        seen.add(m)
        todo += graph.get(m, ())
    research = sorted(m for m in seen if m.startswith("robotd.research"))
    assert not research, f"the daemon imports research code: {research}"


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), iteratively."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    counter = 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
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


def test_no_import_cycles() -> None:
    cycles = _cycles(_graph())
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_cycle_finder_finds_a_cycle() -> None:
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_each_hardware_library_has_one_importer() -> None:
    owners = {"depthai": "drivers/oak", "serial": "drivers/serial_link.py", "pymavlink": "drivers/mavlink_link.py"}
    bad: list[str] = []
    for f in sorted(REPO.glob("**/*.py")):
        rel = f.relative_to(REPO).as_posix()
        if rel.startswith((".venv", "tests/", "bench/", "build/")):
            continue
        for name in _imports(f):
            top = name.split(".")[0]
            if top in owners and not rel.startswith(owners[top]):
                bad.append(f"{rel} imports {name} (only {owners[top]} may)")
    assert not bad, "\n".join(bad)
