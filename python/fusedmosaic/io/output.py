"""Atomic writer for ``fusedmosaic run … --out OUT`` (design.md, "Output contract")."""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from pathlib import Path, PurePath
from typing import Any

import cv2
import numpy as np

from fusedmosaic.io.homographies import write_homographies_csv, write_poses_csv


class OutputWriter:
    """Collect output files in a temporary folder next to ``out_dir`` and move them into
    ``out_dir`` (created if needed) only when the ``with`` block exits normally; on an exception
    the temporary folder is removed and ``out_dir`` is left untouched.

    Each file is moved with os.replace, so a reader of ``out_dir`` never sees a partial file;
    existing files of the same name are replaced, other files in ``out_dir`` are kept.
    """

    def __init__(self, out_dir: str | Path) -> None:
        self.out_dir = Path(out_dir)
        self._tmp: Path | None = None

    def __enter__(self) -> OutputWriter:
        self.out_dir.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = Path(
            tempfile.mkdtemp(prefix=f".{self.out_dir.name}.tmp-", dir=self.out_dir.parent)
        )
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        tmp, self._tmp = self._tmp, None
        try:
            if exc_type is None:
                self.out_dir.mkdir(parents=True, exist_ok=True)
                for entry in sorted(tmp.iterdir()):
                    target = self.out_dir / entry.name
                    if entry.is_dir() and target.is_dir():
                        shutil.rmtree(target)
                    os.replace(entry, target)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def path(self, name: str) -> Path:
        """Temporary path for ``name`` (relative to OUT); write the file there yourself."""
        if self._tmp is None:
            raise RuntimeError("OutputWriter: use it as a context manager (with OutputWriter(…))")
        relative = PurePath(name)
        if relative.is_absolute() or ".." in relative.parts or not relative.parts:
            raise ValueError(f"OutputWriter: {name!r} must be a relative path inside OUT")
        path = self._tmp / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        return path

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
