"""Review 45 (D) of the live view and its OpenIGTLink server: a slow client no longer holds the
view's compositing (findings 1), and a pause in the stamps while a backlog drains is no clock
jump (finding 5)."""

from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest

from fusedmosaic.compositing import IncrementalCanvas, live_view
from fusedmosaic.compositing.live_view import LiveMosaicView
from fusedmosaic.io import igtl
from fusedmosaic.io.igtl import STAMP_JUMP, IgtlImageServer, StampJumps


def _wait(condition, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.01)
    return condition()


def _shift(x: float) -> np.ndarray:
    G = np.eye(3)
    G[0, 2] = x
    return G


class _HeldServer:
    """A server stand-in whose first send waits until `release` is set (a client taking the
    message slowly), keeping what it was sent."""
    address, device_name, clients_served, messages_sent = "-", "Mosaic", 1, 0

    def __init__(self) -> None:
        self.sent: list[np.ndarray] = []
        self.entered = threading.Event()
        self.release = threading.Event()

    def send(self, image, timestamp=None, *, ijk_to_world=None):
        self.entered.set()
        self.release.wait(30.0)
        self.sent.append(image.copy())
        self.messages_sent += 1
        return 1


# -- finding 1: the network is off the compositing thread --------------------------------------


def test_a_send_held_by_a_slow_client_does_not_stop_compositing(monkeypatch):
    """server.send ran on the view's worker: a client taking a 12 MB mosaic at 1.5 MB/s held it
    5.4 s a publication, the frames beyond the 100 waiting were never drawn (166 of 200) and
    the next publication waited 21.6 s (review). Now the worker composites on while the
    publisher sends; the publication waiting is replaced by each newer one, and close()
    delivers the last."""
    monkeypatch.setattr(live_view, "PUBLISH_DUTY", 0.0)  # a publication after every frame
    server = _HeldServer()
    view = LiveMosaicView(16, 16, server=server, interval_s=0.0)
    reference = IncrementalCanvas(16, 16, blend="linear")
    frames = [(np.full((16, 16), 40 + 20 * k, np.uint8), _shift(8 * k)) for k in range(10)]
    try:
        view.add(*frames[0])
        assert server.entered.wait(10.0)  # the publisher is in the send of frame 0's view
        for image, G in frames[1:]:
            view.add(image, G)
        assert _wait(lambda: view.frames_added == 10), view.frames_added  # (before: 1)
        assert _wait(lambda: view.superseded == 8)  # views 1..8 replaced, view 9 waits
        assert view.published == 0 and server.sent == []
    finally:
        server.release.set()
    view.close(timeout_s=30)
    for image, G in frames:
        reference.add(image, G)
    assert view.problems == {}
    assert view.published == server.messages_sent == len(server.sent) == 2
    np.testing.assert_array_equal(server.sent[-1], reference.render())  # the last view
    summary = view.summary()
    assert summary["superseded"] == 8 and summary["width"] == reference.render().shape[1]


def test_close_reports_a_publisher_still_sending():
    """close() waits for the last delivery within its timeout, then says so."""
    server = _HeldServer()
    view = LiveMosaicView(16, 16, server=server, interval_s=0.0)
    view.add(np.full((16, 16), 90, np.uint8), np.eye(3))
    try:
        assert server.entered.wait(10.0)
        view.close(timeout_s=0.2)
    finally:
        server.release.set()
    assert view.problems == {"the view was still publishing after 0.2 s": 1}


# -- finding 1: a message's send time is bounded per client -------------------------------------


def _client(port: int) -> socket.socket:
    client = socket.socket()
    client.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 64 * 1024)  # a slow link's window
    client.connect(("127.0.0.1", port))
    return client


def _read_all(client: socket.socket, chunk: int, pause_s: float, fast: threading.Event) -> int:
    """Bytes read until the server closes: `chunk` every `pause_s`, at once after `fast`."""
    got = 0
    client.settimeout(10.0)
    try:
        while data := client.recv(chunk):
            got += len(data)
            if not fast.is_set():
                time.sleep(pause_s)
    except OSError:  # (reset by the server dropping it)
        pass
    return got


@pytest.mark.realtime  # (a reader paced on the wall clock: run alone)
def test_a_client_slower_than_min_send_rate_is_dropped(monkeypatch):
    """A client taking bytes steadily was kept however slow: one message held the send (and
    the live view) size / rate s. It now has max(send_timeout_s, size / MIN_SEND_RATE): here
    MIN_SEND_RATE is raised to 10 MB/s so that a 12 MB image allows 1.2 s, and a client
    reading ~3 MB/s (never stalled for send_timeout_s, 0.5 s) is dropped mid-message."""
    monkeypatch.setattr(igtl, "MIN_SEND_RATE", 10e6)
    image = np.zeros((2000, 2000, 3), np.uint8)  # 12 MB: 3x the socket's buffer (4 MB)
    size = len(igtl.igtl_image_message(image, device_name="Mosaic", timestamp=0.0).pack())
    with IgtlImageServer("0", send_timeout_s=0.5) as server, _client(server.port) as client:
        assert _wait(lambda: server.num_clients == 1)
        got, fast = [], threading.Event()
        reader = threading.Thread(target=lambda: got.append(
            _read_all(client, 1 << 16, 0.02, fast)))
        reader.start()  # 64 KB every 20 ms: ~3 MB/s, ~2.5 s for 12 MB beyond the buffers
        try:
            assert server.send(image, 0.0) == 0  # (before: 1, after ~2.5 s)
        finally:
            fast.set()  # (the rest the kernel had taken, read at once)
        assert server.num_clients == 0 and server.messages_sent == 0
        reader.join(15.0)
        assert got and got[0] < size


