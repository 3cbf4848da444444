"""Recording a live session as a dataset folder (the dataset contract), while it runs.

The recording is built in a hidden staging folder next to the destination (``.NAME.tmp-*``)
that is a readable dataset at every moment, so that a session killed outright (SIGKILL, a power
cut of the process, a crash) loses at most the frame being written:

- camera.yaml and hand_eye.txt are written when the recording starts;
- frames are written as received (8- or 16-bit PNG, lossless: an offline re-run reads what the
  sender sent) by a background thread, each under a hidden name renamed once complete, and only
  then is its row appended to frames.csv;
- every tracker sample is appended to tracking.csv as it arrives (at the tracker's own rate;
  samples the sender flagged or that are not rigid as valid=0), or for a robot its valid
  positions to robot.csv (µm);
- each row is appended unbuffered (nothing waits in a buffer of this process; no fsync, so a
  crash of the machine itself may lose the last seconds the OS had not yet written), whole or
  not at all: a write cut short (a full disk takes part of a row, then fails) is taken back.

The recording does not hold up a live session: it may skip frames, the live view does not fall
behind for it. `add_frame` never waits for the disk (the OpenIGTLink receiver calls it: a
receiver that waited stopped reading the socket, and at 1920x1080, 25 frames/s, the live view
was 68 s behind after 95 s while the latency measured from receipt read 0.1 s), and the writer
thread runs at a lower priority (nice 10, on Linux): it takes the CPU the receiver and the live
loop leave. The frames waiting to be written hold at most ``max_queued_bytes`` (256 MiB); a
frame that does not fit is not recorded (`add_frame` returns None; counted in
`frames_not_recorded`; run_igtl neither records nor processes it, warns at the first and reports
the count). To record as many as it can, the writer compresses fast (zlib's run-length strategy
on the "up" filter: 1920x1080 colour 52 ms a frame, 3.1 MB, where level 1 took 116 ms for
3.0 MB; a scope's round field on black 29 ms instead of 85, and smaller) and, while frames wait
beyond an eighth of that bound (the compression behind the stream), stores them uncompressed
(12 ms and 6.2 MB each written to disk here) unless storing was measured slower (a slow disk):
lossless either way, `frames_uncompressed` counts them. With the CPU and disk to spare, every
frame is recorded.

`finish` renames the folder into place atomically; SIGINT / SIGTERM / SIGHUP arriving meanwhile
are handled after it, and a failure keeps the frames written, a readable dataset (a recording
that holds a frame is never deleted; a tracker sample that cannot be written stops the samples
and the frames received after it, the frames already waiting are still written); `abort`
discards it. A lock file in the staging folder
(``.fusedmosaic-recording.json``, locked while its process lives) tells a later recorder in the
same folder that a session ended without finishing: `recover_unfinished_recordings` renames such
a folder into a dataset ``NAME.recovered-START`` beside it and says so. The recording can then
be mosaicked offline with any method (``fusedmosaic run DATA --method ba-emt``).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import queue
import shutil
import socket
import sys
import threading
import time
import warnings
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from fusedmosaic.io._table import format_float
from fusedmosaic.io.calibration import Camera, write_camera_yaml
from fusedmosaic.io.dataset import _replace_dir, staging_folder
from fusedmosaic.io.output import ImageEncodingError, signals_deferred, write_image_file
from fusedmosaic.io.tracking import ROBOT_COLUMNS, TRACKING_COLUMNS, write_hand_eye

__all__ = ["DatasetRecorder", "recover_unfinished_recordings"]

# In a recording's staging folder while its session runs; locked (flock) by that process, so a
# folder whose lock can be taken belongs to a session that ended without finishing.
MARKER = ".fusedmosaic-recording.json"
# The frames waiting to be written, at most (their arrays' bytes): 43 frames of 1920x1080 colour,
# 1.7 s of a 25 frames/s stream: a short stall of the disk passes without a frame lost, in memory
# a theatre PC spares (the former bound, 64 frames, was 400 MB at 1080p and could not drop).
MAX_QUEUED_BYTES = 256 << 20
# Lossless PNG, fast: zlib's run-length strategy (LZ77 of distance 1) on the "up" filter, against
# level 1's default (1920x1080, one core here): textured colour 52 ms / 3.11 MB a frame (level 1
# 116 ms / 3.04 MB), a round field on black 29 ms / 1.39 MB (85 ms / 1.57 MB), 16-bit gray
# 21 ms / 1.16 MB (55 ms / 1.24 MB); Huffman-only was 46 ms but 2.0 MB for the round field.
# (cv2 < 4.10 has no filter setting: the strategy alone, 101 ms on the textured frame.)
_FILTER = ([cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP]
           if hasattr(cv2, "IMWRITE_PNG_FILTER") else [])
PNG_COMPRESSED = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY,
                  cv2.IMWRITE_PNG_STRATEGY_RLE, *_FILTER]
# Stored (deflate's level 0, no filter): 7 ms to encode a 1920x1080 colour frame, 12 ms with the
# write, 6.2 MB; for the frames written while the compression is behind the stream.
PNG_STORED = [cv2.IMWRITE_PNG_COMPRESSION, 0,
              *([cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE] if _FILTER else [])]
STORE_ABOVE = 1 / 8  # of max_queued_bytes waiting (32 MiB: 5 frames of 1080p colour, 0.2 s)
# The writer thread's nice value (Linux, where a thread has its own): the receiver and the live
# loop come first, the recording takes the CPU they leave, and a queue that fills drops frames.
# 1920x1080 colour at 25 frames/s into IgtlSource for 30 s (review's repro; 2 cores shared with
# another job, runs interleaved): at nice 10 the frame taken was 0.04 s old (median; 0.27-0.31 s
# at most), 91 % of the frames recorded; at nice 0 all were, but it fell 2.3-5.7 s behind; with
# no recorder, 0.04 s (0.07-0.12 s at most).
WRITER_NICE = 10
RETRY_STORED = 32  # while behind and compressing (storing measured slower), every 32nd frame
# is stored to measure it again (a disk stall may have made it look slow)


class DatasetRecorder:
    """Records frames (`add_frame`) and tracker samples (`add_sample`) into dataset folder
    `root` (must not exist or be empty, unless overwrite replaces an earlier dataset there).
    Thread-safe: the OpenIGTLink receiver calls it from its thread. robot: the samples are a
    robot's probe positions (their translation, mm, in the image axes) and go to robot.csv in µm
    (valid ones only: robot.csv has no validity column) instead of tracking.csv. Recordings of
    earlier sessions in the same parent folder that ended without finishing are recovered first
    (`recover_unfinished_recordings`, a warning each; `recovered` lists them).
    max_queued_bytes: the frames waiting to be written hold at most this (see the module's
    docstring); a frame beyond it is not recorded."""

    def __init__(self, root: str | Path, camera: Camera, hand_eye=None, *,
                 overwrite: bool = False, max_queued_bytes: int = MAX_QUEUED_BYTES,
                 robot: bool = False, tracker_time_offset: float = 0.0,
                 source: str = "live session") -> None:
        if not (isinstance(max_queued_bytes, int) and max_queued_bytes > 0):
            raise ValueError(f"recorder: max_queued_bytes must be an integer > 0, got "
                             f"{max_queued_bytes!r}")
        self.root = Path(root)
        self.recovered = recover_unfinished_recordings(self.root.parent, self.root.name)
        for note in self.recovered:
            warnings.warn(note, stacklevel=2)
        self._tmp = staging_folder(self.root, overwrite, "choose a new folder for the "
                                   "recording, or allow overwriting an earlier recording")
        self.camera, self.hand_eye, self.robot = camera, hand_eye, robot
        self.timestamps: list[float] = []  # every frame queued (recording ids 0, 1, ...)
        self.frames_written = 0  # frames on disk with their frames.csv row
        self.frames_not_recorded = 0  # frames add_frame had no room for
        self.frames_uncompressed = 0  # frames written stored, the compression behind
        self._max_bytes = max_queued_bytes
        self._queued_bytes = 0  # of the frames queued and not yet written
        # seconds per byte of image written, EMA, compressed [0] / stored [1] (0: not measured)
        self._cost = [0.0, 0.0]
        self._since_stored = 0  # frames compressed while behind since the last one stored
        self._valid_span: list[float] = []  # first and last valid sample time
        self.samples_skipped = 0
        self._last_sample = -np.inf
        self._lock = threading.Lock()
        self._queue: queue.Queue = queue.Queue()  # bounded by _max_bytes in add_frame
        self._error: BaseException | None = None  # a frame's (the frames stop there)
        # tracking.csv's / robot.csv's: the samples stop there, and the frames received after it
        # (the frames already waiting are written: they were all lost to a failed sample, and
        # the recording deleted as "no frame could be written", frames never tried; review 48)
        self._samples_error: BaseException | None = None
        self._discard = False
        self._finished = False
        self._samples_fd: int | None = None
        self._frames_fd: int | None = None
        self._marker_fd: int | None = None
        try:
            self._marker_fd = _write_marker(self._tmp / MARKER, self.root, robot)
            write_camera_yaml(self._tmp / "camera.yaml", camera)
            if hand_eye is not None:
                write_hand_eye(self._tmp / "hand_eye.txt", hand_eye)
            if tracker_time_offset:  # the samples are recorded on the video's clock (stamped -
                # offset): said as import says it, so that run --calibration on the recording
                # does not shift them again (io.plus.applied_tracker_time_offset)
                from fusedmosaic.io.plus import IMPORT_RECORD, time_offset_record

                (self._tmp / IMPORT_RECORD).write_text(time_offset_record(
                    tracker_time_offset, source, "robot.csv" if robot else "tracking.csv",
                    "live --tracker-time-offset"))
            (self._tmp / "frames").mkdir()
            self._frames_fd = _open_table(self._tmp / "frames.csv", ["frame", "timestamp"])
        except BaseException:
            self._close_files()
            shutil.rmtree(self._tmp, ignore_errors=True)
            raise
        self._writer = threading.Thread(target=self._write_loop, name="recorder", daemon=True)
        self._writer.start()

    def add_frame(self, image: np.ndarray, timestamp: float) -> int | None:
        """Queues a frame for writing (the array is kept as it is: not to be changed after);
        returns its frame id in the recording (0, 1, ...), or None, at once, when the frames
        waiting to be written would hold more than max_queued_bytes with it: it is not recorded
        (counted in `frames_not_recorded`). Never waits for the disk."""
        size = image.nbytes
        with self._lock:
            if self._error is not None or self._samples_error is not None:
                raise self._error or self._samples_error
            if self._queued_bytes and self._queued_bytes + size > self._max_bytes:  # (a frame
                # larger than the bound is taken when nothing waits)
                self.frames_not_recorded += 1
                return None
            k = len(self.timestamps)
            self.timestamps.append(float(timestamp))
            self._queued_bytes += size
            self._queue.put((k, image, float(timestamp)))  # (unbounded: does not block)
        return k

    def add_sample(self, timestamp: float, tracker_from_sensor: np.ndarray | None) -> None:
        """A tracker sample (4x4 tracker_from_sensor, mm), or None: a missing one (valid=0),
        appended to tracking.csv (robot: a valid one's translation to robot.csv, µm). A sample
        not after the previous one is not recorded (counted in `samples_skipped`; the OpenIGTLink
        receiver does not pass them on)."""
        t = float(timestamp)
        M = None if tracker_from_sensor is None else np.asarray(tracker_from_sensor, float)
        if self.robot:
            if M is None:
                return
            row = [format_float(t), *(format_float(v) for v in M[:2, 3] * 1e3)]
        elif M is None:
            row = [format_float(t), *[""] * 7, "0"]
        else:
            q = Rotation.from_matrix(M[:3, :3]).as_quat()  # ~50 µs: 2 ms/s at 40 Hz
            row = [format_float(t), *(format_float(v) for v in (*M[:3, 3], *q)), "1"]
        with self._lock:
            if (self._error is not None or self._samples_error is not None or self._finished
                    or self._discard):
                return
            if not t > self._last_sample:  # tracking.csv is in time order
                self.samples_skipped += 1
                return
            try:
                if self._samples_fd is None:
                    name, columns = (("robot.csv", ROBOT_COLUMNS) if self.robot else
                                     ("tracking.csv", [*TRACKING_COLUMNS, "valid"]))
                    self._samples_fd = _open_table(self._tmp / name, columns)
                _append_row(self._samples_fd, (",".join(row) + "\n").encode(),
                            self._samples_name())
            except OSError as exc:  # e.g. a full disk: the recording stops growing here
                self._samples_error = exc
                return
            self._last_sample = t
            if M is not None:
                self._valid_span = [self._valid_span[0] if self._valid_span else t, t]

    def _samples_name(self) -> str:
        return "robot.csv" if self.robot else "tracking.csv"

    def valid_sample_span(self) -> tuple[float, float] | None:
        """(first, last) time of the valid tracker samples recorded; None without any."""
        with self._lock:
            return tuple(self._valid_span) if self._valid_span else None

    @property
    def max_queued_bytes(self) -> int:
        """The bound of the frames waiting to be written (bytes)."""
        return self._max_bytes

    @property
    def finished(self) -> bool:
        """Whether the recording is in place (`finish` done)."""
        return self._finished

    @property
    def staging(self) -> Path:
        """The folder the recording grows in (a readable dataset) until `finish`."""
        return self._tmp

    def finish(self) -> Path:
        """Waits for the frames to be written and renames the recording into place; returns its
        folder. SIGINT / SIGTERM / SIGHUP arriving meanwhile are handled once it is done. When a
        frame or sample could not be written (e.g. a full disk), the frames written before are
        kept all the same, a dataset, and ValueError says how many and what failed; when even
        the rename fails, the recording stays in the staging folder, named in the error. Calling
        it again returns the folder."""
        with signals_deferred():
            if self._finished:
                return self.root
            self._queue.put(None)
            self._writer.join()
            self._close_files(keep_marker=True)
            failed = self._failures()
            if failed:  # (each row is whole and each frame has its row: this checks it again, as
                # recovering a killed session's does, so the folder kept is a dataset whatever
                # the write that failed left)
                try:
                    self.frames_written = min(self.frames_written, _repair(self._tmp))
                except OSError as exc:
                    failed += f"; the recording could not be checked ({_describe(exc)})"
            if self.frames_written == 0 and failed:
                self.abort()
                if self._error is None:  # (the samples failed before a frame was received)
                    raise ValueError(f"recording {self.root}: {failed}, before a frame was "
                                     "received; nothing is kept") from None
                raise ValueError(f"recording {self.root}: no frame could be written: "
                                 f"{failed}") from None
            try:
                _replace_dir(self._tmp, self.root)
            except OSError as exc:
                raise ValueError(f"recording {self.root}: could not be moved into place "
                                 f"({_describe(exc)}); the {self.frames_written} frame(s) "
                                 f"recorded are in {self._tmp} (a dataset: rename it)") from None
            self._finished = True
            (self.root / MARKER).unlink(missing_ok=True)
            self._close_files()
        if failed:
            raise ValueError(f"recording {self.root}: stopped after {self.frames_written} "
                             f"frame(s) ({failed}); those are kept there") from None
        return self.root

    def _failures(self) -> str:
        """What could not be written, for the user ("" when nothing failed)."""
        said = []
        if self._samples_error is not None:
            said.append(_describe(self._samples_error))
        if self._error is not None:
            said.append(_describe(self._error))
        return "; ".join(said)

    def abort(self) -> None:
        """Discards the recording (the frames still queued are not written)."""
        if self._finished:
            return
        self._discard = True
        self._queue.put(None)
        self._writer.join()
        self._close_files()
        shutil.rmtree(self._tmp, ignore_errors=True)

    def _close_files(self, keep_marker: bool = False) -> None:
        with self._lock:
            names = ["_frames_fd", "_samples_fd"] + ([] if keep_marker else ["_marker_fd"])
            for name in names:
                fd = getattr(self, name)
                if fd is not None:
                    setattr(self, name, None)
                    os.close(fd)  # closing the marker releases its lock

    def _write_loop(self) -> None:
        if sys.platform.startswith("linux"):  # (where a thread has its own nice value)
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), WRITER_NICE)
        while True:
            item = self._queue.get()
            if item is None:
                return
            k, image, t = item
            try:
                if self._error is None and not self._discard:
                    self._write(k, image, t)
            except BaseException as exc:
                with self._lock:
                    self._error = exc
            finally:
                with self._lock:
                    self._queued_bytes -= image.nbytes

    def _store(self) -> bool:
        """Whether the next frame is stored uncompressed: while the frames waiting exceed
        STORE_ABOVE of the bound (the compression behind the stream), unless storing was
        measured slower than compressing (a disk slower than the encoder), then only every
        RETRY_STORED frames, to measure it again."""
        with self._lock:
            behind = self._queued_bytes > STORE_ABOVE * self._max_bytes
        compressed, stored = self._cost
        if not behind:
            return False
        self._since_stored += 1
        return not (stored > compressed > 0) or self._since_stored >= RETRY_STORED

    def _write(self, k: int, image: np.ndarray, t: float) -> None:
        name = f"{k:06d}.png"
        part = self._tmp / "frames" / f".{k:06d}.part.png"  # hidden: not a frame yet
        store = self._store()
        start = time.perf_counter()
        _write_png(part, image, PNG_STORED if store else PNG_COMPRESSED)
        cost, mode = (time.perf_counter() - start) / max(image.nbytes, 1), int(store)
        self._cost[mode] = cost if not self._cost[mode] else 0.75 * self._cost[mode] + 0.25 * cost
        if store:
            self._since_stored = 0
        try:
            os.replace(part, part.with_name(name))
            with self._lock:
                _append_row(self._frames_fd, f"{k},{format_float(t)}\n".encode(), "frames.csv")
                self.frames_written += 1
                self.frames_uncompressed += store
        except BaseException:  # no frame without its row (read_dataset refuses the folder)
            for path in (part, part.with_name(name)):
                with contextlib.suppress(OSError):
                    path.unlink(missing_ok=True)
            raise


def _write_png(path: Path, image: np.ndarray, params: list[int]) -> None:
    """`image` written as a PNG at `path` (io.output.write_image_file); OSError naming `path` if
    it cannot be encoded or written."""
    try:
        write_image_file(path, image, params)
    except ImageEncodingError as exc:
        raise OSError(str(exc)) from None
    except OSError as exc:
        raise OSError(exc.errno, f"{path}: {exc.strerror}") from None


def _describe(exc: BaseException) -> str:
    return (exc.strerror or str(exc)) if isinstance(exc, OSError) else str(exc)


def _open_table(path: Path, header: list[str]) -> int:
    """A new CSV file with its header, open for appending rows (`_append_row`); not left
    behind if the header cannot be written."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND, 0o666)
    try:
        _append_row(fd, (",".join(header) + "\n").encode(), path.name)
    except BaseException:
        os.close(fd)
        with contextlib.suppress(OSError):
            path.unlink()
        raise
    return fd


def _append_row(fd: int, row: bytes, name: str) -> None:
    """Appends `row` to the table open at `fd` (O_APPEND), whole or not at all: a write cut short
    is continued, and when one fails the table is cut back to where the row began. (A full disk,
    or a file size limit, takes part of the row and fails the next write: the table ended in half
    a row, '41,170', and the recording kept was no dataset; review 48.) OSError naming `name`."""
    start = os.fstat(fd).st_size
    done = 0
    try:
        while done < len(row):
            n = os.write(fd, row[done:])
            if n <= 0:  # (not expected of a regular file: not looped on)
                raise OSError(errno.EIO, "the write wrote nothing")
            done += n
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.ftruncate(fd, start)
        if isinstance(exc, OSError):
            raise OSError(exc.errno, f"{name}: {exc.strerror or exc}") from None
        raise


def _write_marker(path: Path, root: Path, robot: bool) -> int:
    """Writes the staging folder's marker and keeps it open, locked: returns its descriptor."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        info = {"written_by": "fusedmosaic", "recording": str(Path(os.path.abspath(root))),
                "name": root.name, "robot": robot, "pid": os.getpid(),
                "host": socket.gethostname(), "started": time.time()}
        os.write(fd, (json.dumps(info) + "\n").encode())
    except BaseException:
        os.close(fd)
        raise
    return fd


def recover_unfinished_recordings(folder: str | Path, name: str | None = None) -> list[str]:
    """Recordings in `folder` whose session ended without finishing (its process was killed or
    crashed: the staging folder's marker is no longer locked) become datasets: the last,
    incomplete row or frame is dropped and the folder is renamed NAME.recovered-START (START:
    when the session started; -2, -3, ... when taken). A leftover without a frame is removed.
    Returns a message per folder, for the user: what was found and where it is now. A staging
    folder of this recording's name without the marker (an older version's, frames without
    timestamps, the recording `name` given) is named, not touched."""
    folder = Path(folder)
    notes: list[str] = []
    try:
        entries = sorted(folder.iterdir())
    except OSError:
        return notes
    for entry in entries:
        if not (entry.name.startswith(".") and ".tmp-" in entry.name and entry.is_dir()
                and not entry.is_symlink()):
            continue
        if not (entry / MARKER).is_file():
            if name is not None and entry.name.startswith(f".{name}.tmp-") and (
                    entry / "frames").is_dir() and not (entry / "frames.csv").exists():
                notes.append(f"{entry}: frames of an earlier recording into {folder / name} "
                             "that never finished (an older version's, without timestamps: "
                             "not a dataset); delete it unless a fusedmosaic process still "
                             "writes there")
            continue
        try:
            note = _recover(entry)
        except (OSError, ValueError) as exc:
            note = (f"{entry}: a live session's recording that ended without finishing; it "
                    f"could not be recovered ({_describe(exc)}): its frames/ and .csv files "
                    f"are there")
        if note:
            notes.append(note)
    return notes


def _recover(staging: Path) -> str | None:
    """Recovers one staging folder (see recover_unfinished_recordings); None when its session
    is still running."""
    fd = os.open(staging / MARKER, os.O_RDONLY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return None  # its session is running
        try:
            info = json.loads(os.read(fd, 1 << 16) or b"{}")
        except ValueError:
            info = {}
        if not isinstance(info, dict):
            info = {}
        host = info.get("host")
        if isinstance(host, str) and host != socket.gethostname():
            return (f"{staging}: a live session recording made on {host} (not this machine: "
                    f"it may still be running there) that looks unfinished; not touched. When "
                    f"that session is over, rename this folder to use it as a dataset")
        frames = _repair(staging)
        name = str(info.get("name") or staging.name.lstrip(".").split(".tmp-")[0])
        what = (f"a live session recording into {staging.parent / name}"
                + (f" (process {info['pid']}, started {_local_time(info['started'])})"
                   if isinstance(info.get("pid"), int)
                   and isinstance(info.get("started"), (int, float)) else ""))
        if frames == 0:
            shutil.rmtree(staging)
            return f"{what} ended without finishing and without a frame; removed its {staging}"
        start = info.get("started")
        stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(
            start if isinstance(start, (int, float)) else staging.stat().st_mtime))
        target = staging.parent / f"{name}.recovered-{stamp}"
        n = 2
        while target.exists() or target.is_symlink():
            target = staging.parent / f"{name}.recovered-{stamp}-{n}"
            n += 1
        os.replace(staging, target)
        (target / MARKER).unlink(missing_ok=True)
    finally:
        os.close(fd)
    method = "kalman-robot" if info.get("robot") else "ba-emt"
    return (f"{what} ended without finishing (killed or crashed); its {frames} frame(s) are "
            f"recovered as the dataset {target} (re-run it offline: fusedmosaic run {target} "
            f"--method {method} --out OUT --allow-untracked)")


def _local_time(t: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t))


def _repair(staging: Path) -> int:
    """Makes a killed session's staging folder a consistent dataset: the .csv files end at their
    last complete row, the frames are those with a frames.csv row (a frame being written is
    dropped). Returns the number of frames."""
    for name in ("frames.csv", "tracking.csv", "robot.csv"):
        path = staging / name
        if path.is_file():
            data = path.read_bytes()
            if data and not data.endswith(b"\n"):
                with path.open("r+b") as f:
                    f.truncate(data.rfind(b"\n") + 1)
    rows = 0
    table = staging / "frames.csv"
    if table.is_file():
        rows = max(0, len(table.read_bytes().splitlines()) - 1)
    images = staging / "frames"
    present = 0
    if images.is_dir():
        for path in images.iterdir():
            stem = path.name.removesuffix(".png")
            if path.name.startswith(".") or not stem.isdigit() or int(stem) >= rows:
                path.unlink()  # a frame being written, or written but without its row
        while (images / f"{present:06d}.png").is_file():
            present += 1
    if present < rows:  # (rows are appended after their frame: not expected)
        lines = table.read_bytes().splitlines(keepends=True)
        table.write_bytes(b"".join(lines[:present + 1]))
    return min(rows, present)
