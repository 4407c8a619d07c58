import cv2
import numpy as np

from sefm_recon import __version__, versions
from sefm_recon.bench import format_report


def test_library_versions_are_the_imported_modules():
    v = versions.library_versions()
    assert list(v) == ["sefm-recon", "python", *versions.DISTRIBUTIONS]
    assert v["sefm-recon"] == __version__
    assert v["numpy"] == np.__version__
    assert v["opencv"].startswith(cv2.__version__)  # (the wheel's version adds its build number)
    assert all(isinstance(x, str) for x in v.values())


def test_a_library_not_installed_is_none_and_named_missing(monkeypatch):
    monkeypatch.setitem(versions.DISTRIBUTIONS, "nothing", ("no-such-distribution-sefm",))
    v = versions.library_versions()
    assert v["nothing"] is None
    assert versions.format_versions(v).endswith("nothing missing")


def test_the_bench_report_names_the_libraries():
    m = {"wall_s": 1.0, "matches": 10, "precision@1": 1.0, "precision@3": 1.0, "coverage@1": 0.5,
         "coverage@3": 0.5, "peak_mb": 100.0}
    r = {"size": [64, 48], "seed": 1, "repeat": 1, "libraries": {"numpy": "9.9"},
         "sefm": {**m, "stages_s": {"matching": 0.5}, "matching_s": 0.5}, "sgbm": m,
         "ratio_matching_to_sgbm": 0.5, "ratio_wall_to_sgbm": 1.0}
    assert format_report(r).splitlines()[1] == "numpy 9.9"
