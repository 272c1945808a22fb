"""Packaged sysid data (sysid.data, importlib.resources): the defaults are read from the package, and a
missing file is an error that names it, never a silent fallback."""

from __future__ import annotations

import pytest

from sim_core.errors import ConfigError
from sysid.bagio.reader import load_bag_config
from sysid.data import DEFAULT_CONFIG, FEATS_INDENTATION, data_file
from sysid.noise import noise_config


def test_the_packaged_files_are_found_and_read():
    for name in (DEFAULT_CONFIG, FEATS_INDENTATION):
        path = data_file(name)
        assert path.is_file() and path.parent.name == "data" and path.parent.parent.name == "sysid"
    assert load_bag_config().namespace == "/thinshell"
    assert noise_config() == {"difference_order": 2}


def test_a_missing_data_file_names_it_and_lists_the_packaged_ones():
    with pytest.raises(ConfigError, match=r"'nope.yaml' is not in the package sysid.data .*'default.yaml'"):
        data_file("nope.yaml")


def test_an_explicit_config_that_does_not_exist_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="sysid config file does not exist"):
        noise_config(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="cannot read sysid config"):
        load_bag_config(tmp_path / "missing.yaml")
