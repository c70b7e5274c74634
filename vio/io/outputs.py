"""Checks on the files a command is about to write, made before the work that produces them (a replay may take an
hour; a typo found after it would lose the run's other outputs, and an output written into the recording it reads
would lose the recording)."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path

from vio import VioError
from vio.io.atomic import temporary_path

# files of a recording's folder besides its sensor data (mav0/): what the simulator knew (vio.sim.generate)
RECORDING_ROOT_FILES = ("simulation.yaml", "calibration_truth.yaml")


class NotWritable(VioError):
    """An output's folder exists but cannot be written (check_outputs): `vio run` flies without that output."""


def in_recording(path: str | Path, recording: str | Path) -> bool:
    """Would writing `path` touch the EuRoC recording in folder `recording`: its sensor data and ground truth (all of
    mav0/, files there now or not: a new file among the images is read as a frame) or the simulator's files beside
    them? Other files in the recording's folder (a trajectory written next to it on an earlier run) are fair game."""
    rec = Path(os.path.realpath(recording))
    if not rec.is_dir():
        return False
    from vio.io.euroc import find_mav0

    try:  # the dataset given as the folder holding mav0/ or as mav0/ itself, which readers take too (a review's)
        mav0 = Path(os.path.realpath(find_mav0(rec)))
    except VioError:  # not a EuRoC folder (a bag's): nothing of it is a mav0/
        mav0 = rec / "mav0"
    p = Path(os.path.realpath(path))
    return p == mav0 or mav0 in p.parents or p in {mav0.parent / n for n in RECORDING_ROOT_FILES}


def recording_of(path: str | Path) -> str | None:
    """The recording folder `path` is, or lies in (a ground-truth csv inside its mav0/); None for other files."""
    p = Path(os.path.realpath(path))
    if p.is_dir():
        return str(p)
    return next((str(a.parent) for a in p.parents if a.name == "mav0"), None)


def file_key(path: str | Path) -> tuple:
    """What names one file whatever path reaches it: (device, inode) where it exists (a hard link has another real
    path but is the same file: written through, it is the file read), else its real path (not written yet)."""
    try:
        st = os.stat(path)
    except OSError:
        return ("path", os.path.realpath(path))
    return ("inode", st.st_dev, st.st_ino)


def same_file(a: str | Path, b: str | Path) -> bool:
    """Do `a` and `b` name one file (by a link, a hard link or another spelling; or are both one path not there)?"""
    return file_key(a) == file_key(b)


def distinct_files(paths: dict[str, str | None]) -> dict[tuple, str]:
    """{file_key: what} of the outputs named (empty ones left out); VioError when two are one file."""
    seen: dict[tuple, str] = {}
    for what, p in paths.items():
        if p:
            key = file_key(p)
            if key in seen:
                raise VioError(f"{p}: {seen[key]} and {what} would be written to the same file")
            seen[key] = what
    return seen


def check_not_reads(outputs: dict[str, str | None], reads: dict[str, str | None] | None,
                    grows: dict[str, str] | None = None) -> None:
    """No two outputs one file, and no output a file the run reads (`reads`), except an output over the one read
    it grows (`grows`: {output: read})."""
    seen = distinct_files(outputs)
    for what, p in (reads or {}).items():
        writer = seen.get(file_key(p)) if p else None
        if writer is not None and (grows or {}).get(writer) != what:
            raise VioError(f"{p}: {writer} would be written over {what}")


