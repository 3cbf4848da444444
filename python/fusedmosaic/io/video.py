"""Frame access: ``frames/*.png`` (sorted by name) or one ``video.*`` file, read lazily."""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import cv2
import numpy as np


class FrameSource(Sequence):
    """Sequence of frames read from disk on demand; no image is kept in memory.

    Items are uint8 (H, W) or (H, W, 3) BGR as stored (an alpha channel is dropped; a video is
    always decoded to BGR). With ``expected_size=(w, h)`` every image is checked against it.
    Video sources decode sequentially and seek for random access; they are not thread-safe.
    """

    def __init__(
        self,
        paths: list[Path] | None = None,
        *,
        video: Path | None = None,
        expected_size: tuple[int, int] | None = None,
        size_source: str = "camera.yaml",
    ) -> None:
        if (paths is None) == (video is None):
            raise ValueError("FrameSource: give exactly one of paths or video")
        self.paths = None if paths is None else [Path(p) for p in paths]
        self.video = None if video is None else Path(video)
        self.expected_size = expected_size
        self.size_source = size_source
        self._capture: cv2.VideoCapture | None = None
        self._next = 0  # index the capture will decode next
        if self.paths is not None:
            self._length = len(self.paths)
        else:
            capture = self._open_capture()
            self._length = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
            if self._length <= 0:  # container without a frame count: count by decoding
                self._length = 0
                while capture.grab():
                    self._length += 1
                self.close()
        if self._length <= 0:
            raise ValueError(
                f"{self.paths[0].parent if self.paths is not None else self.video}: no frames"
            )

    @classmethod
    def open(
        cls,
        dataset_root: str | Path,
        *,
        expected_size: tuple[int, int] | None = None,
        size_source: str = "camera.yaml",
    ) -> FrameSource:
        """Find ``frames/*.png`` or a single ``video.*`` under ``dataset_root``."""
        root = Path(dataset_root)
        frames_dir = root / "frames"
        videos = sorted(p for p in root.glob("video.*") if p.is_file())
        if frames_dir.is_dir():
            paths = sorted(frames_dir.glob("*.png"))
            if not paths:
                raise ValueError(f"{frames_dir}: no frames (*.png)")
            return cls(paths, expected_size=expected_size, size_source=size_source)
        if len(videos) > 1:
            raise ValueError(
                f"{root}: several video files ({', '.join(p.name for p in videos)}), expected one"
            )
        if not videos:
            raise ValueError(f"{root}: no frames (neither frames/*.png nor a video.* file)")
        return cls(video=videos[0], expected_size=expected_size, size_source=size_source)

    def __len__(self) -> int:
        return self._length

    def __getitem__(self, index: int) -> np.ndarray:
        if not isinstance(index, (int, np.integer)):
            raise TypeError(f"FrameSource indices must be integers, not {type(index).__name__}")
        i = int(index) + (self._length if index < 0 else 0)
        if not 0 <= i < self._length:
            raise IndexError(f"frame index {index} out of range for {self._length} frames")
        if self.paths is not None:
            image, name = cv2.imread(str(self.paths[i]), cv2.IMREAD_UNCHANGED), self.paths[i]
        else:
            image, name = self._read_video(i), f"{self.video} frame {i}"
        return self._check(image, name)

    def __iter__(self) -> Iterator[np.ndarray]:
        for i in range(self._length):
            yield self[i]

    def __del__(self) -> None:
        self.close()

    def close(self) -> None:
        if getattr(self, "_capture", None) is not None:
            self._capture.release()
            self._capture = None

    def _open_capture(self) -> cv2.VideoCapture:
        if self._capture is None:
            self._capture = cv2.VideoCapture(str(self.video))
            self._next = 0
            if not self._capture.isOpened():
                self._capture = None
                raise ValueError(f"{self.video}: cannot open video")
        return self._capture

    def _read_video(self, i: int) -> np.ndarray | None:
        capture = self._open_capture()
        if i != self._next:
            capture.set(cv2.CAP_PROP_POS_FRAMES, i)
        ok, image = capture.read()
        self._next = i + 1
        return image if ok else None

    def _check(self, image: np.ndarray | None, name) -> np.ndarray:
        if image is None:
            raise ValueError(f"{name}: cannot read image")
        if image.dtype != np.uint8:
            raise ValueError(f"{name}: expected an 8-bit image, got {image.dtype}")
        if image.ndim == 3 and image.shape[2] == 4:
            image = np.ascontiguousarray(image[:, :, :3])
        if image.ndim == 3 and image.shape[2] == 1:
            image = image[:, :, 0]
        if self.expected_size is not None:
            w, h = self.expected_size
            if image.shape[1] != w or image.shape[0] != h:
                raise ValueError(
                    f"{name}: image is {image.shape[1]}x{image.shape[0]} but "
                    f"{self.size_source} says {w}x{h}"
                )
        return image


def write_frames(frames_dir: str | Path, images: Iterable[np.ndarray]) -> int:
    """Write images as ``000000.png``, ``000001.png``, … one at a time; returns the count."""
    frames_dir = Path(frames_dir)
    frames_dir.mkdir(parents=True, exist_ok=True)
    count = 0
    for count, image in enumerate(images, start=1):
        image = np.asarray(image)
        path = frames_dir / f"{count - 1:06d}.png"
        if image.dtype != np.uint8 or image.ndim not in (2, 3):
            raise ValueError(
                f"{path}: expected a uint8 (H, W) or (H, W, 3) image, "
                f"got {image.dtype} {image.shape}"
            )
        if not cv2.imwrite(str(path), image):
            raise ValueError(f"{path}: cv2.imwrite failed")
    return count
