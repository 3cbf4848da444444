"""Atomic writer for ``fusedmosaic run … --out OUT`` (design.md, "Output contract").

Which files in a folder are fusedmosaic's is recorded, never guessed: every writer with a
``record`` lists what it wrote in the folder's hidden manifest (MANIFEST), and a later writer
removes only files that such a record names. Anything else in the folder belongs to the user."""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import re
import shutil
import signal
import tempfile
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path, PurePath
from typing import Any

import cv2
import numpy as np

from fusedmosaic._entry import OutputsWrittenInterrupt  # (raised by OutputWriter)
from fusedmosaic.io.homographies import write_homographies_csv, write_poses_csv

# {"written_by": "fusedmosaic", "format": 1, "sets": {KEY: {"files": [...], "stale_after_run":
# bool}}}: KEY is "run", "demo" or "evaluation:NAME.json"; files are relative to the folder.
MANIFEST = ".fusedmosaic-outputs.json"
# Staging folders: OUT/.fusedmosaic.tmp-PID-* (OUT exists) or PARENT/.OUT.fusedmosaic.tmp-PID-*.
TEMP_TAG = ".fusedmosaic.tmp-"


def _describe(exc: OSError) -> str:
    return exc.strerror or type(exc).__name__


def check_output_dir(
    out_dir: str | Path, what: str = "output folder", *, create_parent: bool = True
) -> Path:
    """Checks, before any work, that ``out_dir`` can be created or written: it is a folder or
    does not exist, and no part of its path is a file. An existing folder must be writable
    (OutputWriter stages inside it); a missing one is created later, so its parent must be
    writable (staged there). The parent is created if missing (and removed again if the check
    then fails); it stays when the caller's work fails later, so a command that may fail checks
    with create_parent=False, which creates nothing and probes the nearest existing ancestor,
    and lets the writer create the folders (OutputWriter, created_folders_removed_on_failure).

    Raises ValueError naming the path and the problem. Returns ``out_dir`` as a Path."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out}: exists and is not a folder (the {what} must be a folder)")
    created: list[Path] = []  # parents made here: removed again if the probe fails
    if out.is_dir():
        directory, why = out, ""
    else:
        existing = next((p for p in out.parents if p.exists()), Path("."))
        if not existing.is_dir():  # a file where a folder should be
            raise ValueError(f"{out}: cannot create the {what}: {existing} is a file")
        if create_parent:
            created = missing_folders(out.parent)
            try:
                out.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                remove_created_folders(created)
                raise ValueError(
                    f"{out}: cannot create the {what}'s parent folder {out.parent}: "
                    f"{_describe(exc)}"
                ) from None
            existing = out.parent
        directory, why = existing, f" (the {what} is created there)"
    try:
        fd, probe = tempfile.mkstemp(prefix=".fusedmosaic-probe-", dir=directory)
    except OSError as exc:
        # creating a file in an existing folder gives ENOENT only on file systems that do not
        # take new files (/proc, /sys): strerror's "No such file or directory" would mislead
        reason = ("the file system there takes no new files" if exc.errno == errno.ENOENT
                  and directory.is_dir() else _describe(exc))
        remove_created_folders(created)
        raise ValueError(f"{out}: cannot write in {directory}{why}: {reason}") from None
    os.close(fd)
    os.unlink(probe)
    return out


def missing_folders(path: str | Path) -> list[Path]:
    """``path`` and its ancestors that do not exist yet, deepest first: the folders that
    creating ``path`` creates (for remove_created_folders when the command then fails)."""
    path = Path(path)
    return [p for p in (path, *path.parents) if not (p.exists() or p.is_symlink())]


def remove_created_folders(folders: Iterable[Path]) -> None:
    """Removes the folders of missing_folders() that are empty, deepest first: what a failed
    command created on the way to its output. A folder holding anything (someone else's file)
    is kept, and so are its parents; a folder that existed before is never in the list."""
    for folder in sorted(folders, key=lambda p: len(p.absolute().parts), reverse=True):
        try:
            folder.rmdir()
        except OSError:  # not empty, or already gone
            pass


@contextlib.contextmanager
def created_folders_removed_on_failure(path: str | Path) -> Iterator[None]:
    """The folders on the way to ``path`` (itself included) that do not exist on entering are
    removed again, when empty, if the block raises (Ctrl-C included): a command that fails
    leaves no empty folder it made, as its outputs are all or nothing."""
    created = missing_folders(path)
    try:
        yield
    except BaseException:
        remove_created_folders(created)
        raise


def read_json_object(path: str | Path) -> dict:
    """A JSON file whose top level is an object; ValueError naming the file otherwise."""
    try:
        obj = json.loads(Path(path).read_text())
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text (UTF-8) JSON file") from None
    except json.JSONDecodeError as exc:
        raise ValueError(
            f"{path}: not valid JSON ({exc.msg} at line {exc.lineno}, column {exc.colno})"
        ) from None
    if not isinstance(obj, dict):
        raise ValueError(
            f"{path}: expected a JSON object {{...}} at the top level, got {type(obj).__name__}"
        )
    return obj


def read_plane_json(path: str | Path) -> np.ndarray:
    """pi (3,) from plane.json / truth_plane.json ({"plane": [x, y, z], ...})."""
    obj = read_json_object(path)
    if "plane" not in obj:
        raise ValueError(f'{path}: no "plane" entry')
    try:
        plane = np.asarray(obj["plane"], np.float64)
    except (TypeError, ValueError):
        plane = None
    if plane is None or plane.shape != (3,) or not np.isfinite(plane).all() or not plane.any():
        raise ValueError(
            f'{path}: "plane" must be 3 finite numbers, not all zero; got {obj["plane"]!r:.80}'
        )
    return plane


def read_manifest(folder: str | Path) -> dict[str, dict] | None:
    """The output sets recorded in ``folder``'s MANIFEST: {key: {"files": [...],
    "stale_after_run": bool}}; None when there is no readable fusedmosaic manifest (then
    nothing in the folder is known to be ours)."""
    try:
        obj = read_json_object(Path(folder) / MANIFEST)
    except (OSError, ValueError):
        return None
    if obj.get("written_by") != "fusedmosaic" or not isinstance(obj.get("sets"), dict):
        return None
    sets = {}
    for key, entry in obj["sets"].items():
        if isinstance(entry, dict) and isinstance(entry.get("files"), list):
            files = [
                f for f in entry["files"] if isinstance(f, str) and _is_relative_inside(PurePath(f))
            ]
            sets[key] = {"files": files, "stale_after_run": entry.get("stale_after_run") is True}
    return sets


def is_under(path: str | Path, folder: str | Path, *, or_equal: bool = False) -> bool:
    """Whether ``path`` lies inside ``folder`` (both resolved; or is it, with or_equal)."""
    path, folder = Path(path).resolve(), Path(folder).resolve()
    return (or_equal and path == folder) or folder in path.parents


class OutputWriter:
    """Collect output files in a hidden temporary folder and move them into ``out_dir`` only
    when the ``with`` block exits normally; on an exception (Ctrl-C included) the temporary
    folder is removed and ``out_dir`` is left untouched.

    The temporary folder is inside ``out_dir`` when it exists (same file system, and only the
    folder itself needs to be writable), else beside it, where ``out_dir`` is created. Each file
    is moved with os.replace, so a reader never sees a partial file; files of the same name are
    replaced. Before anything is moved, every destination is checked (a folder where a file
    goes, or the reverse, fails the whole commit). Temporary folders of a killed process are
    removed by the next writer in the same place.

    record: key under which the written files are listed in ``out_dir``'s MANIFEST. The files
        an earlier writer recorded under the same key and that are not written again are
        removed (e.g. report.md after a run with --no-report). None: no record, and nothing
        but the written files is touched.
    stale_after_run: the set describes the run in ``out_dir`` (an evaluation of it): a later
        run there removes it.
    new_run: this writer is a run: it also removes every recorded set marked stale_after_run.
    expects: names (relative to OUT, folders end with "/") the writer will surely write,
        checked up front for a folder/file of the other kind.
    replaces: names of an earlier output set that the caller recognised as fusedmosaic's
        without a manifest record (older versions): used only when ``record`` has no entry in
        the manifest; those not written again are removed (a name ending in "/" as a folder).

    foreign: "replace" (default): an existing file of a written name is replaced, whoever wrote
        it (the caller checked); "refuse": one that the manifest does not record (any set) and
        that is not in ``replaces`` nor ``older`` is a user's file: ValueError naming it, for
        the ``expects`` names in ``__enter__`` (before the computation) and for every file in
        the commit (before anything is moved).
    older: names the caller recognised as an older version's outputs, besides ``replaces``
        (used likewise only when ``record`` has no entry): replaced when written again, not
        removed otherwise.

    ``__enter__`` checks up front that ``out_dir`` can be written (check_output_dir), so a bad
    OUT fails before the computation, with a ValueError.
    """

    def __init__(
        self,
        out_dir: str | Path,
        *,
        record: str | None = None,
        stale_after_run: bool = False,
        new_run: bool = False,
        expects: Iterable[str] = (),
        replaces: Iterable[str] = (),
        foreign: str = "replace",
        older: Iterable[str] = (),
    ) -> None:
        if foreign not in ("replace", "refuse"):
            raise ValueError(
                f"OutputWriter: foreign must be 'replace' or 'refuse', got {foreign!r}")
        self.out_dir = Path(out_dir)
        self.foreign = foreign
        self.older = list(older)
        self.record = record
        self.stale_after_run = stale_after_run
        self.new_run = new_run
        self.expects = list(expects)
        self.replaces = list(replaces)
        self._tmp: Path | None = None
        self._external: list[tuple[Path, Path]] = []  # (temp, target) outside OUT
        self._external_dirs: list[Path] = []  # folders created for them, deepest first
        self._created: list[Path] = []  # OUT and its parents, when missing: removed on failure

    def __enter__(self) -> OutputWriter:
        self._created = missing_folders(self.out_dir)
        try:
            check_output_dir(self.out_dir)  # (creates OUT's parent)
            self.check_expected()
            if self.out_dir.is_dir():
                where, prefix = self.out_dir, TEMP_TAG
            else:
                where, prefix = self.out_dir.parent, f".{self.out_dir.name}{TEMP_TAG}"
            _remove_stale_temps(where, prefix)
            self._tmp = Path(tempfile.mkdtemp(prefix=f"{prefix}{os.getpid()}-", dir=where))
        except BaseException:
            remove_created_folders(self._created)
            raise
        return self

    @staticmethod
    def _check_kind(target: Path, is_dir: bool) -> None:
        if is_dir and target.exists() and not target.is_dir():
            raise ValueError(
                f"{target}: is a file; the output needs a folder of that name (remove or rename it)"
            )
        if not is_dir and target.is_dir():
            raise ValueError(
                f"{target}: is a folder; the output needs a file of that name (remove or rename it)"
            )

    def check_expected(self) -> None:
        """The ``expects`` names against what OUT holds (a user's folder named like one of our
        files or the reverse; with foreign="refuse", a user's file): ValueError naming it.
        Creates nothing and needs no ``with``: ``__enter__`` runs it, and a caller that writes
        long after it knows OUT (a live session, before it connects) can run it first."""
        for name in self.expects:
            self._check_kind(self.out_dir / name.rstrip("/"), name.endswith("/"))
            if not name.endswith("/"):
                self._check_ours(PurePath(name))

    def check_ours(self, *names: str) -> None:
        """With foreign="refuse": ValueError when a file OUT/name exists that nobody recorded
        as fusedmosaic's (see the class); for names the writer may write, checked before the
        computation (the ``expects`` names are checked on entering)."""
        for name in names:
            self._check_ours(PurePath(name))

    def _check_ours(self, relative: PurePath) -> None:
        target = self.out_dir / relative
        if self.foreign != "refuse" or not (target.is_file() or target.is_symlink()):
            return
        sets = read_manifest(self.out_dir) or {}
        ours = {f for s in sets.values() for f in s["files"]}
        older = [] if self.record in sets else [*self.replaces, *self.older]
        ours.update(n for n in older if not n.endswith("/"))
        folders = [PurePath(n.rstrip("/")) for n in older if n.endswith("/")]
        if relative.as_posix() not in ours and not any(relative.is_relative_to(f)
                                                       for f in folders):
            raise ValueError(
                f"{target}: exists and fusedmosaic did not write it (not listed in "
                f"{self.out_dir / MANIFEST}); it is not replaced: choose another output folder, "
                "or move the file away")

    def __exit__(self, exc_type, exc, tb) -> None:
        tmp, self._tmp = self._tmp, None
        external, self._external = self._external, []
        folders, self._external_dirs = self._external_dirs, []
        created, self._created = self._created, []
        committed = False
        try:
            with signals_deferred():  # an interrupt here would leave a half-moved set
                try:
                    if exc_type is None:
                        self._commit(tmp, external)
                        committed = True
                finally:
                    shutil.rmtree(tmp, ignore_errors=True)
                    for temp, _ in external:
                        temp.unlink(missing_ok=True)
                    # created for a file outside OUT that did not land, and (on failure) OUT's
                    # parents that __enter__ created: only if empty, someone else's file keeps
                    # them
                    remove_created_folders([*folders, *([] if committed else created)])
        except KeyboardInterrupt:  # held during the commit, delivered after it
            if committed:
                raise OutputsWrittenInterrupt(self.out_dir) from None
            raise

    def _commit(self, tmp: Path, external: list[tuple[Path, Path]]) -> None:
        moves: list[tuple[Path, Path]] = []  # planned first: fail before moving anything

        def plan(src: Path, relative: PurePath) -> None:
            target = self.out_dir / relative
            if src.is_dir() and target.is_dir():
                for child in sorted(src.iterdir()):  # merge: keep the user's other files
                    plan(child, relative / child.name)
                return
            self._check_kind(target, src.is_dir())
            if not src.is_dir():
                self._check_ours(relative)
            moves.append((src, target))

        for entry in sorted(tmp.iterdir()):
            plan(entry, PurePath(entry.name))
        for _, target in external:
            self._check_kind(target, False)
        written = self._written(tmp)
        stale_files, stale_folders, manifest = self._superseded(written)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        for folder in stale_folders:  # an older version's recorded folder, e.g. "plots/"
            shutil.rmtree(self.out_dir / folder)
        for name in stale_files:
            target = self.out_dir / name
            if target.is_file() or target.is_symlink():
                target.unlink()
                self._remove_empty_parents(target)
        for src, target in moves:
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(src, target)
        for temp, target in external:
            if temp.exists():
                os.replace(temp, target)
        if manifest is not None:
            self._write_manifest(tmp, manifest)

    def _superseded(self, written: list[str]) -> tuple[list[str], list[str], dict | None]:
        """(files to remove, folders to remove whole, the new manifest sets or None)."""
        if self.record is None:
            return [], [], None
        sets = read_manifest(self.out_dir) or {}
        replaced = {self.record} | {
            k for k, s in sets.items() if self.new_run and s["stale_after_run"]
        }
        kept = {k: s for k, s in sets.items() if k not in replaced}
        keep = set(written).union(*(s["files"] for s in kept.values()))
        stale = {f for k in replaced & sets.keys() for f in sets[k]["files"]}
        folders = []
        if self.record not in sets:  # no record yet: the caller's recognised older set
            for name in self.replaces:
                relative = PurePath(name.rstrip("/"))
                if not _is_relative_inside(relative) or str(relative) in keep:
                    continue
                target = self.out_dir / relative
                if name.endswith("/"):
                    if target.is_dir() and not target.is_symlink():
                        folders.append(str(relative))
                else:
                    stale.add(str(relative))
        for s in kept.values():  # a file now written by this set is no longer theirs
            s["files"] = [f for f in s["files"] if f not in written]
        kept[self.record] = {"files": written, "stale_after_run": self.stale_after_run}
        return sorted(stale - keep), folders, kept

    def _write_manifest(self, tmp: Path, sets: dict) -> None:
        sets = {k: s for k, s in sets.items() if s["files"]}
        target = self.out_dir / MANIFEST
        if not sets:
            target.unlink(missing_ok=True)
            return
        temp = tmp / MANIFEST
        obj = {"written_by": "fusedmosaic", "format": 1, "sets": sets}
        temp.write_text(json.dumps(obj, indent=2) + "\n")
        os.replace(temp, target)

    def _remove_empty_parents(self, target: Path) -> None:
        for folder in target.parents:  # e.g. OUT/videos/, emptied by this removal
            if folder == self.out_dir or not folder.is_relative_to(self.out_dir):
                break
            if any(folder.iterdir()):
                break
            folder.rmdir()

    def path(self, name: str) -> Path:
        """Temporary path for ``name`` (relative to OUT); write the file there yourself."""
        if self._tmp is None:
            raise RuntimeError("OutputWriter: use it as a context manager (with OutputWriter(…))")
        relative = PurePath(name)
        if not _is_relative_inside(relative) or relative.parts[0] == MANIFEST:
            raise ValueError(f"OutputWriter: {name!r} must be a relative path inside OUT")
        path = self._tmp / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        return path

    def written(self) -> list[str]:
        """The files written so far, relative to OUT (POSIX separators), sorted."""
        if self._tmp is None:
            raise RuntimeError("OutputWriter: use it as a context manager (with OutputWriter(…))")
        return self._written(self._tmp)

    @staticmethod
    def _written(tmp: Path) -> list[str]:
        return sorted(
            p.relative_to(tmp).as_posix() for p in tmp.rglob("*") if p.is_file() or p.is_symlink()
        )

    def external_path(self, target: str | Path) -> Path:
        """Temporary path for a file outside OUT (e.g. a video elsewhere): written beside
        ``target`` and renamed to it on commit with the rest; removed on failure."""
        if self._tmp is None:
            raise RuntimeError("OutputWriter: use it as a context manager (with OutputWriter(…))")
        target = Path(target)
        temp = temp_beside(target)
        missing = missing_folders(target.parent)
        target.parent.mkdir(parents=True, exist_ok=True)
        self._external_dirs += missing
        self._external.append((temp, target))
        return temp

    # Every write_* (and a caller writing at path() itself, through named_errors) fails with an
    # OSError naming OUT/name when the file system refuses the write: Python's write errors
    # carry no file name (a full disk on homographies.csv said only "error: File too large"),
    # and the staged copy's name means nothing to the user. OSError, not ValueError: the
    # command's input was right and the same command succeeds once there is room or permission;
    # the CLI exits 1 for it, as for a --video that does not read back (README), and 2 for an
    # input or a command line to change (review 47: mosaic.png's refusal was a ValueError, exit
    # 2, the other files' exit 1).

    @contextlib.contextmanager
    def named_errors(self, name: str, what: str = "") -> Iterator[Path]:
        """The staged path of ``name`` (relative to OUT), for a caller that writes it itself: an
        OSError of a write inside the block removes what it left there and is raised again
        naming OUT/name, or OUT/<the staged file it names> (a report's plot). An OSError naming
        a file outside the staging folder (a frame being read) passes as it is. what: the
        file's kind for the message ("the image", "the report")."""
        path = self.path(name)
        tmp = self._tmp
        try:
            yield path
        except OSError as exc:
            staged = None if exc.filename is None else _relative_or_none(exc.filename, tmp)
            if exc.filename is not None and staged is None:
                raise
            with contextlib.suppress(OSError):  # (a partial file does not wait for the commit)
                path.unlink(missing_ok=True)
            raise OSError(exc.errno, f"{what + ' ' if what else ''}could not be written "
                                     f"({exc.strerror or exc}: a full disk, or no write "
                                     f"permission in {self.out_dir}?)",
                          str(self.out_dir / (staged or name))) from None

    def write_homographies(self, frame_ids, H, name: str = "homographies.csv") -> Path:
        with self.named_errors(name) as path:
            write_homographies_csv(path, frame_ids, H)
        return path

    def write_poses(self, frame_ids, poses, name: str = "poses.csv") -> Path:
        with self.named_errors(name) as path:
            write_poses_csv(path, frame_ids, poses)
        return path

    def write_json(self, name: str, obj: Any) -> Path:
        """Write JSON; numpy arrays/scalars and paths are converted, NaN and inf become null."""
        text = json.dumps(to_jsonable(obj), indent=2, allow_nan=False) + "\n"
        with self.named_errors(name) as path:
            path.write_text(text)
        return path

    def write_image(self, name: str, image: np.ndarray) -> Path:
        """Writes `image` in the format its name's extension says (OpenCV's encoders); an image
        OpenCV cannot encode is a ValueError naming OUT/name."""
        with self.named_errors(name, "the image") as path:
            try:
                write_image_file(path, image)
            except ImageEncodingError as exc:
                raise ValueError(f"{self.out_dir / name}: the image could not be encoded"
                                 f"{exc.reason}") from None
        return path

    def write_text(self, name: str, text: str) -> Path:
        with self.named_errors(name) as path:
            path.write_text(text)
        return path


class ImageEncodingError(ValueError):
    """OpenCV could not encode an image; `reason` is its text (" (…)") or empty."""

    def __init__(self, path: Path, reason: str = "") -> None:
        super().__init__(f"{path}: the image could not be encoded{reason}")
        self.reason = reason


def write_image_file(path: str | Path, image: np.ndarray, params: Iterable[int] = ()) -> None:
    """`image` encoded by OpenCV in the format of `path`'s extension, in memory, and written by
    Python, whose close() reports a failed last write: cv2.imwrite does not check it, and a
    mosaic.png cut 300 bytes short (a file size limit, as on a full disk) was committed with
    exit 0 (review 46). Nothing is left at `path` when it fails. Raises ImageEncodingError if the
    image cannot be encoded, OSError (errno, strerror and `path` as its filename) if it cannot
    be written. The one encoder of OUT's images, the live recorder's frames and the live preview."""
    path = Path(path)
    try:
        ok, data = cv2.imencode(path.suffix, image, list(params))
    except cv2.error as exc:  # (OpenCV's text without its source file and function)
        raise ImageEncodingError(path, " ({})".format(re.sub(
            r" in function .*$", "", re.sub(r"^.*error: \([^)]*\) ", "", str(exc).strip())))
        ) from None
    if not ok:
        raise ImageEncodingError(path)
    try:
        path.write_bytes(data.tobytes())
    except OSError as exc:
        with contextlib.suppress(OSError):  # (not left cut short)
            path.unlink(missing_ok=True)
        raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from None


def to_jsonable(obj: Any) -> Any:
    """Plain-Python copy of ``obj`` for json.dumps: numpy -> lists/scalars, non-finite -> None."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, PurePath):
        return str(obj)
    return obj


def _relative_or_none(path: str | Path, folder: Path) -> str | None:
    """``path`` relative to ``folder`` (POSIX separators), None when it is not inside it."""
    try:
        return Path(path).relative_to(folder).as_posix()
    except ValueError:
        return None


def _is_relative_inside(relative: PurePath) -> bool:
    """A relative path that stays inside the folder it is relative to."""
    return bool(relative.parts) and not relative.is_absolute() and ".." not in relative.parts


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # e.g. another user's process: alive
        return True
    return True


def temp_beside(target: str | Path) -> Path:
    """The hidden temporary file a file is written to before being renamed to `target`:
    ``.<stem>.tmp-<pid><suffix>`` beside it (the suffix kept: a video writer picks its container
    by it)."""
    target = Path(target)
    return target.with_name(f".{target.stem}.tmp-{os.getpid()}{target.suffix}")


def _remove_stale_temps(folder: Path, prefix: str) -> None:
    """Staging folders ``prefix``PID-* in ``folder`` whose process is gone (killed before its
    clean-up could run): ours by name, and nobody will commit them."""
    try:
        entries = list(folder.iterdir())
    except OSError:
        return
    for entry in entries:
        pid = entry.name[len(prefix) :].split("-", 1)[0] if entry.name.startswith(prefix) else ""
        if pid.isdigit() and entry.is_dir() and not entry.is_symlink() and not _pid_alive(int(pid)):
            shutil.rmtree(entry, ignore_errors=True)


# The signals that end a command as Ctrl-C does (_entry.signals_as_interrupt: SIGTERM from
# `timeout` or a scheduler, SIGHUP from a closed terminal): signals_deferred holds all three.
DEFERRED_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP")
                         if hasattr(signal, name))


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP during the block are delivered after it, each once, to the
    handler the block replaced, so a commit, a recording's finish or a session's last step is
    never cut in half: SIGTERM alone unlinked an earlier run's files, moved 2 of the new ones in
    and left the manifest unwritten (review 47). A signal ignored (SIG_IGN: nohup, a background
    job's SIGINT) or handled outside Python stays as it was. Delivered to SIG_DFL: SIGINT
    raises KeyboardInterrupt (as Python's own handler), SIGTERM / SIGHUP are raised again and
    end the process as they would have, the block done. Only the main thread can set handlers;
    elsewhere a no-op."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []
    previous = {}
    for sig in DEFERRED_SIGNALS:
        handler = signal.getsignal(sig)
        if handler is not signal.SIG_IGN and handler is not None:
            previous[sig] = signal.signal(sig, lambda signum, frame: received.append(signum))
    try:
        yield
    finally:  # (delivered even when the block raised: a commit failing on a full disk lost a
        # held SIGTERM, the process living on; review Z 47. An interrupt raised here carries
        # that exception as its context.)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        for sig in dict.fromkeys(received):  # (in the order heard; a second adds nothing)
            handler = previous[sig]
            if callable(handler):
                handler(sig, None)
            elif sig == signal.SIGINT:
                raise KeyboardInterrupt
            else:
                signal.raise_signal(sig)
