"""The architecture's rules that code can break silently (docs/service.md, "Layers"): the import
graph (fpm imports no other package of ours; the service neither the job runner, the local
stack nor the exporters (fpm.io); the store none above it), Redis keys built only in the
store, and a service that validates specs with fpm.model.spec / fpm.model.problem but never
loads the numerical kernels."""

import ast
import inspect
import re
import subprocess
import sys
from pathlib import Path

import pytest

from store import keys

KERNELS = (
    "numba",
    "fpm.dynamics.voigt",
    "fpm.dynamics.simulation",
    "fpm.fem.reference",
    "fpm.fitting.calibration",
    "pyamg",
)


def test_the_service_does_not_import_the_numerical_kernels():
    code = f"import sys, service.main\nprint([m for m in {KERNELS!r} if m in sys.modules])\n"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_the_service_never_imports_the_exporters():
    """Exports are a worker's job (worker.jobs.export_parameter_set): no module of the service
    imports fpm.io, not even lazily inside a route."""
    assert arrows("service", "fpm") != []
    assert [a for a in arrows("service", "fpm") if a.split(" -> ")[1].startswith("fpm.io")] == []


def test_fpm_public_names_load_on_first_use():
    import fpm

    assert set(fpm.__all__) >= {"load_problem", "simulate", "solve_fem", "calibrate"}
    assert callable(fpm.calibrate) and fpm.ProblemSpec.__name__ == "ProblemSpec"


ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("fpm", "fpmcal", "store", "worker", "service", "stack", "client")


def imports_of(package: str) -> dict[str, set[str]]:
    """Module path -> the project modules it imports (lazy imports in functions included)."""
    found: dict[str, set[str]] = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        module = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        names: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:  # relative: resolve against this module's package
                    parent = module.split(".")[: -node.level]
                    base = ".".join([*parent, base] if base else parent)
                names.update(f"{base}.{a.name}" for a in node.names)
                names.add(base)
        found[module] = {n for n in names if n.split(".")[0] in PACKAGES}
    return found


def arrows(source: str, target: str) -> list[str]:
    return sorted(
        f"{module} -> {name}"
        for module, names in imports_of(source).items()
        for name in names
        if name.split(".")[0] == target
    )


@pytest.mark.parametrize("target", [p for p in PACKAGES if p != "fpm"])
def test_the_numerical_core_imports_no_other_package(target):
    assert arrows("fpm", target) == []


@pytest.mark.parametrize("target", ["worker", "stack", "fpmcal", "client"])
def test_the_service_imports_neither_the_job_runner_nor_the_local_stack(target):
    assert arrows("service", target) == []


@pytest.mark.parametrize("target", ["worker", "service", "stack", "fpmcal", "client"])
def test_the_store_sits_below_the_service_and_the_workers(target):
    assert arrows("store", target) == []


KEY_BUILDERS = {
    name
    for name, value in vars(keys).items()
    if inspect.isfunction(value)
    and value.__module__ == keys.__name__
    and not name.endswith("_id")  # ids (of jobs, parameter sets) are not Redis keys
}


def test_redis_keys_are_built_only_in_the_store():
    """Outside ``store`` no code names a key of ours: every read and write goes through it."""
    assert KEY_BUILDERS >= {"calibration", "fem_reference", "chain_checkpoint", "parameter_set"}
    uses = []
    for package in PACKAGES:
        if package == "store":
            continue
        for path in sorted((ROOT / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if (
                    isinstance(node, ast.Attribute)
                    and isinstance(node.value, ast.Name)
                    and node.value.id == "keys"
                    and node.attr in KEY_BUILDERS
                ):
                    uses.append(f"{path.relative_to(ROOT)}:{node.lineno} keys.{node.attr}")
    assert uses == []


def test_the_store_takes_only_the_spec_from_the_numerical_core():
    names = [a.split(" -> ")[1] for a in arrows("store", "fpm")]
    assert names and all(n.startswith("fpm.model.spec") for n in names), names


def layout_blocks() -> dict[str, str]:
    """The manual's layout page (docs/explanation/layout.md): package path ('fpm', 'fpm/model',
    ...) -> its text."""
    page = (ROOT / "docs" / "explanation" / "layout.md").read_text()
    section = page.split("```text\n", 1)[1].split("```")[0]
    blocks: dict[str, str] = {}
    parent, current = "", ""
    for line in section.splitlines():
        top = re.match(r"(\w+)/\s", line + " ")
        sub = re.match(r"  (\w+)/\s", line + " ")
        if top:
            parent = current = top.group(1)
        elif sub:
            current = f"{parent}/{sub.group(1)}"
        if current:
            blocks[current] = blocks.get(current, "") + " " + line
    return blocks


def test_the_layout_page_matches_the_tree():
    """Every package and fpm subpackage has its entry, and each entry names its modules."""
    blocks = layout_blocks()
    packages = sorted(
        str(init.parent.relative_to(ROOT))
        for init in ROOT.glob("*/**/__init__.py")
        if init.parent.parent == ROOT or init.parent.parent.name == "fpm"
    )
    assert sorted(b for b in blocks if b not in ("tests", "docs")) == packages
    for package in packages:
        modules = {
            p.stem for p in (ROOT / package).glob("*.py") if p.stem not in ("__init__", "__main__")
        }
        modules |= {
            p.name
            for p in (ROOT / package).iterdir()
            if (p / "__init__.py").exists() and f"{package}/{p.name}" not in blocks
        }
        missing = [m for m in sorted(modules) if not re.search(rf"\b{m}\b", blocks[package])]
        assert missing == [], f"docs/explanation/layout.md, {package}/: {missing}"


# The numerical core's plan (docs/explanation/layout.md): each subpackage of fpm imports
# only from the layers below it; fitting and io sit side by side and never import each other;
# no module imports, even lazily, a module that imports it back.
LAYERS = {"model": 0, "fem": 1, "dynamics": 2, "fitting": 3, "io": 3, "native": 4}


def module_graph(package: str = "fpm") -> dict[str, set[str]]:
    """Module -> the modules of ``package`` it imports (lazy ones too), names resolved to the
    module that holds them (``from .x import name`` is an arrow to ``x``, or to ``x.name``
    where that is a module). Package ``__init__`` modules are left out: they only document,
    and fpm's loads its public names on first use."""
    modules = {
        ".".join(p.relative_to(ROOT).with_suffix("").parts)
        for p in (ROOT / package).rglob("*.py")
        if p.stem != "__init__"
    }
    return {
        module: {n for n in names if n in modules and n != module}
        for module, names in imports_of(package).items()
        if module in modules
    }


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def test_cycles_finds_a_loop_and_only_loops():
    """The checker itself: a loop through three modules is one component; a chain is none."""
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set()}
    assert cycles(graph) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []


@pytest.mark.parametrize("package", PACKAGES)
def test_no_import_loops(package):
    assert cycles(module_graph(package)) == []


def test_fpm_imports_only_downward():
    """model < fem < dynamics < fitting, io (the last two not into each other)."""
    wrong = []
    for module, names in module_graph("fpm").items():
        here = module.split(".")[1]
        for name in names:
            there = name.split(".")[1]
            if here in LAYERS and there in LAYERS and there != here:
                if LAYERS[there] >= LAYERS[here]:
                    wrong.append(f"{module} -> {name}")
    assert wrong == []


def test_every_fpm_subpackage_has_a_layer():
    subpackages = {p.parent.name for p in (ROOT / "fpm").glob("*/__init__.py")}
    assert subpackages <= set(LAYERS), subpackages - set(LAYERS)
