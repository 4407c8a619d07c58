from pathlib import Path

import pytest

from sefm_recon.config import USER_KEYS, Config, load_config
from sefm_recon.errors import InputError

ROOT = Path(__file__).resolve().parents[1]


def test_overrides_are_typed():
    cfg = load_config(None, ["rough.jump_threshold=5", "output.mesh=false", "dense.band_max=32"], internal=True)
    assert cfg.rough.jump_threshold == 5.0 and cfg.output.mesh is False and cfg.dense.band_max == 32


def test_at_most_25_user_settings_and_internal_constants_are_refused():
    assert len(USER_KEYS) <= 25 and len(set(USER_KEYS)) == len(USER_KEYS)
    for key in USER_KEYS:  # every user key names a real field
        section, name = key.split(".")
        assert hasattr(getattr(Config(), section), name), key
    with pytest.raises(InputError, match="unknown config key rough.jump_threshold"):
        load_config(None, ["rough.jump_threshold=5"])
    with pytest.raises(InputError, match="unknown config key dense.band_max .*keys: method"):
        load_config(None, ["dense.band_max=32"])


def test_the_paper_method_sets_the_papers_constants_and_explicit_keys_win():
    paper = load_config(ROOT / "configs" / "paper.toml")
    assert paper.dense.method == "paper" and paper.lines.neighbours == 0 and paper.dense.subpixel is False
    assert paper.pyramid.min_size == 0 and paper.validity.sv_max_unmatched == 0
    again = load_config(None, ["dense.method=paper", "lines.neighbours=1"], internal=True)
    assert again.lines.neighbours == 1 and again.dense.both_directions is False
    assert Config().dense.method == "sgm" and Config().lines.neighbours != 0


@pytest.mark.parametrize("bad", ["foo.bar=1", "output.nope=1", "output.max_size=abc", "novalue", "output.mesh=2"])
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
    bad.write_text("[geometry]\nransac_max_error = 'x'\n")
    with pytest.raises(InputError, match="expected float"):
        load_config(bad)
    with pytest.raises(InputError, match="not found"):
        load_config(tmp_path / "missing.toml")


def test_default_preset_is_the_code_default():
    assert load_config(ROOT / "configs" / "default.toml").to_dict() == Config().to_dict()
