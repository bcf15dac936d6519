"""Checks that keep the code readable, from its syntax trees: no module reaches into another's
private names, functions stay short, and the library does not import the applications.

A function over ``MAX_LINES`` is refused unless it is in ``LONG_FUNCTIONS``, the ones that were
already longer when these checks came in, each held to the length it had then: the list may
only shrink (remove an entry when its function is split)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("iiwa_torch", "envs", "train", "benchmarks")
MAX_LINES = 60

LONG_FUNCTIONS: dict[str, int] = {}  # "path:function" -> its length in lines when the check came in


def _modules() -> list[tuple[str, ast.Module]]:
    files = sorted(p for package in PACKAGES for p in (ROOT / package).rglob("*.py"))
    return [(p.relative_to(ROOT).as_posix(), ast.parse(p.read_text(), filename=str(p))) for p in files]


MODULES = _modules()


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _function_lengths(tree: ast.Module) -> dict[str, int]:
    """Every function and method's length in lines (decorators excluded), by name; the longest
    of a name wins."""
    lengths: dict[str, int] = {}
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            length = node.end_lineno - node.lineno + 1
            lengths[node.name] = max(length, lengths.get(node.name, 0))
    return lengths


def test_the_checks_see_the_packages():
    assert len(MODULES) > 40
    assert _function_lengths(ast.parse("def f():\n    a = 1\n    return a\n")) == {"f": 3}


def test_no_function_grows_past_its_limit():
    too_long = []
    for path, tree in MODULES:
        for name, length in _function_lengths(tree).items():
            limit = LONG_FUNCTIONS.get(f"{path}:{name}", MAX_LINES)
            if length > limit:
                too_long.append(f"{path}:{name} has {length} lines (limit {limit})")
    assert not too_long, "split these functions:\n" + "\n".join(too_long)


def test_the_list_of_long_functions_only_shrinks():
    """An entry whose function is gone or now short must leave the list (so it cannot regrow)."""
    lengths = {f"{path}:{name}": n for path, tree in MODULES for name, n in _function_lengths(tree).items()}
    stale = [key for key in LONG_FUNCTIONS if lengths.get(key, 0) <= MAX_LINES]
    assert not stale, f"remove from LONG_FUNCTIONS (split or gone): {stale}"


def _ours(node: ast.ImportFrom) -> bool:
    """Whether ``from ... import`` reads one of this project's modules (relative, or in ``PACKAGES``)."""
    return node.level > 0 or (node.module or "").split(".")[0] in PACKAGES


def _imported_modules(tree: ast.Module) -> set[str]:
    """The names a module binds to this project's modules (``import iiwa_torch.dh as d`` -> ``d``,
    ``from iiwa_torch import collision`` -> ``collision``)."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.asname or a.name.split(".")[0] for a in node.names if a.name.split(".")[0] in PACKAGES}
        elif isinstance(node, ast.ImportFrom) and _ours(node):
            names |= {a.asname or a.name for a in node.names}
    return names


@pytest.mark.parametrize("path,tree", MODULES, ids=[p for p, _ in MODULES])
def test_no_private_names_of_other_modules(path, tree):
    """``from m import _x`` and ``m._x`` for a module ``m`` of this project are refused; a module's
    own private names, and dunders, are its business (so are third-party libraries')."""
    modules = _imported_modules(tree)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and _ours(node):
            found += [f"from {node.module} import {a.name}" for a in node.names if _private(a.name)]
        elif (isinstance(node, ast.Attribute) and _private(node.attr) and isinstance(node.value, ast.Name)
              and node.value.id in modules):
            found.append(f"{node.value.id}.{node.attr} (line {node.lineno})")
    assert not found, f"{path} uses private names of other modules: {found}"


def test_the_library_does_not_import_the_applications():
    """``iiwa_torch`` imports neither ``envs`` nor ``train`` (the CLI reaches the training code's
    playback through an entry point)."""
    found = []
    for path, tree in MODULES:
        if not path.startswith("iiwa_torch/"):
            continue
        for node in ast.walk(tree):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            if isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module or ""]
            found += [f"{path}: {name}" for name in names if name.split(".")[0] in ("envs", "train")]
    assert not found, found


def test_the_readme_stays_a_short_guide():
    """Reference goes to docs/, history to CHANGELOG.md and the RECORD.md files."""
    assert len((ROOT / "README.md").read_text().splitlines()) <= 250


def _thresholds() -> list[str]:
    """Module-level integer constants named ``*_BATCH``, ``*_BLOCK`` or ``*_ROWS``: the batch sizes at
    which a call changes path, as ``module.NAME`` (package prefix dropped)."""
    found = []
    for path, tree in MODULES:
        if path.startswith("benchmarks/"):
            continue
        module = path.removesuffix(".py").replace("/", ".").removeprefix("iiwa_torch.")
        for node in tree.body:
            if (isinstance(node, ast.Assign) and isinstance(node.value, ast.Constant)
                    and type(node.value.value) is int):
                found += [f"{module}.{t.id}" for t in node.targets if isinstance(t, ast.Name)
                          and t.id.endswith(("_BATCH", "_BLOCK", "_ROWS")) or getattr(t, "id", "") == "BLOCK"]
    return found


def test_every_path_threshold_is_in_the_table():
    """docs/kinematics.md's "Path thresholds" lists every batch size that chooses a path."""
    table = (ROOT / "docs" / "kinematics.md").read_text().split("## Path thresholds")[1].split("\n## ")[0]
    names = _thresholds()
    assert len(names) >= 10
    missing = [name for name in names if f"`{name}`" not in table]
    assert not missing, f"add to docs/kinematics.md's Path thresholds: {missing}"


#: Module constants that share a name with different values on purpose: each subsystem's array
#: namespace over torch or numpy (``iiwa_torch.ik.analytic._common`` for the closed forms,
#: ``envs.arrays`` for the env step).
SHARED_CONSTANTS = {"NUMPY", "TORCH"}


def test_no_two_constants_share_a_name():
    """In the packages (not the benchmark scripts, each its own program), a module-level UPPER_CASE
    name means one thing: the same name in two modules must have the same value (an alias such as
    ``_F64 = torch.float64``). Two thresholds both called ``SMALL_BATCH`` with different meanings
    were how this check came about."""
    values: dict[str, dict[str, str]] = {}
    for path, tree in MODULES:
        if path.startswith("benchmarks/"):
            continue
        for node in tree.body:
            if isinstance(node, (ast.Assign, ast.AnnAssign)) and node.value is not None:
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                for target in targets:
                    if isinstance(target, ast.Name) and target.id.lstrip("_").isupper() and len(target.id) > 2:
                        values.setdefault(target.id, {})[path] = ast.unparse(node.value)
    clashes = {name: found for name, found in values.items()
               if len(set(found.values())) > 1 and name not in SHARED_CONSTANTS}
    assert not clashes, clashes
