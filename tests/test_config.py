from pathlib import Path

import pytest

from sefm_recon.config import Config, load_config
from sefm_recon.errors import InputError

ROOT = Path(__file__).resolve().parents[1]


def test_overrides_are_typed():
    cfg = load_config(None, ["rough.jump_threshold=5", "output.mesh=false", "dense.band_max=32"])
    assert cfg.rough.jump_threshold == 5.0 and cfg.output.mesh is False and cfg.dense.band_max == 32


@pytest.mark.parametrize("bad", ["foo.bar=1", "rough.nope=1", "rough.jump_threshold=abc", "novalue", "output.mesh=2"])
def test_bad_overrides_are_input_errors(bad):
    with pytest.raises(InputError):
        load_config(None, [bad])


def test_presets_load_and_differ_from_defaults():
    presets = sorted((ROOT / "configs").glob("*.toml"))
    assert presets, "configs/ holds the presets"
    for p in presets:
        load_config(p)
    assert load_config(ROOT / "configs" / "fast.toml").to_dict() != Config().to_dict()


def test_config_file_errors(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[rough]\njump_threshold = 'x'\n")
    with pytest.raises(InputError, match="expected float"):
        load_config(bad)
    with pytest.raises(InputError, match="not found"):
        load_config(tmp_path / "missing.toml")


def test_default_preset_is_the_code_default():
    assert load_config(ROOT / "configs" / "default.toml").to_dict() == Config().to_dict()
