"""Repository invariants: CI runs the README's test command exactly."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _readme_commands() -> list[str]:
    return re.findall(r"```bash\n(.+?)\n```", (ROOT / "README.md").read_text())


def test_ci_runs_the_readme_test_command():
    commands = _readme_commands()
    assert len(commands) >= 2
    test_cmd = next(c for c in commands if "pytest" in c)
    ci_lines = [ln for ln in (ROOT / ".ci" / "run").read_text().splitlines() if ln and not ln.startswith("#")]
    assert test_cmd in ci_lines


def test_readme_installs_torch_first():
    for cmd in _readme_commands()[:2]:
        assert cmd.index("pip install torch==2.13.0") < cmd.index("pip install -e")
