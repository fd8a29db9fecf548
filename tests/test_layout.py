"""The package's layering, read from the source: commands on top, imported by the CLI alone; the gate's
mode written by the runtime layer alone; no module over 500 lines; every benchmark that needs a trained
policy or a dataset says so for `make bench`."""

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = [
    ROOT / "lerobot_suture",
    ROOT / "policies",
    ROOT / "envs",
    ROOT / "robots",
    ROOT / "teleoperators",
    ROOT / "chain",
    ROOT / "studies",
]
SOURCES = sorted(p for package in PACKAGES for p in package.rglob("*.py") if ".venv" not in p.parts)
MAX_MODULE_LINES = 500


def _module(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    if parts[0] in ("policies", "envs", "robots", "teleoperators", "chain", "studies"):
        parts = parts[1:]
    return ".".join(p for p in parts if p != "__init__")


def _imports(tree: ast.AST) -> set[str]:
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names |= {f"{node.module}.{alias.name}" for alias in node.names}
    return names


def _enforce_writes(tree: ast.AST) -> list[int]:
    """Lines that assign ``<...>.ood.enforce``."""
    lines = []
    for node in ast.walk(tree):
        targets = node.targets if isinstance(node, ast.Assign) else [getattr(node, "target", None)]
        for target in targets:
            if isinstance(target, ast.Attribute) and target.attr == "enforce":
                owner = target.value
                if (isinstance(owner, ast.Attribute) and owner.attr == "ood") or (
                    isinstance(owner, ast.Name) and owner.id == "ood"
                ):
                    lines.append(node.lineno)
    return lines


@pytest.fixture(scope="module")
def trees() -> dict[str, tuple[Path, ast.AST]]:
    return {_module(p): (p, ast.parse(p.read_text(), filename=str(p))) for p in SOURCES}


def test_the_scan_sees_the_package(trees):
    assert {
        "lerobot_suture.cli",
        "lerobot_suture.runtime.policy",
        "lerobot_suture.commands.experiments",
    } <= set(trees)
    assert _enforce_writes(ast.parse("runner.policy.config.ood.enforce = True")) == [1]
    assert _enforce_writes(ast.parse("ood.enforce = x")) == [1]


def test_only_the_runtime_layer_writes_the_gate_mode(trees):
    writers = {
        f"{name}:{line}"
        for name, (_, tree) in trees.items()
        for line in _enforce_writes(tree)
        if not name.startswith("lerobot_suture.runtime.")
    }
    assert not writers, f"`ood.enforce` written outside lerobot_suture.runtime: {sorted(writers)}"


def test_commands_are_imported_by_the_cli_alone_and_nothing_imports_the_cli(trees):
    offenders = []
    for name, (_, tree) in trees.items():
        imported = _imports(tree)
        if name != "lerobot_suture.cli" and any(
            i == "lerobot_suture.cli" or i.startswith("lerobot_suture.cli.") for i in imported
        ):
            offenders.append(f"{name} imports lerobot_suture.cli")
        if not name.startswith("lerobot_suture.commands") and any(
            i.startswith("lerobot_suture.commands") for i in imported
        ):
            offenders.append(f"{name} imports a command")
    assert not offenders, offenders


def test_nothing_in_the_product_or_its_plugins_imports_the_studies(trees):
    """The studies (``studies/``) import the product; the product and its plugins never import them back,
    not even inside a function (the CLI runs a study's command by its module's name)."""
    assert any(name.startswith("lerobot_suture_studies.") for name in trees), "the scan misses the studies"
    offenders = [
        f"{name} imports {imported}"
        for name, (_, tree) in trees.items()
        if not name.startswith("lerobot_suture_studies")
        for imported in _imports(tree)
        if imported == "lerobot_suture_studies" or imported.startswith("lerobot_suture_studies.")
    ]
    assert not offenders, offenders


def test_the_layers_below_the_runtime_never_import_it(trees):
    below = (
        "lerobot_suture.sim",
        "lerobot_suture.safety",
        "lerobot_suture.detectors",
        "lerobot_suture.datasets",
    )
    offenders = [
        name
        for name, (_, tree) in trees.items()
        if name.startswith(below) and any(i.startswith("lerobot_suture.runtime") for i in _imports(tree))
    ]
    assert not offenders, offenders


def _local_imports(path: Path, tree: ast.AST, modules: set[str]) -> set[str]:
    """The modules of ``modules`` that ``tree`` (the source of ``path``) imports, at any depth, relative
    imports resolved (``from . import x`` imports the submodule ``x``, not its package)."""
    name = _module(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            candidates = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                parts = parts[: len(parts) - (node.level - 1)]
                base = ".".join(parts + ([node.module] if node.module else []))
            submodules = [f"{base}.{alias.name}" for alias in node.names]
            candidates = [m for m in submodules if m in modules] or [base]
        else:
            continue
        found |= {c for c in candidates if c in modules and c != name}
    return found


def test_no_import_circles():
    """No module imports, at any depth and even inside a function, one that imports it back."""
    modules = {_module(p): p for p in SOURCES}
    graph = {name: _local_imports(p, ast.parse(p.read_text()), set(modules)) for name, p in modules.items()}
    circles = []
    for start in graph:
        stack, seen = [(start, [start])], set()
        while stack:
            node, trail = stack.pop()
            for nxt in graph[node]:
                if nxt == start:
                    circles.append(" -> ".join([*trail, start]))
                elif nxt not in seen:
                    seen.add(nxt)
                    stack.append((nxt, [*trail, nxt]))
    assert not circles, "import circles:\n" + "\n".join(sorted(circles)[:20])


_LEAVES = {"lerobot_suture.plotting", "lerobot_suture.checks"}
FLOORS = {
    "lerobot_suture.sim": {"lerobot_suture.sim", *_LEAVES},
    "lerobot_suture.expert_plans": {"lerobot_suture.sim", "lerobot_suture.expert_plans", *_LEAVES},
    "lerobot_suture.safety": {"lerobot_suture.sim", "lerobot_suture.safety", *_LEAVES},
    "lerobot_suture.plotting": set(),
    "lerobot_suture.checks": set(),
    "lerobot_suture.lerobot_shim": set(),
    "lerobot_suture.datasets": {
        "lerobot_suture.sim",
        "lerobot_suture.expert",
        "lerobot_suture.expert_plans",
        "lerobot_suture.datasets",
        *_LEAVES,
    },
}
"""The bottom floors and what each may import of the package: nothing above it."""


def test_the_bottom_floors_import_nothing_above_them(trees):
    offenders = []
    for name, (_, tree) in trees.items():
        floor = next((f for f in FLOORS if name == f or name.startswith(f + ".")), None)
        if floor is None:
            continue
        for imported in _imports(tree):
            if imported.startswith("lerobot_suture.") and not any(
                imported == a or imported.startswith(a + ".") for a in FLOORS[floor]
            ):
                offenders.append(f"{name} imports {imported}")
    assert not offenders, sorted(offenders)


def test_no_module_is_over_500_lines():
    long = {
        str(p.relative_to(ROOT)): n
        for p in SOURCES
        if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES
    }
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


NEEDS_LINE = re.compile(r'^NEEDS = "(.*)"$', re.MULTILINE)  # what `make bench` reads (Makefile, sed)


def _needs_an_input(tree: ast.AST) -> bool:
    """A required option, a positional argument that must be given, or the failure benchmarks' command line."""
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call) or not isinstance(node.func, (ast.Attribute, ast.Name)):
            continue
        name = node.func.attr if isinstance(node.func, ast.Attribute) else node.func.id
        keywords = {k.arg: k.value for k in node.keywords}
        if name == "run_nominal_seeds":
            return True
        if name not in (
            "add_argument",
            "add_mutually_exclusive_group",
        ):  # a required group: one must be given
            continue
        required = keywords.get("required")
        if isinstance(required, ast.Constant) and required.value is True:
            return True
        first = node.args[0] if node.args else None
        nargs = keywords.get("nargs")
        optional_nargs = isinstance(nargs, ast.Constant) and nargs.value in ("?", "*")
        if isinstance(first, ast.Constant) and not str(first.value).startswith("-") and not optional_nargs:
            return True
    return False


BENCHMARKS = sorted(
    [*(ROOT / "benchmarks").glob("[!_]*.py"), *(ROOT / "studies" / "benchmarks").glob("[!_]*.py")]
)


@pytest.mark.parametrize("script", BENCHMARKS, ids=lambda p: str(p.relative_to(ROOT)))
def test_a_benchmark_that_needs_a_policy_or_dataset_declares_it_for_make_bench(script):
    """`make bench` runs every script bare except those with a NEEDS line, which it names and skips."""
    source = script.read_text()
    declared = NEEDS_LINE.search(source)
    if _needs_an_input(ast.parse(source)):
        assert declared and declared.group(1).strip(), f'{script.name}: add NEEDS = "what to pass"'
    else:
        assert not declared, f"{script.name} runs bare; its NEEDS line would make `make bench` skip it"
