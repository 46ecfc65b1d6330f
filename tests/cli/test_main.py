"""The ``diffaccel`` group: commands load when they run, ``--help`` stays light."""

from __future__ import annotations

import subprocess
import sys

import click
import pytest
from click.testing import CliRunner

from diffaccel.cli.main import COMMANDS, SUBCOMMANDS, load_command, main

# libraries no command listing needs (torch alone takes seconds to import)
HEAVY = ("torch", "numpy", "scipy", "h5py", "matplotlib", "gpytorch", "botorch", "tqdm")


def test_help_imports_no_command_module_and_no_heavy_library() -> None:
    code = (
        "import sys\n"
        "from diffaccel.cli.main import main\n"
        "try:\n"
        "    main(['--help'])\n"
        "except SystemExit:\n"
        "    pass\n"
        f"heavy = sorted({set(HEAVY)!r} & set(sys.modules))\n"
        "cmds = sorted(m for m in sys.modules if m.startswith('diffaccel.cli.')"
        " and m != 'diffaccel.cli.main')\n"
        "print('RESULT', heavy, cmds)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    )
    assert "RESULT [] []" in out.stdout, out.stdout
    for name in COMMANDS:  # every command is still listed
        assert f"\n  {name} " in out.stdout


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_table_help_line_is_the_commands_own(name: str) -> None:
    cmd = load_command(name)
    assert isinstance(cmd, click.Command)
    assert cmd.get_short_help_str(limit=1000) == COMMANDS[name][2]


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_command_help_runs(name: str) -> None:
    result = CliRunner().invoke(main, [name, "--help"])
    assert result.exit_code == 0, result.output
    assert result.output.startswith(f"Usage: main {name} ")


SUBS = [(g, name) for g, subs in SUBCOMMANDS.items() for name in sorted(subs)]


@pytest.mark.parametrize(("group", "name"), SUBS, ids=[f"{g}-{n}" for g, n in SUBS])
def test_subcommands_load_from_the_table(group: str, name: str) -> None:
    cmd = load_command(group)
    assert isinstance(cmd, click.Group)
    assert cmd.list_commands(click.Context(cmd)) == sorted(SUBCOMMANDS[group])
    module, attr, help_line = SUBCOMMANDS[group][name]
    sub = cmd.get_command(click.Context(cmd), name)
    assert sub is getattr(sys.modules[module], attr)
    assert sub.name == name
    assert sub.get_short_help_str(limit=1000) == help_line
    result = CliRunner().invoke(main, [group, name, "--help"])
    assert result.exit_code == 0, result.output


def test_subcommand_imports_only_its_own_module() -> None:
    # hysteresis predict streams long files: no plotting, no GP libraries
    code = (
        "import sys\n"
        "from diffaccel.cli.main import main\n"
        "try:\n"
        "    main(['hysteresis', 'predict', '--help'])\n"
        "except SystemExit:\n"
        "    pass\n"
        "heavy = sorted({'matplotlib', 'gpytorch', 'botorch'} & set(sys.modules))\n"
        "cmds = sorted(m for m in sys.modules if m.startswith('diffaccel.cli.'))\n"
        "print('RESULT', heavy, cmds)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    )
    # (cli.output: the shared --out checks; it imports click and data only)
    expect = (
        "RESULT [] ['diffaccel.cli.hysteresis', 'diffaccel.cli.hysteresis_predict', "
        "'diffaccel.cli.main', 'diffaccel.cli.output']"
    )
    assert expect in out.stdout, out.stdout


def test_unknown_command_is_a_usage_error() -> None:
    result = CliRunner().invoke(main, ["reconstrut"])
    assert result.exit_code == 2
    assert "No such command 'reconstrut'" in result.output


@pytest.mark.parametrize("enabled", [True, False])
def test_command_import_restores_the_garbage_collector(enabled: bool) -> None:
    import gc

    cli_main = sys.modules["diffaccel.cli.main"]  # the module (the package's
    # attribute of that name is the click group)
    was = gc.isenabled()
    try:
        gc.enable() if enabled else gc.disable()
        cmd = cli_main._import(*COMMANDS["synthetic"][:2])
        assert isinstance(cmd, click.Command)
        assert gc.isenabled() is enabled
        with pytest.raises(ModuleNotFoundError):
            cli_main._import("diffaccel.cli.no_such_module", "x")
        assert gc.isenabled() is enabled
    finally:
        gc.enable() if was else gc.disable()


def test_program_keeps_output_and_exit_status_when_it_ends_at_once() -> None:
    import os

    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}

    def program(*args: str) -> subprocess.CompletedProcess:
        # stdout a pipe (block-buffered)
        return subprocess.run(
            [sys.executable, "-m", "diffaccel", *args],
            capture_output=True,
            text=True,
            env=env,
        )

    ok = program("--version")
    assert ok.returncode == 0
    assert "diffaccel" in ok.stdout
    bad = program("no-such-command")
    assert bad.returncode == 2
    assert "no-such-command" in bad.stderr


@pytest.mark.parametrize("verbose", [[], ["-vv"]], ids=["quiet", "vv"])
def test_vv_shows_the_traceback_of_a_nested_subcommand(
    tmp_path, monkeypatch: pytest.MonkeyPatch, verbose: list[str]
) -> None:
    # the nested lazy group (hysteresis) caught the error first, and -v is not
    # among its own parameters: -vv never raised
    import importlib

    predict = importlib.import_module("diffaccel.cli.hysteresis_predict")

    def boom(fit_dir):
        raise RuntimeError("boom")

    monkeypatch.setattr(predict, "_load", boom)
    (tmp_path / "fit").mkdir()
    data = tmp_path / "in.csv"
    data.write_text("current_A\n1.0\n")
    out = tmp_path / "p.csv"
    args = ["hysteresis", "predict", str(tmp_path / "fit"), "--input", str(data)]
    result = CliRunner().invoke(main, [*verbose, *args, "--out", str(out)])
    if verbose:
        assert isinstance(result.exception, RuntimeError), result.output
        assert str(result.exception) == "boom"
    else:
        assert result.exit_code == 1
        assert "unexpected RuntimeError: boom (this is a bug" in result.output
