"""The tree is the architecture (docs/architecture.md): layered packages, lowest first, each module importing only
from its own package or a lower layer; kernels mirror the host packages; first-party imports at module top; no
import circles, deferred imports counted."""

import ast
import pathlib

import pytest

from helpers import ROOT

# layer of each package, lowest first; sph and dda are side by side (neither imports the other)
LAYERS = {"base": 0, "sph": 1, "dda": 1, "coupling": 2, "scene": 3, "build": 4, "sim": 5, "output": 6, "app": 7}
PHYSICS = ("base", "sph", "dda", "coupling")
# deliberate exceptions: (importing module, imported module) with the reason
EXCEPTIONS = {
    ("rockwave.sim.simulation", "rockwave.app.run"): "Simulation.run hands a simulation over to the run loop",
}



def _modules() -> dict[str, pathlib.Path]:
    out = {}
    for base, prefix in ((ROOT / "rockwave", "rockwave"), (ROOT / "kernels", "rockwave.kernels")):
        for p in sorted(base.rglob("*.py")):
            rel = p.relative_to(base).with_suffix("")
            parts = [x for x in rel.parts if x != "__init__"]
            out[".".join([prefix, *parts])] = p
    return out


MODULES = _modules()


def _imports(path: pathlib.Path):
    """(imported module, line, at module top) for every first-party import of a file, deferred ones included."""
    tree = ast.parse(path.read_text())
    top = {id(n) for n in tree.body}
    # an import in a module-level `if TYPE_CHECKING:` or try block counts as top
    for n in tree.body:
        if isinstance(n, (ast.If, ast.Try)):
            top |= {id(c) for c in ast.walk(n)}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("rockwave"):
            for a in node.names:
                full = f"{node.module}.{a.name}"
                yield (full if full in MODULES else node.module), node.lineno, id(node) in top
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("rockwave"):
                    yield a.name, node.lineno, id(node) in top


def _package(mod: str) -> tuple[str, str]:
    """('host' | 'kernels', package) of a module name."""
    parts = mod.split(".")
    if len(parts) < 2:
        return "host", ""
    if parts[1] == "kernels":
        return "kernels", parts[2] if len(parts) > 3 else ""
    return "host", parts[1] if len(parts) > 2 else ""


def test_no_module_at_the_top_but_the_package_face():
    top = sorted(p.name for p in (ROOT / "rockwave").glob("*.py"))
    assert top == ["__init__.py", "__main__.py"], top
    ktop = sorted(p.name for p in (ROOT / "kernels").glob("*.py"))
    assert ktop == ["__init__.py"], ktop
    for mod in MODULES:
        kind, pkg = _package(mod)
        if mod.count(".") >= (3 if kind == "kernels" else 2):
            assert pkg in LAYERS, f"{mod}: package {pkg!r} has no layer"


def test_kernels_pair_with_host_modules_by_path():
    """Every kernel module's package is a host package; a kernel module with a host module of the same name pairs
    with it (rockwave/sph/fluid.py <-> kernels/sph/fluid.py)."""
    for mod in MODULES:
        kind, pkg = _package(mod)
        if kind == "kernels" and pkg:
            assert (ROOT / "rockwave" / pkg).is_dir(), f"{mod}: no host package rockwave/{pkg}/"


@pytest.mark.parametrize("mod", sorted(m for m in MODULES if m not in ("rockwave", "rockwave.__main__")))
def test_imports_go_down_the_layers_and_sit_at_module_top(mod):
    kind, pkg = _package(mod)
    errors = []
    for target, line, at_top in _imports(MODULES[mod]):
        where = f"{MODULES[mod].relative_to(ROOT)}:{line} imports {target}"
        if target == "rockwave":
            errors.append(f"{where}: the package face (import from the module that defines the name)")
            continue
        if (mod, target) in EXCEPTIONS:  # deferred, so that the writers load only when a run writes
            if at_top:
                errors.append(f"{where}: an upward exception ({EXCEPTIONS[(mod, target)]}) must be imported where used")
            continue
        if not at_top:
            errors.append(f"{where} inside a function (first-party imports sit at module top)")
        tkind, tpkg = _package(target)
        if kind == "kernels" and tkind == "host":
            errors.append(f"{where}: kernels import no host code")
            continue
        if not pkg or not tpkg or tpkg == pkg:
            continue
        if LAYERS[tpkg] > LAYERS[pkg] or (LAYERS[tpkg] == LAYERS[pkg]):
            errors.append(f"{where}: {tpkg} is not below {pkg}")
        if pkg in PHYSICS and tpkg == "scene":
            errors.append(f"{where}: physics never reads the scene")
    assert not errors, "\n".join(errors)


def test_no_import_circles():
    graph = {m: {t for t, _, _ in _imports(p) if t in MODULES and t != m} for m, p in MODULES.items()}
    for m, deps in graph.items():  # `from rockwave.sph import fluid` reaches the package first
        graph[m] = deps | {".".join(t.split(".")[:-1]) for t in deps if ".".join(t.split(".")[:-1]) in MODULES} - {m}
    graph["rockwave"] = set()  # the package face imports the API; nothing inside imports it (checked above)
    state, stack, cycles = {}, [], []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for t in sorted(graph.get(m, ())):
            if state.get(t) == 1:
                cycles.append(stack[stack.index(t):] + [t])
            elif t not in state:
                visit(t)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)
    assert not cycles, "\n".join(" -> ".join(c) for c in cycles)


SCENE_ARGS = ("scene", "scene_fluid", "cfg", "fluid_section")


@pytest.mark.parametrize("mod", sorted(m for m in MODULES if _package(m)[0] == "host" and _package(m)[1] in PHYSICS))
def test_physics_takes_no_scene(mod):
    """Physics receives typed options and parameters (rockwave/build/options.py makes them from the scene): no function
    of base, sph, dda or coupling takes a scene or one of its sections, and no Options class reads one (from_scene)."""
    tree = ast.parse(MODULES[mod].read_text())
    errors = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            if node.name == "from_scene":
                errors.append(f"{mod}:{node.lineno} from_scene (scene -> options belongs in rockwave/build/options.py)")
            a = node.args
            for arg in a.posonlyargs + a.args + a.kwonlyargs:
                if arg.arg in SCENE_ARGS:
                    errors.append(f"{mod}:{node.lineno} {node.name}({arg.arg}): physics takes typed options, not the scene")
    assert not errors, "\n".join(errors)
