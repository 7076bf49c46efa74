"""`omnipipe --help` answers without loading the heavy stages (no timing here: see
benchmarks/bench_cli.py); the help lines cli.py shows match what each module registers."""

from __future__ import annotations

import argparse
import importlib
import json
import subprocess
import sys

import pytest

from omnipipe.cli import COMMAND_MODULES, COMMANDS, build_parser, main

HEAVY = ("cv2", "numba", "llvmlite", "scipy", "numpy", "omnipipe.sim.scene")


def _modules_after(code: str) -> set[str]:
    out = subprocess.run(
        [sys.executable, "-c", code + "\nimport json, sys; print(json.dumps(sorted(sys.modules)))"],
        capture_output=True,
        text=True,
        check=True,
    )
    return set(json.loads(out.stdout.strip().splitlines()[-1]))


def test_import_cli_and_help_load_no_heavy_module() -> None:
    loaded = _modules_after(
        "import contextlib, io\n"
        "from omnipipe.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    try:\n"
        "        main(['--help'])\n"
        "    except SystemExit:\n"
        "        pass\n"
    )
    assert "omnipipe.cli" in loaded
    assert not [m for m in HEAVY if m in loaded]


def test_reconstruct_help_loads_no_opencv_or_numba() -> None:
    loaded = _modules_after(
        "import contextlib, io\n"
        "from omnipipe.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    try:\n"
        "        main(['reconstruct', '--help'])\n"
        "    except SystemExit:\n"
        "        pass\n"
    )
    assert "omnipipe.pipeline.cli" in loaded
    assert not [m for m in ("cv2", "numba", "scipy", "numpy") if m in loaded]


def test_static_help_lines_match_the_registered_ones() -> None:
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    registered = {a.dest: a.help for a in sub._choices_actions}
    assert registered == {name: help_line for name, _, help_line in COMMANDS}


def test_lazy_parser_parses_like_the_full_one() -> None:
    argv = ["reconstruct", "ds", "--out", "o", "--survey", "s.yaml", "--topic", "/cam"]
    lazy = build_parser(argv).parse_args(argv)
    full = build_parser().parse_args(argv)
    assert vars(lazy) == vars(full)
    assert (lazy.dataset, lazy.survey, lazy.topic) == ("ds", "s.yaml", "/cam")


def test_unknown_command_is_refused(capsys) -> None:
    try:
        main(["no-such-command"])
    except SystemExit as exc:
        assert exc.code == 2
    else:  # pragma: no cover - argparse always exits here
        raise AssertionError("argparse accepted an unknown command")
    assert "invalid choice" in capsys.readouterr().err


def test_reconstruct_help_names_every_output(capsys) -> None:
    """Issue 31 item 10: ``reconstruct --help`` lists the deliverable's files."""
    from omnipipe.cli import main

    with pytest.raises(SystemExit):
        main(["reconstruct", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for name in ("points.laz", "points.e57", "model.obj", "defects.csv", "model.glb", "report.html"):
        assert name in text, name
    assert "Warnings go to stderr" in text
