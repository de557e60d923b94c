"""The layers of docs/architecture.md "Module map", enforced by walking the imports.

- every layer is a folder: ``LAYERS`` names packages (folders), and no module of robotd/ sits beside
  them but the package's own ``__init__.py`` and ``__main__.py``;
- every row of the page's layer table: ``LAYERS`` puts each module of robotd/, drivers/ and calib/
  in the layer its row names, ``RULES`` says what each layer may import (its own layer, whole
  layers, single modules of others, libraries), and the page's table and ``LAYERS`` must agree;
- core (robotd/core/: geometry, stereo, msgs, statecheck, outliers, ...; robotd/frontend/,
  robotd/slam/): numpy, scipy, OpenCV and numba (with llvmlite, numba's code generator) only;
- pipeline (robotd/pipeline/: the step, its stages, relocalise, odometry, feed, ...; robotd/config/):
  the core, no I/O (but the config's loader);
- drivers (drivers/): the core and three modules of the formats, each hardware library in its owner;
- the daemon never imports the research package, not even indirectly;
- no import cycles among the modules of robotd, drivers and calib;
- each hardware library has one importer.
"""

from __future__ import annotations

import ast
import re
import sys
from dataclasses import dataclass
from pathlib import Path

from drivers.cameras import CAMERAS
from tests.support.paths import REPO

PACKAGES = ("robotd", "drivers", "calib")

# docs/architecture.md's layer table, row by row: which packages (a folder, with a trailing slash)
# belong to which layer, every module in them included. The one place the test says it; the page
# must agree (test_the_doc_table_and_the_layers_agree). Each layer is one or a few folders, so the
# tree shows the layers (test_every_layer_is_a_folder); the only files named are robotd's own two.
LAYERS: dict[str, tuple[str, ...]] = {
    "core": (
        "robotd/__init__.py",  # the package itself: its docstring and __version__
        "robotd/core/",
        "robotd/frontend/",
        "robotd/slam/",
    ),
    "pipeline": ("robotd/pipeline/", "robotd/config/"),
    "formats": ("robotd/formats/",),
    "drivers": ("drivers/",),
    "service": ("robotd/daemon/", "robotd/outputs/"),
    "tools": (
        "robotd/tools/",
        "robotd/__main__.py",  # ``python -m robotd``: the command of robotd/tools/cli.py
        "calib/",
    ),
    "research": ("robotd/research/",),
}
# the modules of robotd/ outside every layer's folder: the package itself and ``python -m robotd``
TOP_LEVEL = ("robotd/__init__.py", "robotd/__main__.py")
CORE = list(LAYERS["core"])
PIPELINE = list(LAYERS["pipeline"])
# llvmlite: numba's own code generator, for a kernel intrinsic (_stereo_kernels._popcount64, one POPCNT)
ALLOWED_THIRD_PARTY = {"numpy", "scipy", "cv2", "numba", "llvmlite"}
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


def _camera_library_owners() -> dict[str, str]:
    """library -> the camera driver's module or package that alone may import it, from the cameras'
    registrations (drivers.cameras: each kind's ``libraries``)."""
    owners: dict[str, str] = {}
    for reg in CAMERAS.values():
        module = reg.target.partition(":")[0] if isinstance(reg.target, str) else type(reg.target).__module__
        path = module.replace(".", "/")
        owners.update({lib: path if (REPO / path).is_dir() else f"{path}.py" for lib in reg.kind.libraries})
    return owners


# each hardware library -> its one importer: the cameras' from their registrations, the vehicle links'
HARDWARE_OWNERS = {
    **_camera_library_owners(),
    "serial": "drivers/serial_link.py",
    "pymavlink": "drivers/mavlink_link.py",
}
# the I/O libraries that must stay in drivers/, the outputs and the daemon
FORBIDDEN = {"zenoh", "socket", "mcap", "threading", "subprocess", "matplotlib", *HARDWARE_OWNERS}


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