def check_outputs(paths: dict[str, str | None], reads: dict[str, str | None] | None = None,
                  grows: dict[str, str] | None = None, recordings: tuple[str | None, ...] = (),
                  folders: dict[str, str | None] | None = None, renamed: tuple[str, ...] = ()) -> None:
    """Every output file can be written where it is asked for (its folder exists, it is no folder itself). No two
    outputs may be one file, nor an output a file the run reads (`reads`), except an output over the one read it
    grows (`grows`: {output: read}, a map saved over the map it loaded; only that one: `--save-map` over the
    `--calibration` file wrote the map over the calibration), nor any output (files in `paths`, output folders in
    `folders`) lie in the sensor data of a recording folder the run reads (`recordings`). An output in `renamed`
    (written beside its path and renamed over it: the map) must not be a device, pipe or socket there now."""
    check_not_reads(paths, reads, grows)
    for rec in recordings:
        for what, p in {**paths, **(folders or {})}.items():
            if rec and p and in_recording(p, rec):
                raise VioError(f"{p}: {what} would be written into the recording {rec} (its sensor data, "
                               "ground truth and simulator files are never written over): write it elsewhere")
    for what, p in paths.items():
        if not p:
            continue
        path = Path(p)
        if path.is_dir():
            raise VioError(f"{p}: is a folder; {what} needs a file name")
        # a link is written through (a map: save_map writes beside the file it names and renames over that file):
        # the folder that matters is the named file's, which the link's own folder said nothing of
        real = Path(os.path.realpath(path)) if path.is_symlink() else path
        via = f" (a link to {real})" if real is not path else ""
        if what in renamed and real.exists() and not real.is_file():
            # `--save-map /dev/full` (as root) renamed a regular file over the device node: /dev/full was gone
            raise VioError(f"{p}: is not a regular file (a device, pipe or socket); {what} is written beside it and "
                           "renamed over it: give a file path")
        n_tmp = len(os.fsencode(temporary_path(real).name)) if what in renamed else 0
        if n_tmp > 255:  # the save failed, "File name too long", after the whole replay or flight (a review's)
            raise VioError(f"{p}: the name is too long: {what} is written beside it under a name of {n_tmp} bytes "
                           "(over the 255 a file system allows) and renamed over it: give a shorter name")
        folder = real.parent if str(real.parent) else Path(".")
        if not folder.is_dir():
            raise VioError(f"{p}: cannot write {what}{via}: folder {folder} does not exist")
        if not os.access(folder, os.W_OK):
            raise NotWritable(f"{p}: cannot write {what}{via}: folder {folder} is not writable")
        # tried, not only asked: os.access says yes to root in /proc and in a read-only folder, and the stats or the
        # map of a whole replay then failed at its end (the map lost)
        # (a device or pipe there is written into, not made: /dev is not tried)
        problem = None if real.exists() and not real.is_file() else folder_problem(folder, made=False)
        if problem:
            raise NotWritable(f"{p}: cannot write {what}{via}: {problem}")


def folder_problem(folder: str | Path, made: bool) -> str | None:
    """Why files cannot be written in `folder`, or None. `made`: the writer makes the folder and its parents (the
    nearest one that exists is tried), else the folder itself must exist.

    Tried, not asked: a file is made and removed there. os.access says yes to root in a read-only (mode 555)
    folder and in /proc, and the writer then failed once the sensors were up (`vio record`: an OAK takes
    seconds to start), with "what was written before stays readable" where nothing was."""
    folder = Path(folder)
    try:
        existing = next((p for p in (folder, *folder.parents) if p.exists()), Path(".")) if made else folder
        if not existing.exists():
            return f"folder {existing} does not exist"
        if not existing.is_dir():
            return f"{existing} is a file, not a folder"
    except OSError as e:  # a name over the file system's limits (made=False: the folder's own exists() raised)
        return f"{folder}: {e.strerror or e}"
    try:
        fd, probe = tempfile.mkstemp(prefix=".vio-write-test-", dir=existing)
    except OSError as e:
        return f"folder {existing} cannot be written ({e.strerror or e})"
    os.close(fd)
    os.unlink(probe)
    return None


def check_new_file(path: str | Path, overwrite: bool, *recordings: str | Path | None) -> None:
    """Refuse, before any work, a single output file that would destroy a file or cannot be written (VioError,
    one line): an existing one unless `overwrite`, and one in a recording the command reads (`recordings`: a
    folder, or a file inside its mav0/) even with it.

    `calib imu-noise -o` wrote its seven IMU lines over a whole calibration, and a read-only folder ended in an
    "internal error" after the work was done (a review's findings); a project calibration over a EuRoC
    sensor.yaml leaves a recording nothing reads."""
    path = Path(path)
    check_outputs({}, recordings=tuple(recording_of(r) for r in recordings if r is not None),
                  folders={"the output": str(path)})
    if path.is_dir():
        raise VioError(f"{path}: is a folder; give the file to write")
    if path.exists() and not overwrite:
        raise VioError(f"{path} exists: not replaced (--overwrite replaces it)")
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise VioError(f"{path}: folder {folder} does not exist")
    if not os.access(folder, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise VioError(f"{path}: cannot write there (read-only or no permission)")
    # os.access says yes to root in /proc and in a read-only folder; a device or pipe is written into, not made
    problem = None if path.exists() and not path.is_file() else folder_problem(folder, made=False)
    if problem:
        raise VioError(f"{path}: cannot write there ({problem})")


DISK_FULL_BYTES = 4 << 20  # below this much free space, a failed image write is taken for a full disk


def storage_diagnosis(root: Path | None, said: str = "") -> str:
    """What an image write error (cv2.imwrite only says it failed) most likely was: ' (disk full: ...)', ' (the
    recording folder was removed)', or '' (shared by `vio run`'s recorder and `vio record`); '' too when the error
    `said` it already (the writer saw its folder gone)."""
    from vio.io.euroc import REMOVED_TEXT

    if root is None or REMOVED_TEXT in said:
        return ""
    if not root.exists():
        return f" ({REMOVED_TEXT})"
    with contextlib.suppress(OSError):
        free = shutil.disk_usage(root).free
        if free < DISK_FULL_BYTES:  # a file system keeps a few blocks back, and one image did not fit
            return f" (disk full: {free // 1024} KiB left, No space left on device)"
    return ""
