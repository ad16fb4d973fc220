"""Every option of every `aumesh` command has help text that states its default."""

from __future__ import annotations

import argparse
import re

import pytest

from aumesh import cli

COMMANDS = {
    "compose-params",
    "synth",
    "prepare",
    "evaluate",
    "release",
    "render",
    "predict",
    "sweep",
    "runs",
    "promote",
}


def _commands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    return next(a.choices for a in parser._actions if isinstance(a, argparse._SubParsersAction))


def test_every_option_has_help_with_its_default():
    parser = cli.build_parser()
    commands = _commands(parser)
    assert COMMANDS <= set(commands)
    missing = []
    for name, sub in [("aumesh", parser), *commands.items()]:
        formatter = sub._get_formatter()
        for action in sub._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            label = f"aumesh {name} {'/'.join(action.option_strings) or action.dest}"
            text = formatter._get_help_string(action)
            if not text:
                missing.append(f"{label}: no help")
            elif action.nargs != 0 and not action.required and "default" not in text:
                missing.append(f"{label}: help does not state the default")  # flags are off unless given
    assert not missing, "\n".join(missing)


@pytest.mark.parametrize(
    "argv, expected",
    [
        (
            ["synth", "--help"],
            [r"--frames FRAMES\s+number of frames .* \(default: 4000\)", r"\(default: 0\)", r"\(default:\s+columns\)"],
        ),
        (["predict", "--help"], [r"\(default:\s+release/au_to_mesh_pls\.npz\)", r"--ignore .*\(default:\s+none\)"]),
        (["evaluate", "--help"], [r"\(default:\s+params\.yaml\)"]),
    ],
)
def test_help_as_the_user_sees_it(argv, expected, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code == 0
    out = " ".join(capsys.readouterr().out.split())
    for pattern in expected:
        assert re.search(pattern, out), (pattern, out)


def test_the_command_exits_with_mains_status_and_frozen_objects(monkeypatch):
    """``aumesh`` (console script) and ``python -m aumesh`` go through ``cli.run``: the status of ``main``, with the
    garbage collector's objects frozen so the interpreter's exit does not walk them (0.6-0.8 s a stage)."""
    import gc
    import runpy
    import tomllib
    from pathlib import Path

    pyproject = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    assert pyproject["project"]["scripts"]["aumesh"] == "aumesh.cli:run"
    calls = []
    monkeypatch.setattr(cli, "main", lambda: calls.append("main") or 3)
    monkeypatch.setattr(gc, "freeze", lambda: calls.append("freeze"))
    with pytest.raises(SystemExit) as exit_:
        cli.run()
    assert exit_.value.code == 3 and calls == ["main", "freeze"]

    ran = []
    monkeypatch.setattr(cli, "run", lambda: ran.append(True))
    runpy.run_module("aumesh", run_name="__main__")
    assert ran == [True]
