"""The house rules of ``../shared/STYLE.md`` §1: imports only point down."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "diffaccel"

# room -> diffaccel rooms it may import
ALLOWED: dict[str, set[str]] = {
    "dynamics": set(),
    "data": {"dynamics"},
    "hysteresis": {"dynamics", "data"},
    "reconstruction": {"dynamics", "data"},
    "plotting": {"dynamics", "data", "hysteresis", "reconstruction"},
    "cli": {"dynamics", "data", "hysteresis", "reconstruction", "plotting"},
}
# third-party packages a room may not import (heavy or out of its concern)
FORBIDDEN_THIRD_PARTY: dict[str, set[str]] = {
    "dynamics": {"matplotlib", "h5py", "gpytorch", "botorch", "click", "tqdm"},
    "data": {"matplotlib", "gpytorch", "botorch", "click", "tqdm"},
    "hysteresis": {"matplotlib", "click", "tqdm"},
    "reconstruction": {"matplotlib", "gpytorch", "botorch", "click", "tqdm"},
    "plotting": {"click", "tqdm"},
}


def _modules() -> list[Path]:
    return sorted(p for p in SRC.rglob("*.py"))


def _room(path: Path) -> str | None:
    rel = path.relative_to(SRC).parts
    return rel[0] if len(rel) > 1 else None


def _imports(path: Path) -> list[tuple[str, int, bool]]:
    """(module, line, top_level) for every import in ``path``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    top_nodes = {id(n) for n in tree.body}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                found.append((alias.name, node.lineno, id(node) in top_nodes))
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.module, node.lineno, id(node) in top_nodes))
    return found


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(SRC)))
def test_imports_point_down(path: Path) -> None:
    room = _room(path)
    if room is None:  # diffaccel/__init__.py, __main__.py
        return
    for module, line, _ in _imports(path):
        parts = module.split(".")
        if parts[0] == "diffaccel" and len(parts) > 1 and parts[1] != room:
            assert parts[1] in ALLOWED[room], (
                f"{path.name}:{line}: room '{room}' imports diffaccel.{parts[1]}"
            )
        assert parts[0] not in FORBIDDEN_THIRD_PARTY.get(room, set()), (
            f"{path.name}:{line}: room '{room}' imports {parts[0]}"
        )


def _lazy_attribute_lines(path: Path) -> set[int]:
    """Lines of imports inside a package ``__init__``'s module-level ``__getattr__``."""
    if path.name != "__init__.py":
        return set()
    tree = ast.parse(path.read_text(), filename=str(path))
    lines = set()
    for node in tree.body:
        if isinstance(node, ast.FunctionDef) and node.name == "__getattr__":
            for sub in ast.walk(node):
                if isinstance(sub, ast.Import | ast.ImportFrom):
                    lines.add(sub.lineno)
    return lines


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(SRC)))
def test_no_type_checking_or_function_level_diffaccel_imports(path: Path) -> None:
    text = path.read_text()
    assert "TYPE_CHECKING" not in text, f"{path}: cycles are fixed by rooms"
    # One exception: a room's package __init__ may load its own heavy modules on
    # first use of their names (PEP 562 module __getattr__), e.g. the GP parts of
    # diffaccel.hysteresis, so that light commands do not import gpytorch/botorch.
    # Only the room's own modules: it cannot point up or sideways.
    lazy = _lazy_attribute_lines(path)
    room = _room(path)
    for module, line, top in _imports(path):
        if not module.startswith("diffaccel") or top:
            continue
        if line in lazy and module.split(".")[:2] == ["diffaccel", room]:
            continue
        pytest.fail(f"{path.name}:{line}: diffaccel import inside a function")


def test_top_level_package_holds_version_only() -> None:
    tree = ast.parse((SRC / "__init__.py").read_text())
    names = [t.id for n in tree.body if isinstance(n, ast.Assign) for t in n.targets]
    assert names == ["__version__"]
    assert not any(isinstance(n, ast.Import | ast.ImportFrom) for n in tree.body)


def test_dynamics_import_stays_light() -> None:
    code = (
        "import sys, diffaccel.dynamics\n"
        "heavy = {'matplotlib', 'h5py', 'gpytorch', 'botorch'} & set(sys.modules)\n"
        "print(sorted(heavy))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "[]", out.stdout


def test_hysteresis_import_loads_gp_parts_on_first_use() -> None:
    # predicting with a Preisach model must not pay for gpytorch/botorch
    code = (
        "import sys, diffaccel.hysteresis as h\n"
        "gp = {'gpytorch', 'botorch', 'matplotlib'}\n"
        "print(sorted(gp & set(sys.modules)))\n"
        "from diffaccel.hysteresis import HysteresisGP, HysteresisBO\n"
        "print(HysteresisGP.__name__, h.fit_hysteresis_gp.__name__, "
        "sorted({'gpytorch', 'botorch'} & set(sys.modules)))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    )
    assert out.stdout.split("\n")[:2] == [
        "[]",
        "HysteresisGP fit_hysteresis_gp ['botorch', 'gpytorch']",
    ], out.stdout


# Deferred imports by name. The one allowed use: cli/main.py loads a command's
# module when that command runs, so `diffaccel --help` imports no command. cli is
# the leaf room (nothing imports it), so this cannot hide a cycle; anywhere else
# importlib/__import__ would dodge the rules above.
DYNAMIC_IMPORT_ALLOWED = {Path("cli/main.py")}


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(SRC)))
def test_no_dynamic_imports_outside_the_command_loader(path: Path) -> None:
    if path.relative_to(SRC) in DYNAMIC_IMPORT_ALLOWED:
        return
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        name = None
        if isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", None)
        assert name not in ("import_module", "__import__"), (
            f"{path.name}:{node.lineno}: dynamic import outside cli/main.py"
        )


def test_command_loader_loads_only_cli_modules() -> None:
    from diffaccel.cli.main import COMMANDS, SUBCOMMANDS

    modules = [m for m, _, _ in COMMANDS.values()]
    modules += [m for subs in SUBCOMMANDS.values() for m, _, _ in subs.values()]
    assert all(m.startswith("diffaccel.cli.") for m in modules), modules
