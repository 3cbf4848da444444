"""Recording a live session as a dataset folder (the dataset contract), while it runs.

Frames are written as PNG (fast, level 1) by a background thread (a live loop does not wait for
the disk) into a temporary folder next to the destination. The queue holds at most
``max_queued`` frames: when the disk cannot keep up, `add_frame` waits (the recording never
skips a frame, and memory stays bounded; the live view then drops more frames). `finish` adds
frames.csv, tracking.csv (every tracker sample, at the tracker's own rate, samples the sender
flagged or that are not rigid as valid=0), camera.yaml and hand_eye.txt and renames the folder into
place, so the recording is complete or absent, never partial; `abort` removes it. The recording
can then be mosaicked offline with any method (`fusedmosaic run DATA --method ba-emt`).
"""

from __future__ import annotations

import queue
import shutil
import threading
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from fusedmosaic.io._table import format_float, write_table
from fusedmosaic.io.calibration import Camera, write_camera_yaml
from fusedmosaic.io.dataset import _replace_dir, staging_folder
from fusedmosaic.io.tracking import (
    RobotSamples,
    TrackingSamples,
    write_hand_eye,
    write_robot_csv,
    write_tracking_csv,
)

__all__ = ["DatasetRecorder"]


class DatasetRecorder:
    """Records frames (`add_frame`) and tracker samples (`add_sample`) into dataset folder
    `root` (must not exist or be empty, unless overwrite replaces an earlier dataset there).
    Thread-safe: the OpenIGTLink receiver calls it from its thread. robot: the samples are a
    robot's probe positions (their translation, mm, in the image axes) and go to robot.csv in µm
    (valid ones only: robot.csv has no validity column) instead of tracking.csv."""

    def __init__(self, root: str | Path, camera: Camera, hand_eye=None, *,
                 overwrite: bool = False, max_queued: int = 64, robot: bool = False) -> None:
        self.root = Path(root)
        self._tmp = staging_folder(self.root, overwrite, "choose a new folder for the "
                                   "recording, or allow overwriting an earlier recording")
        self.camera, self.hand_eye, self.robot = camera, hand_eye, robot
        (self._tmp / "frames").mkdir()
        self.timestamps: list[float] = []
        self._samples: list[tuple[float, np.ndarray | None]] = []
        self._lock = threading.Lock()
        self._queue: queue.Queue = queue.Queue(maxsize=max_queued)
        self._error: BaseException | None = None
        self._discard = False
        self._writer = threading.Thread(target=self._write_loop, name="recorder", daemon=True)
        self._writer.start()

    def add_frame(self, image: np.ndarray, timestamp: float) -> int:
        """Queues a frame for writing; returns its frame id in the recording (0, 1, ...)."""
        with self._lock:
            if self._error is not None:
                raise self._error
            k = len(self.timestamps)
            self.timestamps.append(float(timestamp))
        self._queue.put((k, image))
        return k

    def add_sample(self, timestamp: float, tracker_from_sensor: np.ndarray | None) -> None:
        """A tracker sample (4x4 tracker_from_sensor, mm), or None: a missing one (valid=0)."""
        with self._lock:
            self._samples.append((float(timestamp), None if tracker_from_sensor is None
                                  else np.asarray(tracker_from_sensor, float)))

    def valid_sample_span(self) -> tuple[float, float] | None:
        """(first, last) time of the valid tracker samples recorded; None without any."""
        with self._lock:
            times = [t for t, m in self._samples if m is not None]
        return (times[0], times[-1]) if times else None

    def finish(self) -> Path:
        """Waits for the frames to be written, writes the tables and renames the recording
        into place; returns its folder. On failure the temporary folder is removed."""
        try:
            self._queue.put(None)
            self._writer.join()
            if self._error is not None:
                raise self._error
            write_camera_yaml(self._tmp / "camera.yaml", self.camera)
            write_table(self._tmp / "frames.csv", ["frame", "timestamp"],
                        ([str(k), format_float(t)] for k, t in enumerate(self.timestamps)))
            if self.robot:
                kept = [(t, m[:2, 3] * 1e3) for t, m in self._samples if m is not None]
                if kept:
                    write_robot_csv(self._tmp / "robot.csv", RobotSamples(
                        [t for t, _ in kept], np.array([xy for _, xy in kept])))
            elif self._samples:
                times = np.array([t for t, _ in self._samples])
                valid = np.array([m is not None for _, m in self._samples])
                T = np.stack([np.full((4, 4), np.nan) if m is None else m
                              for _, m in self._samples])
                q = np.full((len(times), 4), np.nan)
                if valid.any():
                    q[valid] = Rotation.from_matrix(T[valid, :3, :3]).as_quat()
                write_tracking_csv(self._tmp / "tracking.csv", TrackingSamples(
                    times, T[:, :3, 3], q, valid))
            if self.hand_eye is not None:
                write_hand_eye(self._tmp / "hand_eye.txt", self.hand_eye)
            _replace_dir(self._tmp, self.root)
        except BaseException:
            self.abort()
            raise
        return self.root

    def abort(self) -> None:
        """Discards the recording (the frames still queued are not written)."""
        self._discard = True
        self._queue.put(None)
        self._writer.join()
        shutil.rmtree(self._tmp, ignore_errors=True)

    def _write_loop(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            if self._error is not None or self._discard:
                continue
            k, image = item
            path = self._tmp / "frames" / f"{k:06d}.png"
            try:  # fast PNG (level 1): the disk keeps up with the video
                if not cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
                    raise ValueError(f"{path}: cv2.imwrite failed")
            except BaseException as exc:
                with self._lock:
                    self._error = exc
