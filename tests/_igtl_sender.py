"""A minimal OpenIGTLink sender for tests: a TCP server on localhost that, once a client
connects, sends scripted IMAGE / TRANSFORM messages (packed by pyigtl) at their times, then
closes the connection, as PLUS Server streaming a recording would."""

from __future__ import annotations

import socket
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


def tracker_matrix(translation, quaternion) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = Rotation.from_quat(quaternion).as_matrix()
    M[:3, 3] = translation
    return M


def dataset_events(ds, *, n_frames: int | None = None, device: str = "SensorToTracker",
                   invert: bool = False, clock_ahead_s: float = 0.0) -> list[tuple[float, bytes]]:
    """(time, message) for a dataset's frames and valid tracker samples (at the tracker's own
    rate, up to the last frame), images before the transforms of the same time; the
    transforms are stamped clock_ahead_s later than sent (a tracker whose clock is ahead)."""
    times = np.asarray(ds.timestamps)[:n_frames]
    tr = ds.tracking
    events = [(float(t), 1, image_message(ds.frames[k], float(t))) for k, t in enumerate(times)]
    for i, t in enumerate(tr.timestamps):
        if tr.valid[i] and t <= times[-1]:
            M = tracker_matrix(tr.translations[i], tr.quaternions[i])
            events.append((float(t), 2, transform_message(np.linalg.inv(M) if invert else M,
                                                           float(t) + clock_ahead_s, device)))
    events.sort(key=lambda e: (e[0], e[1]))
    return [(t, m) for t, _, m in events]


def robot_events(ds, *, device: str = "RobotToBase",
                 clock_ahead_s: float = 0.0) -> list[tuple[float, bytes]]:
    """(time, message) for a pCLE dataset's frames and robot samples (the probe position as a
    TRANSFORM's translation, mm, in the image axes), up to the last frame; the transforms
    stamped clock_ahead_s later than sent (a robot whose clock is ahead)."""
    times = np.asarray(ds.timestamps)
    events = [(float(t), 1, image_message(ds.frames[k], float(t))) for k, t in enumerate(times)]
    for t, xy in zip(ds.robot.timestamps, ds.robot.xy_um, strict=True):
        if t <= times[-1]:
            M = np.eye(4)
            M[:2, 3] = xy / 1e3
            events.append((float(t), 2, transform_message(M, float(t) + clock_ahead_s,
                                                           device)))
    events.sort(key=lambda e: (e[0], e[1]))
    return [(t, m) for t, _, m in events]


class Sender:
    """Serves `events` [(time s, bytes)] to the first client, in real time (scaled by `speed`),
    starting `delay` s after it connects; then closes. `port` is the listening port."""

    def __init__(self, events, *, speed: float = 1.0, delay: float = 0.3) -> None:
        self.events, self.speed, self.delay = events, speed, delay
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
        except BaseException as exc:  # noqa: BLE001 (reported by join)
            self.error = exc
        finally:
            self.server.close()

    def join(self) -> None:
        self.thread.join(timeout=60)
        if self.error is not None and not isinstance(self.error, (BrokenPipeError,
                                                                  ConnectionResetError)):
            raise self.error