def _check_layer(
    files: list[Path], allowed_project: tuple[str, ...], more_stdlib: frozenset[str] = frozenset()
) -> list[str]:
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
    """``robotd/slam/`` -> ``robotd.slam``, ``robotd/core/msgs.py`` -> ``robotd.core.msgs``,
    ``robotd/__init__.py`` -> ``robotd``."""
    return entry.removesuffix("/").removesuffix("/__init__.py").removesuffix(".py").replace("/", ".")


# the package's own name is no prefix here: ``robotd`` would let in every module of robotd
CORE_MODULES = tuple(_dotted(c) for c in CORE if not c.endswith("__init__.py"))
# what the config's loader (robotd/config/__init__.py) needs to read the TOML file: the
# pipeline's one file access
CONFIG_LOADER_LIBRARIES = frozenset({"pathlib", "tomllib", "re", "types"})


def test_core_imports_only_numeric_libraries() -> None:
    files = _files(CORE)
    assert len(files) > 20, "core files not found"
    bad = _check_layer(files, CORE_MODULES)
    assert not bad, "core modules import I/O or unexpected modules:\n" + "\n".join(bad)


def test_pipeline_imports_the_core_and_the_config_only() -> None:
    files = _files(PIPELINE)
    assert all((REPO / e).exists() for e in PIPELINE) and len(files) > len(PIPELINE)
    pipeline_modules = tuple(_dotted(p) for p in PIPELINE)
    loader = [f for f in files if _module_name(f) in MODULE_LIBRARIES]
    bad = _check_layer([f for f in files if f not in loader], (*CORE_MODULES, *pipeline_modules))
    bad += _check_layer(loader, (*CORE_MODULES, *pipeline_modules), CONFIG_LOADER_LIBRARIES)
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
    owners = HARDWARE_OWNERS
    assert owners["depthai"] == "drivers/oak"  # the OAK's, declared at its registration
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


# --- every row of the table -------------------------------------------------------------------


@dataclass(frozen=True)
class Rule:
    """What a layer's row lets its modules import, besides the modules of their own layer."""

    layers: frozenset[str] = frozenset()  # whole layers
    modules: tuple[str, ...] = ()  # single modules (or packages) of other layers
    never: tuple[str, ...] = ()  # modules not to import even so
    third_party: frozenset[str] | None = None  # None: any
    stdlib: frozenset[str] | None = None  # None: any but never_stdlib
    never_stdlib: frozenset[str] = frozenset()


CORE_LIBRARIES = frozenset(ALLOWED_THIRD_PARTY)
NO_NETWORK = frozenset({"socket", "subprocess", "multiprocessing", "selectors", "ssl"})
BELOW_TOOLS = frozenset({"core", "pipeline", "formats", "drivers", "service"})
RULES: dict[str, Rule] = {
    "core": Rule(third_party=CORE_LIBRARIES, stdlib=frozenset(STDLIB_OK)),
    "pipeline": Rule(layers=frozenset({"core"}), third_party=CORE_LIBRARIES, stdlib=frozenset(STDLIB_OK)),
    # the format libraries: mcap, cbor2, protobuf (google.protobuf) with Foxglove's schemas, zstandard;
    # files and a writer thread, no sockets or processes
    "formats": Rule(
        layers=frozenset({"core"}),
        third_party=frozenset({"numpy", "cv2", "mcap", "cbor2", "google", "foxglove_schemas_protobuf", "zstandard"}),
        never_stdlib=NO_NETWORK,
    ),
    # the hardware libraries' owners are test_each_hardware_library_has_one_importer's
    "drivers": Rule(
        layers=frozenset({"core"}),
        modules=("robotd.formats.queues", "robotd.formats.autopilot", "robotd.formats.record"),
        third_party=frozenset({"numpy", "cv2", "numba", "yaml", *HARDWARE_OWNERS}),
    ),
    "service": Rule(layers=frozenset({"core", "pipeline", "formats", "drivers"}), modules=("calib.camchain",)),
    "tools": Rule(layers=BELOW_TOOLS, modules=("robotd.research.evaluate", "robotd.research.experiments")),
    "research": Rule(layers=BELOW_TOOLS | {"tools"}, never=("robotd.daemon", "robotd.outputs")),
}
# config.py's loader reads the TOML file
MODULE_LIBRARIES: dict[str, frozenset[str]] = {"robotd.config": CONFIG_LOADER_LIBRARIES}


