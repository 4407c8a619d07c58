"""Write configs/default.toml and docs/configuration.md from the code (tests check they agree).

    .venv/bin/python scripts/write_default_config.py
"""

from pathlib import Path

from sefm_recon.config_doc import configuration_markdown, default_toml

ROOT = Path(__file__).resolve().parents[1]


def main(root: Path = ROOT) -> None:
    (root / "configs" / "default.toml").write_text(default_toml())
    (root / "docs" / "configuration.md").write_text(configuration_markdown())


if __name__ == "__main__":
    main()
