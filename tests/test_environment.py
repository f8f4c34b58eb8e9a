"""The user's environment variables (torch_brdf.data): a value the package cannot read is refused
with the variable's name and the allowed values, never silently taken as something else."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from torch_brdf.cli import app
from torch_brdf.data import progress_default
from torch_brdf.errors import ValueRangeError


@pytest.mark.parametrize(("value", "on"), [("1", True), ("on", True), ("Yes", True), ("0", False), ("off", False)])
def test_progress_switch_values(monkeypatch, value, on):
    monkeypatch.setenv("TORCH_BRDF_PROGRESS", value)
    assert progress_default() is on
    assert progress_default(not on) is (not on)  # the API argument wins over the variable


def test_invalid_progress_switch_is_refused(monkeypatch):
    monkeypatch.setenv("TORCH_BRDF_PROGRESS", "maybe")
    with pytest.raises(ValueRangeError, match=r"TORCH_BRDF_PROGRESS='maybe'.*1, true.*0, false"):
        progress_default()
    res = CliRunner().invoke(app, ["info", "cornell_box"])  # before any scene is built
    assert res.exit_code == 2
    assert "error: $TORCH_BRDF_PROGRESS='maybe' is not a switch" in res.output
    assert "objects" not in res.output