def _all_files() -> list[Path]:
    return [f for pkg in PACKAGES for f in sorted((REPO / pkg).rglob("*.py")) if "__pycache__" not in f.parts]


def _layer_of(rel: str) -> str | None:
    """The layer of the repository path ``rel`` by LAYERS (the longest entry that holds it)."""
    best: tuple[int, str | None] = (-1, None)
    for layer, entries in LAYERS.items():
        for e in entries:
            if (rel == e or (e.endswith("/") and rel.startswith(e))) and len(e) > best[0]:
                best = (len(e), layer)
    return best[1]


def _module_layers() -> dict[str, str]:
    out: dict[str, str] = {}
    for f in _all_files():
        layer = _layer_of(f.relative_to(REPO).as_posix())
        assert layer is not None, f"{f.relative_to(REPO)} is in no layer of LAYERS (and of docs/architecture.md)"
        out[_module_name(f)] = layer
    return out


def _project_violations(graph: dict[str, set[str]], layers: dict[str, str]) -> list[str]:
    bad: list[str] = []
    for m in sorted(graph):
        rule = RULES[layers[m]]
        for d in sorted(graph[m]):
            ok = layers[d] == layers[m] or layers[d] in rule.layers or _within(d, rule.modules)
            if not ok or _within(d, rule.never):
                bad.append(f"{m} ({layers[m]}) imports {d} ({layers[d]})")
    return bad


def _library_violations(files: list[Path], layers: dict[str, str]) -> list[str]:
    bad: list[str] = []
    for f in files:
        m = _module_name(f)
        rule = RULES[layers[m]]
        extra = MODULE_LIBRARIES.get(m, frozenset())
        for name in _imports(f):
            top = name.split(".")[0]
            if top in PACKAGES or not top:
                continue
            if top in sys.stdlib_module_names:
                ok = (rule.stdlib is None or top in rule.stdlib | extra) and top not in rule.never_stdlib
            else:
                ok = rule.third_party is None or top in rule.third_party | extra
            if not ok:
                bad.append(f"{f.relative_to(REPO)} ({layers[m]}) imports {top}")
    return sorted(set(bad))


def test_every_module_is_in_one_layer() -> None:
    layers = _module_layers()
    assert len(layers) > 100
    assert set(layers.values()) == set(LAYERS) == set(RULES)


def test_every_layer_is_a_folder() -> None:
    """The tree shows the layers: each entry of LAYERS is a package (a folder with its
    ``__init__.py``) but robotd's own two modules, and every module of robotd/ is in one of those
    folders: none sits beside them."""
    files = sorted(e for entries in LAYERS.values() for e in entries if not e.endswith("/"))
    assert files == sorted(TOP_LEVEL), f"LAYERS names files, not folders: {sorted(set(files) - set(TOP_LEVEL))}"
    folders = [e for entries in LAYERS.values() for e in entries if e.endswith("/")]
    bad = [f"{e} is no package" for e in folders if not (REPO / e / "__init__.py").is_file()]
    flat = sorted(p.relative_to(REPO).as_posix() for p in (REPO / "robotd").glob("*.py"))
    bad += [
        f"{f} sits beside the layers' folders: move it into its layer's package" for f in flat if f not in TOP_LEVEL
    ]
    subpackages = sorted(
        f"robotd/{d.name}/" for d in (REPO / "robotd").iterdir() if d.is_dir() and (d / "__init__.py").is_file()
    )
    bad += [f"{d} is in no layer of LAYERS" for d in subpackages if d not in folders]
    assert not bad, "\n".join(bad)


def test_the_drivers_import_the_core_and_three_modules_of_the_formats() -> None:
    """The drivers' row, held like every other (test_each_layer_imports_only_what_its_row_allows),
    and not vacuously: the drivers do import the core and the formats' record module."""
    graph, layers = _graph(), _module_layers()
    drivers = {m: deps for m, deps in graph.items() if layers[m] == "drivers"}
    assert len(drivers) > 20, "driver modules not found"
    used = {d for deps in drivers.values() for d in deps if layers[d] != "drivers"}
    assert {"robotd.core.msgs", "robotd.formats.record"} <= used, sorted(used)
    bad = [v for v in _project_violations(drivers, layers)]
    assert not bad, "the drivers import what their row does not allow:\n" + "\n".join(bad)


