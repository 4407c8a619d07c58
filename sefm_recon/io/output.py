"""Output folders that never hold half a result.

Everything is written into a hidden staging folder beside OUT,
``.OUT.partial-<host>-<pid>-<random>``, and becomes OUT in one step only when
the whole run succeeded:

* OUT missing or empty: the staging folder is renamed to OUT (one ``rename``).
* OUT holding earlier results (``--overwrite``): files in OUT that are not
  results are hard-linked into the staging folder, which is then swapped with
  OUT in one ``renameat2(RENAME_EXCHANGE)`` (Linux); the old results are
  deleted afterwards. Without that call, OUT is renamed aside and the staging
  folder renamed in its place (OUT is briefly missing, never mixed).
* Where no folder rename is possible (OUT is the current folder, or a mount
  point or on another file system than its parent: a tmpfs, a Docker volume),
  the results are moved in one by one, ``report.json`` last, after the old
  results were moved out. When OUT is on another file system the staging
  folder is made inside OUT instead (hidden, same name), so that no move ever
  crosses file systems.

Inside a result folder (``sparse/``, ``pairs/``) only the files the tool
writes are replaced: files a user put there are kept (``owned``).

So a reader sees either nothing (or the old results) or the complete new set,
also when the process is killed (SIGKILL) at any moment. A failure or Ctrl-C
removes the staging folder; one left by a killed run is removed by the next run
that writes beside it, once its process is gone.
"""

from __future__ import annotations

import ctypes
import errno
import fnmatch
import glob
import hashlib
import logging
import os
import secrets
import shutil
import socket
import sys
from pathlib import Path, PurePosixPath
from typing import Iterable, Mapping

from .. import interrupt
from ..errors import InputError
from .colmap_model import MODEL_FILES
from .space import SLACK_BYTES, NoSpaceError, free_bytes, is_disk_full, no_space_message, require_space, tree_bytes

logger = logging.getLogger(__name__)

#: What ``sefm-recon pair`` writes into OUT; with ``--overwrite`` these are
#: replaced (or removed when the new run does not write them, e.g. mesh.ply),
#: everything else in OUT is kept.
PAIR_RESULTS = ("matches.npz", "points.ply", "mesh.ply", "sparse", "matches.png", "report.json")

#: Inside the result folders of ``pair``, the files the tool writes (paths relative to the folder, ``*`` for
#: one name); with ``--overwrite`` anything else found there is the user's and is kept.
PAIR_OWNED = {"sparse": MODEL_FILES}


def _host_tag() -> str:
    return hashlib.sha1(socket.gethostname().encode()).hexdigest()[:6]


def _stage_prefix(out: Path) -> str:
    return f".{out.name}.partial-"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    return True


def _new_stage_name(out: Path) -> str:
    return f"{_stage_prefix(out)}{_host_tag()}-{os.getpid()}-{secrets.token_hex(4)}"


def clean_stale_stages(out: str | Path) -> list[Path]:
    """Remove staging folders of OUT left by killed runs on this host; returns them.

    Only folders named by this module (beside OUT, or inside it when OUT is on
    another file system), on this host, whose process is gone are touched (a
    folder of a live run, or of another host, is left alone).
    """
    out = Path(out).resolve()
    removed = []
    host = _host_tag()
    folders = [f for f in (out.parent, out) if f.is_dir()]
    for p in (q for f in folders for q in f.glob(glob.escape(_stage_prefix(out)) + "*")):
        parts = p.name[len(_stage_prefix(out)):].split("-")
        if len(parts) != 3 or parts[0] != host or not parts[1].isdigit():
            continue
        pid = int(parts[1])
        if pid == os.getpid() or _pid_alive(pid):
            continue
        shutil.rmtree(p, ignore_errors=True)
        if not p.exists():
            removed.append(p)
            logger.info("removed %s, left by an interrupted run", p.name)
    return removed


