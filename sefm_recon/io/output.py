"""Output folders that never hold half a result.

Everything is written into a hidden staging folder beside OUT and moved into
OUT only when the whole run succeeded; a failure or Ctrl-C removes the staging
folder and leaves OUT as it was.
"""

from __future__ import annotations

import logging
import os
import secrets
import shutil
from pathlib import Path

from ..errors import InputError

logger = logging.getLogger(__name__)


def check_output_dir(out: str | Path, overwrite: bool) -> Path:
    """Refuse an existing, non-empty OUT unless ``overwrite`` (nothing is touched)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"output path exists and is not a folder: {out}")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise InputError(f"output folder is not empty: {out} (use --overwrite to replace its results)")
    return out


class StagedOutput:
    """Context manager: ``with StagedOutput(out, overwrite) as stage: write into stage``."""

    def __init__(self, out: str | Path, overwrite: bool = False):
        self.out = check_output_dir(out, overwrite)
        self.stage: Path | None = None

    def __enter__(self) -> Path:
        parent = self.out.resolve().parent
        parent.mkdir(parents=True, exist_ok=True)
        self.stage = parent / f".{self.out.name}.partial-{secrets.token_hex(4)}"
        self.stage.mkdir()
        return self.stage

    def __exit__(self, exc_type, exc, tb) -> bool:
        assert self.stage is not None
        try:
            if exc_type is None:
                self._commit()
        finally:
            shutil.rmtree(self.stage, ignore_errors=True)
        return False

    def _commit(self) -> None:
        self.out.mkdir(parents=True, exist_ok=True)
        for item in sorted(self.stage.iterdir()):
            target = self.out / item.name
            if target.is_dir() and not target.is_symlink():
                # Swap folders: move the old aside first so a reader never sees a mix.
                old = self.out / f".{item.name}.old-{secrets.token_hex(4)}"
                os.replace(target, old)
                os.replace(item, target)
                shutil.rmtree(old, ignore_errors=True)
            else:
                os.replace(item, target)
        logger.debug("moved results into %s", self.out)