def test_each_layer_imports_only_what_its_row_allows() -> None:
    bad = _project_violations(_graph(), _module_layers())
    assert not bad, "imports the layer table of docs/architecture.md does not allow:\n" + "\n".join(bad)


def test_each_layer_uses_only_the_libraries_its_row_allows() -> None:
    bad = _library_violations(_all_files(), _module_layers())
    assert not bad, "libraries the layer table of docs/architecture.md does not allow:\n" + "\n".join(bad)


def test_the_layer_check_finds_a_violation() -> None:
    layers = {"robotd.core.geometry": "core", "robotd.pipeline.step": "pipeline", "drivers.sim": "drivers"}
    layers |= {"robotd.formats.record": "formats", "robotd.formats.codec": "formats", "robotd.daemon.x": "service"}
    layers |= {"robotd.research.sitl": "research", "calib.camchain": "tools"}
    graph = {
        "robotd.core.geometry": {"robotd.pipeline.step"},  # core up to the pipeline
        "robotd.pipeline.step": {"robotd.core.geometry"},
        "drivers.sim": {"robotd.formats.record", "robotd.formats.codec"},  # record may, codec may not
        "robotd.formats.record": set(),
        "robotd.formats.codec": set(),
        "robotd.daemon.x": {"calib.camchain", "robotd.research.sitl"},  # camchain may, research not
        "robotd.research.sitl": {"robotd.daemon.x"},  # never the daemon
        "calib.camchain": set(),
    }
    assert _project_violations(graph, layers) == [
        "drivers.sim (drivers) imports robotd.formats.codec (formats)",
        "robotd.core.geometry (core) imports robotd.pipeline.step (pipeline)",
        "robotd.daemon.x (service) imports robotd.research.sitl (research)",
        "robotd.research.sitl (research) imports robotd.daemon.x (service)",
    ]


# --- the page's table and LAYERS agree ----------------------------------------------------------

DOC = REPO / "docs" / "architecture.md"


def _doc_rows() -> dict[str, str]:
    """Layer -> its row's modules cell, from the table under "| layer | modules | may import |"."""
    lines = DOC.read_text(encoding="utf-8").splitlines()
    start = lines.index("| layer | modules | may import |")
    rows: dict[str, str] = {}
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        rows[cells[0]] = cells[1]
    return rows


def _doc_paths(cell: str) -> list[str]:
    """The repository paths a modules cell names outside its parentheses: a path in backticks
    (``robotd/core/msgs.py``, ``robotd/slam/``), or a bare file name (``errors.py``) in the folder of
    the last path before it."""
    while True:
        shorter = re.sub(r"\([^()]*\)", "", cell)
        if shorter == cell:
            break
        cell = shorter
    out: list[str] = []
    folder = ""
    for tok in re.findall(r"`([^`]+)`", cell):
        if not tok.endswith((".py", "/")):
            continue
        if "/" in tok:
            out.append(tok)
            folder = tok if tok.endswith("/") else tok.rpartition("/")[0] + "/"
        else:
            out.append(folder + tok)
    return out


def test_the_doc_table_and_the_layers_agree() -> None:
    rows = _doc_rows()
    assert set(rows) == set(LAYERS), f"the page's layers {sorted(rows)} are not LAYERS' {sorted(LAYERS)}"
    bad: list[str] = []
    for layer, cell in rows.items():
        for path in _doc_paths(cell):
            if not (REPO / path).exists():
                bad.append(f"the {layer} row names {path}, which does not exist")
            elif _layer_of(path) != layer:
                bad.append(f"the {layer} row names {path}; LAYERS puts it in {_layer_of(path)}")
        for entry in LAYERS[layer]:
            name = entry.rstrip("/").rpartition("/")[2] + ("/" if entry.endswith("/") else "")
            if entry not in cell and f"`{name}`" not in cell:
                bad.append(f"LAYERS puts {entry} in {layer}; the page's {layer} row does not name it")
    assert not bad, "\n".join(bad)