class _Trickle:
    """A client taking one byte every `every_s` (a real socket underneath for select), as a
    link that trickles; `taken` bytes so far."""

    def __init__(self, sock: socket.socket, every_s: float) -> None:
        self.sock, self.every_s, self.taken, self.closed = sock, every_s, 0, False
        self._last = time.monotonic()

    def fileno(self) -> int:
        return self.sock.fileno()

    def send(self, data) -> int:
        if self.closed:
            raise OSError("closed")
        if time.monotonic() - self._last < self.every_s:
            raise BlockingIOError
        self._last = time.monotonic()
        self.taken += 1
        return 1

    def recv(self, n: int) -> bytes:
        raise BlockingIOError

    def close(self) -> None:
        self.closed = True


@pytest.mark.realtime  # (a client paced on the wall clock: run alone)
def test_a_client_trickling_a_byte_within_the_stall_time_is_dropped():
    """A client taking a byte every 1.9 s was never stalled (send_timeout_s 2 s): it held the
    send for ever (review). Scaled down: a byte every 0.19 s against send_timeout_s 0.2 s; a
    131-byte message allows max(0.2 s, 131 B / MIN_SEND_RATE) = 0.2 s (before: ~25 s)."""
    image = np.zeros((1, 1), np.uint8)
    with IgtlImageServer("0", send_timeout_s=0.2) as server, \
            socket.socket() as a, socket.socket() as b:
        b.bind(("127.0.0.1", 0))
        b.listen()
        a.connect(b.getsockname())
        trickle = _Trickle(a, 0.19)
        with server._lock:
            server._clients.append(trickle)
        sent = []
        sender = threading.Thread(target=lambda: sent.append(server.send(image, 0.0)),
                                  daemon=True)
        sender.start()
        sender.join(5.0)
        assert sent == [0] and trickle.closed and server.num_clients == 0
        assert trickle.taken <= 3


# -- finding 5: a pause in the stamps while a backlog drains -----------------------------------


def _feed(jumps: StampJumps, events) -> list[float]:
    refused = []
    for stamp, arrival in events:
        if jumps.check(stamp, arrival) is None:
            jumps.accepted(stamp, arrival)
        else:
            refused.append(round(stamp, 3))
    return refused


def test_a_pause_in_the_stamps_while_a_backlog_drains_is_no_jump():
    """PLUS Server's burst of its buffer to a new client (40 Hz samples read 1 ms apart), the
    tracker out of the field for 1 s in it: 2 samples were refused and a clock jump of 1.07 s
    taken (review). While the stream drains the bound is MAX_STAMP_LEAD_S; once it is read
    live again, a sample 3 s ahead is refused alone, as before."""
    stamps = [0.025 * k for k in range(200) if not 80 <= k < 120]
    burst = [(s, 0.001 * i) for i, s in enumerate(stamps)]
    jumps = StampJumps()
    assert _feed(jumps, burst) == [] and jumps.jumps == []  # (before: [3.0, 3.025], [1.072])
    assert jumps.draining()
    # then read live for 3 s (arrivals follow the stamps), and one sample 3 s ahead
    t0, a0 = stamps[-1], burst[-1][1]
    live = [(t0 + 0.025 * k, a0 + 0.025 * k) for k in range(1, 121)]
    assert _feed(jumps, live) == [] and not jumps.draining()
    assert jumps.lead_bound() == pytest.approx(igtl.MIN_STAMP_LEAD_S)
    t, a = live[-1]
    assert jumps.check(t + 3.025, a + 0.025) == STAMP_JUMP
    assert _feed(jumps, [(t + 0.05, a + 0.05)]) == [] and jumps.jumps == []
    # a pause beyond MAX_STAMP_LEAD_S in a drain is still a jump
    far = StampJumps()
    gap = [0.025 * k for k in range(80)] + [20.0 + 0.025 * k for k in range(3)]
    assert len(_feed(far, [(s, 0.001 * i) for i, s in enumerate(gap)])) == 2
    assert far.jumps == [pytest.approx((20.05 - 1.975) - 0.003, abs=1e-6)]  # (the third's)


def test_arrivals_in_batches_are_no_drain():
    """A 1 kHz robot whose messages are read in batches of 10 (arrivals 10 ms apart, 10 at
    once) is read live: its bound stays MIN_STAMP_LEAD_S and a sample 3 s ahead is refused."""
    jumps = StampJumps()
    events = [(100.0 + 0.001 * k, 0.01 * (k // 10 + 1)) for k in range(3000)]
    assert _feed(jumps, events) == [] and not jumps.draining()
    assert jumps.lead_bound() == igtl.MIN_STAMP_LEAD_S
    assert jumps.check(100.0 + 3.0 + 3.0, 3.0) == STAMP_JUMP
