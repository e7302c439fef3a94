"""physgrad.load_network on a missing or unfinished run: one line naming the file (issue 53
item 5), not Equinox's traceback."""

from __future__ import annotations

import json

import pytest

import physgrad


def test_a_missing_run_directory_is_one_line(tmp_path):
    with pytest.raises(physgrad.ConfigError, match=r"nowhere is no run directory \(it does not exist\)"):
        physgrad.load_network(tmp_path / "nowhere")


def test_a_run_without_params_is_one_line_naming_the_file(tmp_path):
    (tmp_path / "run").mkdir()
    with pytest.raises(physgrad.ConfigError, match=r"run/params\.eqx is missing: the run has not finished"):
        physgrad.load_network(tmp_path / "run")


def test_a_run_without_its_config_says_to_pass_like(tmp_path):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "params.eqx").write_bytes(b"")
    with pytest.raises(physgrad.ConfigError, match=r"run/config\.json is missing; pass like="):
        physgrad.load_network(tmp_path / "run")
    (tmp_path / "run" / "config.json").write_text(json.dumps([1]))
    with pytest.raises(physgrad.ConfigError, match=r"config\.json is damaged \(not a JSON object\)"):
        physgrad.load_network(tmp_path / "run")
