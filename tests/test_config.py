import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sefm_recon.config import USER_FIELDS, USER_KEYS, Config, Range, load_config
from sefm_recon.config_doc import configuration_markdown, default_toml
from sefm_recon.errors import InputError

ROOT = Path(__file__).resolve().parents[1]


def test_overrides_are_typed():
    cfg = load_config(None, ["rough.jump_threshold=5", "output.mesh=false", "dense.band_max=32"], internal=True)
    assert cfg.rough.jump_threshold == 5.0 and cfg.output.mesh == "none" and cfg.dense.band_max == 32


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


@pytest.mark.parametrize("name, render", [("configs/default.toml", default_toml),
                                          ("docs/configuration.md", configuration_markdown)])
def test_generated_files_match_the_code(name, render):
    """Stale after a change to a setting's default, doc or range: run scripts/write_default_config.py."""
    assert (ROOT / name).read_text() == render(), f"{name} is stale: run scripts/write_default_config.py"


def test_every_user_key_is_documented_with_a_range():
    doc = configuration_markdown()
    for key, f in USER_FIELDS.items():
        meta = f.metadata
        assert meta["doc"], key
        kind = type(getattr(getattr(Config(), key.split(".")[0]), key.split(".")[1]))
        if kind in (int, float):  # every number has a range, and a reason for where it ends
            assert isinstance(meta["range"], Range) and meta["why"], key
            assert meta["range"].low is not None and meta["range"].high is not None, key
            assert meta["range"].holds(getattr(getattr(Config(), key.split(".")[0]), key.split(".")[1])), key
        elif kind is str:
            assert meta["choices"], key
        assert f"| `{key}` |" in doc, key


def test_ranges_say_what_they_hold():
    r = Range(256, 100_000, special=(0, "full size"))
    assert r.holds(0) and r.holds(256) and r.holds(100_000) and not r.holds(1) and not r.holds(100_001)
    assert r.text() == "0 (full size) or >= 256 and <= 100000"
    half_open = Range(0, 1, low_open=True, high_open=True)
    assert not half_open.holds(0) and not half_open.holds(1) and half_open.holds(0.5)
    assert half_open.text() == "> 0 and < 1"


_ODD_NUMBERS = [0, -1, 1, -(10 ** 30), 10 ** 30, 2 ** 63, 0.5, -0.0, 1e-300, 1e300, math.nan, math.inf, -math.inf]
_values = st.one_of(st.sampled_from(_ODD_NUMBERS), st.integers(-10 ** 9, 10 ** 9),
                    st.floats(allow_nan=True, allow_infinity=True), st.booleans(),
                    st.sampled_from(["", "abc", "nan", "-inf", "1e3", "0x10", "true", "sgm", "knn", " 7 "]))


def _accepted(key: str, value) -> bool:
    """``value`` was taken for ``key``: it must be of the key's type and within its documented range."""
    section, name = key.split(".")
    meta = USER_FIELDS[key].metadata
    kind = type(getattr(getattr(Config(), section), name))
    assert type(value) is kind, (key, value)
    if meta["range"] is not None:
        assert math.isfinite(value) and meta["range"].holds(value), (key, value)
    if meta["choices"]:
        assert value in meta["choices"], (key, value)
    return True


def _one_line_error_naming(err: InputError, key: str) -> None:
    text = str(err)
    assert "\n" not in text and key in text, text


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(key=st.sampled_from(USER_KEYS), value=_values)
def test_any_value_of_any_user_key_is_refused_in_one_line_or_in_range(key, value, tmp_path):
    """Negative, zero, huge, NaN, infinite, wrong-typed: through --set (text) and a TOML file (typed)."""
    section, name = key.split(".")
    text = repr(value) if isinstance(value, float) else str(value).lower() if isinstance(value, bool) else str(value)
    for source in ("set", "toml"):
        try:
            if source == "set":
                cfg = load_config(None, [f"{key}={text}"])
            else:
                if isinstance(value, int) and not isinstance(value, bool) and abs(value) >= 2 ** 63:
                    continue  # TOML has no integers that large
                toml = {float: lambda v: {"nan": "nan", "inf": "inf", "-inf": "-inf"}.get(repr(v), repr(v)),
                        bool: lambda v: str(v).lower(), str: json.dumps}.get(type(value), str)(value)
                path = tmp_path / "c.toml"
                path.write_text(f"[{section}]\n{name} = {toml}\n")
                cfg = load_config(path)
        except InputError as err:
            _one_line_error_naming(err, key)
        else:
            assert _accepted(key, getattr(getattr(cfg, section), name))


def test_the_pose_needs_no_more_inliers_than_features():
    with pytest.raises(InputError, match="geometry.min_inliers: must be <= sift.max_features"):
        load_config(None, ["sift.max_features=20"])  # the default min_inliers is 30
    assert load_config(None, ["sift.max_features=20", "geometry.min_inliers=20"]).sift.max_features == 20


@pytest.mark.parametrize("args, key", [
    (["colmap", "no-such-workspace", "--set", "colmap.cell_size=-1"], "colmap.cell_size"),
    (["pair", "a.jpg", "b.jpg", "--max-size", "1000000"], "--max-size"),
])
def test_the_command_line_refuses_out_of_range_values_with_exit_2_and_one_line(tmp_path, args, key):
    r = subprocess.run([sys.executable, "-m", "sefm_recon", *args, "-o", str(tmp_path / "out")],
                       capture_output=True, text=True, timeout=120)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and key in lines[0] and "Traceback" not in r.stderr, r.stderr
    assert not (tmp_path / "out").exists()
