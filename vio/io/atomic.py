"""Files replaced whole: written beside the target under a temporary name and renamed over it, so that a reader (or
the next start, after a kill) finds the old file or the new one, never half of one. The one place that names the
temporary files, so that a start can find the ones a killed writer left (remove_stale_temporaries)."""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import re
import shutil
import stat
import time
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

log = logging.getLogger(__name__)

# A temporary modified this recently is left alone even when no process here has its writer's pid: a writer in
# another container or PID namespace sharing the folder (a replay in a toolbox container saving the map the daemon
# loads) has a pid this process cannot see, and removing its temporary mid-write makes its rename fail and its map
# lost. A write refreshes the file's mtime as it goes (a large map on a slow SD card: seconds); a temporary
# untouched for this long has no writer.
STALE_AFTER_S = 120.0


def temporary_path(path: Path, pid: int | None = None) -> Path:
    """Where `path` is written before it is renamed over: beside it (a rename does not cross file systems), hidden,
    named after it and the writing process (two processes writing one file do not write into one temporary)."""
    return path.with_name(f".{path.name}.{os.getpid() if pid is None else pid}.tmp")


def fsync_folder(folder: Path) -> None:
    """Make a rename (or a new file) in `folder` survive a power cut: the new name is in the folder's own blocks,
    which an fsync of the file does not write. Where a folder cannot be opened or synced (not POSIX, some network
    and FUSE file systems: EINVAL, EBADF) nothing more can be done; said in the debug log."""
    flags = os.O_RDONLY | getattr(os, "O_DIRECTORY", 0)
    try:
        fd = os.open(folder, flags)
    except OSError as e:
        log.debug("cannot open %s to sync it (%s): a power cut may lose the last rename in it", folder, e)
        return
    try:
        os.fsync(fd)
    except OSError as e:
        if e.errno not in (errno.EINVAL, errno.EBADF, errno.ENOTSUP, errno.EROFS):
            raise
        log.debug("cannot sync the folder %s (%s): a power cut may lose the last rename in it", folder, e)
    finally:
        os.close(fd)


def replace_atomically(path: Path, write: Callable[[BinaryIO], None], durable: bool) -> None:
    """Write `path` whole: `write(f)` into temporary_path(path), then renamed over `path` (the temporary removed on
    any failure, the old file kept; its permissions kept by the new one). `durable`: the data are synced before the
    rename and the folder after it, so that a power cut (a drone's battery pulled) leaves the old file or the whole
    new one, and not the old one once the new one was said to be written (a rename is in the page cache until the
    folder is synced). Not durable: a file rewritten every second (the status file) or that a restart can do without
    (the reset counter), where a sync on a busy SD card would hold the writer for up to seconds. OSError as raised,
    the old file kept; once renamed, a folder that cannot be synced is only said (logged)."""
    tmp = temporary_path(path)
    try:
        mode = stat.S_IMODE(os.stat(path).st_mode)
    except OSError:  # none there yet (or not to be seen): the process's default
        mode = None
    try:
        # the file renamed over keeps its permissions: a map kept private (0600) came back readable to all (0644),
        # and one shared with a group for writing (0664) no longer writable by it (a review's finding). Created
        # private, so that nothing is readable to more than the target's mode allows while it is written.
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666 if mode is None else 0o600)
        with os.fdopen(fd, "wb") as f:
            if mode is not None:
                try:
                    os.fchmod(f.fileno(), mode)
                except OSError as e:  # a file system without modes (FAT on an SD card): nothing to keep
                    log.debug("%s: cannot give it the mode of %s (%s)", tmp, path, e.strerror or e)
            write(f)
            if durable:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    if durable:
        try:
            fsync_folder(path.parent)
        except OSError as e:
            # the new file is in place (a reader, and the caller, get it): an error here raised as if the write had
            # failed, and save_map said "the map that was there is kept" of a map already replaced
            log.warning("%s: written, but its folder could not be synced (%s): a power cut soon may bring back the "
                        "file it replaced", path, e.strerror or e)


def write_text_whole(path: str | Path, text: str, durable: bool = True) -> None:
    """A small file a person keeps (a calibration, an IMU noise file) written whole (replace_atomically, through a
    link to the file it names): written in place, a write that failed half way (a full SD card, a kill) left half
    of the new file where the old one was. A device or pipe (`-o /dev/stdout`) is written into, as before."""
    real = Path(os.path.realpath(path))
    if real.exists() and not real.is_file():
        Path(path).write_text(text)
        return
    replace_atomically(real, lambda f: f.write(text.encode()), durable)


def set_aside(path: Path) -> Path:
    """Move the recording at `path` (a folder or a file) to PATH.replaced, where `settle_aside` finds it: an
    `--overwrite` that deleted it at once lost it when the new recording then got no data. One left there by a killed
    run is removed first (that run's recording, at `path`, had replaced it)."""
    aside = path.with_name(path.name + ".replaced")
    if aside.is_dir():
        shutil.rmtree(aside)
    os.replace(path, aside)
    return aside


def settle_aside(aside: Path, path: Path, has_data: bool) -> bool:
    """After the recording at `path` closed: the one `set_aside` kept is removed when it has data, else put back in
    its place (True: put back; the caller says so)."""
    def remove(p: Path) -> None:
        shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()

    if has_data:
        remove(aside)
        return False
    remove(path)
    os.replace(aside, path)
    return True


def _alive(pid: int) -> bool:
    """Is a process `pid` running (another user's too)? A pid reused since counts as running: its file is kept, and
    so is one named with pid 0 (os.kill(0) would ask about this process group; no writer has that pid)."""
    if pid <= 0:
        return True
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):  # OverflowError: a number no pid can be
        return False
    except OSError:  # EPERM: someone else's process
        return True
    return True


def remove_stale_temporaries(path: Path) -> list[Path]:
    """Remove the temporary files of `path` (temporary_path's names) whose writer no longer runs, and return them.

    A writer killed mid-write (a stop's budget that ran out while a map checkpoint was written, the OOM killer, a
    power cut) leaves its temporary beside the file: a map's is as large as the map, one more at every such restart,
    on a companion computer's small disk. Only this name pattern is touched, and not a file of a process that runs
    (a replay saving the same map now, this process), nor one written within STALE_AFTER_S (a writer this process
    cannot see; a clock set back since makes a file look young: kept, it goes at a later start)."""
    pattern = re.compile(rf"\.{re.escape(path.name)}\.(\d+)\.tmp")
    removed = []
    try:
        names = os.listdir(path.parent)
    except OSError:
        return []
    for name in names:
        m = pattern.fullmatch(name)
        if m is None or _alive(int(m.group(1))):
            continue
        p = path.parent / name
        try:
            if not p.is_file() or p.is_symlink() or time.time() - p.lstat().st_mtime < STALE_AFTER_S:
                continue
            p.unlink()
        except OSError as e:
            log.warning("%s: a temporary file left by a writer that was stopped mid-write; cannot remove it (%s)",
                        p, e.strerror or e)
            continue
        removed.append(p)
    return removed
