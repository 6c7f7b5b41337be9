"""The committed sample logs are exactly what their README commands make."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

from click.testing import CliRunner

from relpoint_cli.main import cli

SAMPLES = Path(__file__).resolve().parents[1] / "sample_logs"


def test_sample_logs_are_reproducible(tmp_path: Path) -> None:
    commands = re.findall(r"`(relpoint simulate [^`]+)`", (SAMPLES / "README.md").read_text())
    assert commands
    for command in commands:
        args = shlex.split(command)[1:]
        name = Path(args[args.index("-o") + 1]).name
        args[args.index("-o") + 1] = str(tmp_path / name)
        result = CliRunner().invoke(cli, ["-q", *args])
        assert result.exit_code == 0, result.stderr
        assert (tmp_path / name).read_bytes() == (SAMPLES / name).read_bytes(), f"{name} differs from its command"