def check_output_dir(out: str | Path, overwrite: bool) -> Path:
    """Refuse an unusable OUT, or an existing non-empty one unless ``overwrite`` (nothing in OUT is touched).

    Staging folders beside OUT left by killed runs are removed first (see :func:`clean_stale_stages`).
    """
    if isinstance(out, (str, bytes)) and not out.strip():
        raise InputError("the output folder is an empty name: give one with -o OUT (e.g. -o . for this folder)")
    out = Path(os.fsdecode(out))
    try:
        clean_stale_stages(out)
    except OSError as err:  # never a reason to fail
        logger.debug("could not clean old staging folders of %s: %s", out, err)
    if out.exists() and not out.is_dir():
        raise InputError(f"output path exists and is not a folder: {out}")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise InputError(f"output folder is not empty: {out} (use --overwrite to replace its results)")
    # The staging folder is created beside OUT: its first existing ancestor must be a writable folder.
    anc = out.resolve().parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        raise InputError(f"cannot create output folder {out}: {anc} is not a folder")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise InputError(f"cannot write output folder {out}: no write permission in {anc}")
    return out


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap two paths (Linux ``renameat2``); False where unsupported."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, errno.ENOTSUP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def _link_tree(src: Path, dst: Path) -> None:
    """Hard-link ``src`` (file, symlink or folder) to ``dst``: no data is copied."""
    if src.is_symlink():
        os.symlink(os.readlink(src), dst)
    elif src.is_dir():
        shutil.copytree(src, dst, symlinks=True, copy_function=os.link)
    else:
        os.link(src, dst)


def _is_owned(rel: PurePosixPath, patterns: Iterable[str]) -> bool:
    return any(len(rel.parts) == len(pp.parts) and all(map(fnmatch.fnmatchcase, rel.parts, pp.parts))
               for pp in map(PurePosixPath, patterns))


def user_files(folder: Path, patterns: Iterable[str]) -> list[PurePosixPath]:
    """Entries of a result folder that the tool did not write: files not matching ``patterns``, empty folders."""
    found = []

    def walk(d: Path, rel: PurePosixPath) -> None:
        entries = list(d.iterdir())
        if not entries and rel.parts:
            found.append(rel)
        for p in entries:
            r = rel / p.name
            if p.is_dir() and not p.is_symlink():
                walk(p, r)
            elif not _is_owned(r, patterns):
                found.append(r)

    walk(folder, PurePosixPath())
    return found


def _keep_user_files(old: Path, new: Path, patterns: Iterable[str], move: bool = False) -> None:
    """Hard-link (or ``move``) the user's entries of result folder ``old`` into ``new``, the same path inside."""
    for rel in user_files(old, patterns):
        src, dst = old / rel, new / rel
        if dst.exists() or dst.is_symlink():
            continue  # the new results have it
        dst.parent.mkdir(parents=True, exist_ok=True)
        if src.is_dir() and not src.is_symlink():
            dst.mkdir()
        elif move:
            os.replace(src, dst)
        else:
            _link_tree(src, dst)


def _renames_into(stage: Path, out: Path) -> bool:
    """Whether a folder beside OUT (``stage``) can be renamed into OUT: not across file systems or mounts."""
    if os.path.ismount(out) or stage.stat().st_dev != out.stat().st_dev:
        return False
    probe = stage / "probe"  # a bind mount of the same file system: only a rename tells
    probe.mkdir()
    target = out / stage.name  # named like a staging folder: a killed run's is cleaned up
    try:
        os.rename(probe, target)
    except OSError as err:
        return err.errno != errno.EXDEV  # other reasons (permissions) show at the end, as before
    os.rmdir(target)
    return True


