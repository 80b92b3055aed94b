"""The console script: help lists every subcommand; user errors are one line, exit 2."""

import subprocess
import sys

from neus_l0.cli import COMMANDS, main


def test_help_lists_every_subcommand(capsys):
    try:
        main(["--help"])
    except SystemExit as exc:
        assert exc.code == 0
    out = capsys.readouterr().out
    for name, _ in COMMANDS:
        assert name in out


def test_console_script_runs():
    proc = subprocess.run([sys.executable, "-m", "neus_l0.cli", "--version"],
                          capture_output=True, text=True)
    assert proc.returncode == 0
    assert "neus-l0" in proc.stdout
