"""A minimal OpenIGTLink sender for tests: a TCP server on localhost that, once a client
connects, sends scripted IMAGE / TRANSFORM / POSITION messages (packed by pyigtl) at their
times, then closes the connection, as PLUS Server streaming a recording would."""

from __future__ import annotations

import socket
import struct
import threading
import time

import numpy as np
import pyigtl
from scipy.spatial.transform import Rotation

T0 = 1.7e9  # the sender's clock: seconds since 1970


def image_message(image: np.ndarray, t: float, device: str = "Video") -> bytes:
    image = np.asarray(image)
    if image.ndim == 3:
        image = image[:, :, ::-1]  # BGR -> RGB, as PLUS sends colour
    return pyigtl.ImageMessage(image[None], timestamp=T0 + t, device_name=device).pack()


def transform_message(matrix: np.ndarray, t: float, device: str = "SensorToTracker") -> bytes:
    return pyigtl.TransformMessage(matrix, timestamp=T0 + t, device_name=device).pack()


class _Position(pyigtl.MessageBase):
    def __init__(self, values, **kwargs) -> None:
        super().__init__(**kwargs)
        self._message_type, self.values = "POSITION", values

    def _pack_content(self) -> bytes:
        return struct.pack(f">{len(self.values)}f", *self.values)


def position_message(matrix: np.ndarray, t: float, device: str = "SensorToTracker", *,
                     size: int = 28, metadata: dict | None = None) -> bytes:
    """A standard OpenIGTLink POSITION of a pose: x, y, z, then ox, oy, oz, w (size 28), ox,
    oy, oz with w >= 0 implied (24) or no orientation (12); header version 2 with metadata.
    (pyigtl's PositionMessage packs another, multi-point layout.)"""
    q = Rotation.from_matrix(matrix[:3, :3]).as_quat()
    q = -q if q[3] < 0 else q
    values = [*matrix[:3, 3], *q][: size // 4]
    message = _Position(values, timestamp=T0 + t, device_name=device)
    if metadata is not None:
        message.header_version, message.metadata = 2, metadata
    return message.pack()


def tracker_matrix(translation, quaternion) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = Rotation.from_quat(quaternion).as_matrix()
    M[:3, 3] = translation
    return M


def dataset_events(ds, *, n_frames: int | None = None, device: str = "SensorToTracker",
                   invert: bool = False, clock_ahead_s: float = 0.0,
                   position: bool = False, stamp=None) -> list[tuple[float, bytes]]:
    """(time, message) for a dataset's frames and valid tracker samples (at the tracker's own
    rate, up to the last frame), images before the transforms of the same time; the
    transforms are stamped clock_ahead_s later than sent (a tracker whose clock is ahead);
    position: samples as POSITION messages (28 bytes) instead of TRANSFORMs; stamp(t): the
    stamp of every message sent at t (the sender's clock, e.g. jumping; default t)."""
    stamp = (lambda t: t) if stamp is None else stamp
    pose_message = position_message if position else transform_message
    times = np.asarray(ds.timestamps)[:n_frames]
    tr = ds.tracking
    events = [(float(t), 1, image_message(ds.frames[k], stamp(float(t))))
              for k, t in enumerate(times)]
    for i, t in enumerate(tr.timestamps):
        if tr.valid[i] and t <= times[-1]:
            M = tracker_matrix(tr.translations[i], tr.quaternions[i])
            events.append((float(t), 2, pose_message(np.linalg.inv(M) if invert else M,
                                                     stamp(float(t)) + clock_ahead_s, device)))
    events.sort(key=lambda e: (e[0], e[1]))
    return [(t, m) for t, _, m in events]


def robot_events(ds, *, device: str = "RobotToBase", clock_ahead_s: float = 0.0,
                 position: bool = False) -> list[tuple[float, bytes]]:
    """(time, message) for a pCLE dataset's frames and robot samples (the probe position as a
    TRANSFORM's translation, mm, in the image axes; position: a 12-byte POSITION), up to the
    last frame; the samples stamped clock_ahead_s later than sent (a robot whose clock is
    ahead)."""
    times = np.asarray(ds.timestamps)
    events = [(float(t), 1, image_message(ds.frames[k], float(t))) for k, t in enumerate(times)]
    for t, xy in zip(ds.robot.timestamps, ds.robot.xy_um, strict=True):
        if t <= times[-1]:
            M = np.eye(4)
            M[:2, 3] = xy / 1e3
            stamp = float(t) + clock_ahead_s
            events.append((float(t), 2, position_message(M, stamp, device, size=12) if position
                           else transform_message(M, stamp, device)))
    events.sort(key=lambda e: (e[0], e[1]))
    return [(t, m) for t, _, m in events]


class Sender:
    """Serves `events` [(time s, bytes)] to the first client, in real time (scaled by `speed`),
    starting `delay` s after it connects; then closes (reset: abruptly, the client's next read
    fails with 'connection reset', as when a sender crashes). `port` is the listening port."""

    def __init__(self, events, *, speed: float = 1.0, delay: float = 0.3,
                 reset: bool = False) -> None:
        self.events, self.speed, self.delay, self.reset = events, speed, delay, reset
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        try:
            self.server.settimeout(30)
            conn, _ = self.server.accept()
            with conn:
                time.sleep(self.delay)
                start = time.perf_counter()
                t_first = self.events[0][0] if self.events else 0.0
                for t, message in self.events:
                    due = start + (t - t_first) / self.speed
                    wait = due - time.perf_counter()
                    if wait > 0:
                        time.sleep(wait)
                    conn.sendall(message)
                time.sleep(0.1)
                if self.reset:  # RST instead of FIN
                    conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER,
                                    struct.pack("ii", 1, 0))
        except BaseException as exc:  # noqa: BLE001 (reported by join)
            self.error = exc
        finally:
            self.server.close()

    def join(self) -> None:
        self.thread.join(timeout=60)
        if self.error is not None and not isinstance(self.error, (BrokenPipeError,
                                                                  ConnectionResetError)):
            raise self.error
