"""Atomic writer for ``fusedmosaic run … --out OUT`` (design.md, "Output contract")."""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from collections.abc import Iterable
from pathlib import Path, PurePath
from typing import Any

import cv2
import numpy as np

from fusedmosaic.io.homographies import write_homographies_csv, write_poses_csv

# Everything `fusedmosaic run` (and `evaluate`, `demo`) may leave in OUT. A run replaces the whole
# set: members it does not write again are removed on commit, so OUT never mixes two runs
# (e.g. an earlier method's plane.json next to a method that estimates no plane). Folders end
# with "/"; anything else in OUT belongs to the user and is kept.
RUN_OUTPUTS = (
    "homographies.csv", "poses.csv", "plane.json", "mosaic.png", "report.json", "report.md",
    "plots/", "evaluation.json", "evaluation.md", "evaluation_plots/", "mosaic_seams.png",
)


def _describe(exc: OSError) -> str:
    return exc.strerror or type(exc).__name__


def check_output_dir(out_dir: str | Path, what: str = "output folder", *,
                     create_parent: bool = True) -> Path:
    """Checks, before any work, that ``out_dir`` can be created or written: it is a folder or
    does not exist, no part of its path is a file, and a file can be created in it and in its
    parent (where OutputWriter stages the outputs). The parent is created if missing; with
    create_parent=False nothing is created and the nearest existing ancestor is probed instead.

    Raises ValueError naming the path and the problem. Returns ``out_dir`` as a Path."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out}: exists and is not a folder (the {what} must be a folder)")
    existing = next((p for p in out.parents if p.exists()), Path("."))
    if not existing.is_dir():  # a file where a folder should be
        raise ValueError(f"{out}: cannot create the {what}: {existing} is a file")
    if create_parent:
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ValueError(f"{out}: cannot create the {what}'s parent folder {out.parent}: "
                             f"{_describe(exc)}") from None
        existing = out.parent
    for directory in (existing, out) if out.is_dir() else (existing,):
        try:
            fd, probe = tempfile.mkstemp(prefix=".fusedmosaic-probe-", dir=directory)
        except OSError as exc:
            why = " (outputs are staged there, beside it)" if directory == out.parent else ""
            raise ValueError(f"{out}: cannot write in {directory}{why}: "
                             f"{_describe(exc)}") from None
        os.close(fd)
        os.unlink(probe)
    return out


class OutputWriter:
    """Collect output files in a temporary folder next to ``out_dir`` and move them into
    ``out_dir`` (created if needed) only when the ``with`` block exits normally; on an exception
    the temporary folder is removed and ``out_dir`` is left untouched.

    Each file is moved with os.replace, so a reader of ``out_dir`` never sees a partial file;
    existing files of the same name are replaced. Before anything is moved, every destination is
    checked (a folder where a file goes, or the reverse, fails the whole commit).

    replaces: names (relative to OUT; folders end with "/") of an earlier output set that this
        one supersedes: those not written again are removed on commit. Other files in
        ``out_dir`` are kept. The default replaces nothing.

    ``__enter__`` checks up front that ``out_dir`` can be written (check_output_dir), so a bad
    OUT fails before the computation, with a ValueError.
    """

    def __init__(self, out_dir: str | Path, *, replaces: Iterable[str] = ()) -> None:
        self.out_dir = Path(out_dir)
        self.replaces = list(replaces)
        self._tmp: Path | None = None
        self._external: list[tuple[Path, Path]] = []  # (temp, target) outside OUT

    def __enter__(self) -> OutputWriter:
        check_output_dir(self.out_dir)
        for name in self.replaces:  # a user's folder named like one of our files (or reverse)
            self._check_kind(self.out_dir / name.rstrip("/"), name.endswith("/"))
        self._tmp = Path(
            tempfile.mkdtemp(prefix=f".{self.out_dir.name}.tmp-", dir=self.out_dir.parent)
        )
        return self

    @staticmethod
    def _check_kind(target: Path, is_dir: bool) -> None:
        if is_dir and target.exists() and not target.is_dir():
            raise ValueError(f"{target}: is a file; the output needs a folder of that name "
                             "(remove or rename it)")
        if not is_dir and target.is_dir():
            raise ValueError(f"{target}: is a folder; the output needs a file of that name "
                             "(remove or rename it)")

    def __exit__(self, exc_type, exc, tb) -> None:
        tmp, self._tmp = self._tmp, None
        external, self._external = self._external, []
        try:
            if exc_type is None:
                self._commit(tmp, external)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
            for temp, _ in external:
                temp.unlink(missing_ok=True)

    def _commit(self, tmp: Path, external: list[tuple[Path, Path]]) -> None:
        whole = {name.rstrip("/") for name in self.replaces if name.endswith("/")}
        moves: list[tuple[Path, Path]] = []  # planned first: fail before moving anything
        written: set[str] = set()

        def plan(src: Path, relative: PurePath) -> None:
            target = self.out_dir / relative
            written.add(str(relative))
            if src.is_dir() and str(relative) not in whole and target.is_dir():
                for child in sorted(src.iterdir()):  # merge: keep the user's other files
                    plan(child, relative / child.name)
                return
            self._check_kind(target, src.is_dir())
            moves.append((src, target))

        for entry in sorted(tmp.iterdir()):
            plan(entry, PurePath(entry.name))
        for _, target in external:
            self._check_kind(target, False)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        for src, target in moves:
            if src.is_dir() and target.is_dir():  # a folder the run owns: replaced whole
                shutil.rmtree(target)
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(src, target)
        for temp, target in external:
            if temp.exists():
                os.replace(temp, target)
        for name in self.replaces:  # the earlier run's outputs that this run did not write
            relative = PurePath(name.rstrip("/"))
            if not _inside(relative) or str(relative) in written:
                continue
            target = self.out_dir / relative
            if name.endswith("/") and target.is_dir() and not target.is_symlink():
                shutil.rmtree(target)
            elif not name.endswith("/") and (target.is_file() or target.is_symlink()):
                target.unlink()
                for folder in target.parents:  # e.g. OUT/videos/, emptied by this removal
                    if folder == self.out_dir or not folder.is_relative_to(self.out_dir) \
                            or any(folder.iterdir()):
                        break
                    folder.rmdir()

    def path(self, name: str) -> Path:
        """Temporary path for ``name`` (relative to OUT); write the file there yourself."""
        if self._tmp is None:
            raise RuntimeError("OutputWriter: use it as a context manager (with OutputWriter(…))")
        relative = PurePath(name)
        if not _inside(relative):
            raise ValueError(f"OutputWriter: {name!r} must be a relative path inside OUT")
        path = self._tmp / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        return path

    def written(self) -> list[str]:
        """What has been written so far, relative to OUT: files, and "name/" for a folder the
        writer replaces whole (e.g. "plots/")."""
        if self._tmp is None:
            raise RuntimeError("OutputWriter: use it as a context manager (with OutputWriter(…))")
        whole = {name for name in self.replaces if name.endswith("/")}
        names = []
        for path in sorted(self._tmp.rglob("*")):
            relative = path.relative_to(self._tmp).as_posix()
            top = relative.split("/")[0] + "/"
            if top in whole:
                if relative + "/" == top:
                    names.append(top)
            elif path.is_file():
                names.append(relative)
        return names

    def external_path(self, target: str | Path) -> Path:
        """Temporary path for a file outside OUT (e.g. a video elsewhere): written beside
        ``target`` and renamed to it on commit with the rest; removed on failure."""
        if self._tmp is None:
            raise RuntimeError("OutputWriter: use it as a context manager (with OutputWriter(…))")
        target = Path(target)
        temp = target.with_name(f".{target.stem}.tmp-{os.getpid()}{target.suffix}")
        self._external.append((temp, target))
        return temp

    def write_homographies(self, frame_ids, H, name: str = "homographies.csv") -> Path:
        path = self.path(name)
        write_homographies_csv(path, frame_ids, H)
        return path

    def write_poses(self, frame_ids, poses, name: str = "poses.csv") -> Path:
        path = self.path(name)
        write_poses_csv(path, frame_ids, poses)
        return path

    def write_json(self, name: str, obj: Any) -> Path:
        """Write JSON; numpy arrays/scalars and paths are converted, NaN and inf become null."""
        path = self.path(name)
        path.write_text(json.dumps(to_jsonable(obj), indent=2, allow_nan=False) + "\n")
        return path

    def write_image(self, name: str, image: np.ndarray) -> Path:
        path = self.path(name)
        if not cv2.imwrite(str(path), image):
            raise ValueError(f"{name}: cv2.imwrite failed")
        return path

    def write_text(self, name: str, text: str) -> Path:
        path = self.path(name)
        path.write_text(text)
        return path


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


def _inside(relative: PurePath) -> bool:
    return bool(relative.parts) and not relative.is_absolute() and ".." not in relative.parts