class StagedOutput:
    """Context manager: ``with StagedOutput(out, overwrite) as stage: write into stage``.

    ``results``: the names a run writes into OUT. With ``overwrite``, entries of
    OUT with these names are replaced or removed; other entries are kept. By
    default only the names the run actually wrote are replaced. ``owned``: for
    result folders, the files inside that the tool writes (see
    :data:`PAIR_OWNED`); the user's other files there are kept too.
    """

    def __init__(self, out: str | Path, overwrite: bool = False, results: Iterable[str] | None = None,
                 owned: Mapping[str, Iterable[str]] | None = None):
        self.out = check_output_dir(out, overwrite)
        self.overwrite = overwrite
        self.results = set(results) if results is not None else None
        self.owned = {k: tuple(v) for k, v in (owned or {}).items()}
        self.stage: Path | None = None
        self.inside = False  #: the staging folder is inside OUT (OUT on another file system than its parent)
        self.needed = 0  #: bytes asked for so far (:meth:`require`)

    def __enter__(self) -> Path:
        real = self.out.resolve()
        real.parent.mkdir(parents=True, exist_ok=True)
        clean_stale_stages(real)
        self.stage = real.parent / _new_stage_name(real)
        self.stage.mkdir()
        if real.is_dir() and not _renames_into(self.stage, real):
            shutil.rmtree(self.stage, ignore_errors=True)
            self.stage = real / self.stage.name
            self.stage.mkdir()
            self.inside = True
            logger.debug("%s is on another file system than its parent: staging inside it", real)
        return self.stage

    def require(self, estimate: int) -> None:
        """Refuse to go on (:class:`NoSpaceError`) unless the staging folder's device has room for ``estimate``
        more bytes; call before writing them."""
        assert self.stage is not None
        self.needed += require_space(self.stage, estimate, self.out)

    def __exit__(self, exc_type, exc, tb) -> bool:
        assert self.stage is not None
        full, written = False, 0
        try:
            if exc_type is None:
                interrupt.check()  # a Ctrl-C that a library swallowed still stops the run here
                self._commit()
            elif issubclass(exc_type, Exception) and not issubclass(exc_type, InputError):
                # a full disk, also where a library says something else (sqlite: "No registered database
                # factory succeeded") or wraps the error: no room left where the results were being written
                free = free_bytes(self.stage)
                full = is_disk_full(exc) or (free is not None and free < SLACK_BYTES)
                written = tree_bytes(self.stage) if full else 0
                if full:
                    logger.debug("writing the results failed on a full disk: %s: %s", exc_type.__name__, exc)
        finally:
            shutil.rmtree(self.stage, ignore_errors=True)
        if full:
            raise NoSpaceError(no_space_message(self.out, max(self.needed, written), free_bytes(self.stage.parent))) \
                from exc
        return False

    # ------------------------------------------------------------------ commit

    def _commit(self) -> None:
        real = self.out.resolve()
        old = [p for p in real.iterdir() if p != self.stage] if real.is_dir() else []
        if old and not self.overwrite:
            raise InputError(f"output folder is not empty: {self.out} (it was filled during the run; "
                             "use --overwrite to replace its results)")
        cwd = Path.cwd().resolve()
        if self.inside or real == cwd or real in cwd.parents or (real.exists() and os.path.ismount(real)):
            self._commit_per_item(real, old)  # never rename the shell's current folder or a mount point
            return
        if not old:
            try:
                os.rename(self.stage, real)  # atomic; replaces an empty folder
                logger.debug("results are in %s", real)
                return
            except OSError as err:
                logger.debug("renaming %s to %s failed (%s): moving files one by one", self.stage, real, err)
                self._commit_per_item(real, old)
                return
        ours = self.results if self.results is not None else {p.name for p in self.stage.iterdir()}
        new_names = {p.name for p in self.stage.iterdir()}
        try:
            for p in old:
                if p.name not in ours and p.name not in new_names:
                    _link_tree(p, self.stage / p.name)  # keep the user's other files
                elif p.name in self.owned and p.is_dir() and not p.is_symlink():
                    _keep_user_files(p, self.stage / p.name, self.owned[p.name])  # and theirs in sparse/
            try:
                shutil.copystat(real, self.stage, follow_symlinks=True)
            except OSError:
                pass
        except OSError as err:
            logger.debug("cannot hard-link the other files of %s (%s): moving files one by one", real, err)
            for p in self.stage.iterdir():  # (links made inside result folders are kept: they are wanted)
                if p.name not in new_names:
                    shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()
            self._commit_per_item(real, old)
            return
        if _exchange(self.stage, real):
            logger.debug("swapped the new results into %s", real)
            return  # the stage now holds the old results; __exit__ removes it
        aside = real.parent / _new_stage_name(real)
        os.rename(real, aside)
        try:
            os.rename(self.stage, real)
        except OSError:
            os.rename(aside, real)
            raise
        shutil.rmtree(aside, ignore_errors=True)

    def _commit_per_item(self, real: Path, old: list[Path]) -> None:
        """Move old results out, then the new ones in, ``report.json`` last."""
        real.mkdir(parents=True, exist_ok=True)
        ours = (self.results or set()) | {p.name for p in self.stage.iterdir()}
        for p in old:  # the user's files inside result folders go with the new results
            if p.name in ours and p.name in self.owned and p.is_dir() and not p.is_symlink():
                try:
                    _keep_user_files(p, self.stage / p.name, self.owned[p.name])
                except OSError:  # no hard links here: move them
                    _keep_user_files(p, self.stage / p.name, self.owned[p.name], move=True)
        new = sorted(self.stage.iterdir(), key=lambda p: (p.name == "report.json", p.name))
        trash = real / _new_stage_name(real)  # inside OUT: the same file system as what it receives
        trash.mkdir()
        try:
            for name in sorted(ours, key=lambda n: n != "report.json"):
                target = real / name  # the old report goes first
                if target.exists() or target.is_symlink():
                    os.replace(target, trash / name)
            for item in new:
                os.replace(item, real / item.name)
        finally:
            shutil.rmtree(trash, ignore_errors=True)
        logger.debug("moved results into %s", real)
