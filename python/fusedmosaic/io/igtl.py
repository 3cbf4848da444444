"""Live input over OpenIGTLink: video frames and tracker poses from a PLUS Server (or any
OpenIGTLink sender), as an operating-theatre setup streams them.

`IgtlSource` connects to HOST:PORT and receives, on a background thread, IMAGE messages of one
device (the video) and TRANSFORM or POSITION messages of one device (the tracked sensor, e.g.
PLUS's ``SensorToTracker``: tracker_from_sensor in mm, as ``tracking.csv``; or a robot's probe
position). Messages are decoded with
pyigtl (the OpenIGTLink reference implementation for Python); the socket loop is ours so that a
refused connection, a closed stream or a malformed message is a clear error, not a silent
reconnect.

- Frames: a capture slot of one frame. `next_frame` hands over the newest frame received; frames
  that arrived while the caller was busy are counted as dropped (`dropped`), the live view never
  falls behind. Every frame received goes first to ``on_frame`` (the recorder), which may refuse
  it (returns False: not offered to the loop either).
- Tracker: every TRANSFORM or POSITION sample of the device goes to ``on_sample`` and into a
  history of the last HISTORY_S seconds (at most HISTORY_MAX samples; a POSITION is a position
  and an orientation quaternion: see `position_message_matrix`);
  `pose_at(t)` gives the camera pose at a frame time from it (see there). A sample whose matrix
  is not finite, not a rotation (orthonormal within 1e-3, det +1), beyond
  ``MAX_TRANSLATION_MM``, or flagged by the sender (metadata ``TransformStatus`` not ``OK``, as
  PLUS sends a lost sensor), whose body fails its CRC64 (header field, ECMA-182, as Slicer's
  OpenIGTLinkIF checks), or that pyigtl cannot decode (e.g. metadata in an encoding other than
  ASCII or UTF-8) is kept as an invalid sample: a glitch does not end a session. An IMAGE whose
  body fails its CRC64 is dropped and counted (``corrupted_frames``). The CRC is _core.crc64,
  which releases the GIL: 3.7 ms per 1080p RGB frame on a loaded 2-core machine, the live loop
  running meanwhile. crcmod's C extension, used before, held the GIL (27 ms there, 15 ms on an
  idle one), and at 1080p30 frames arrived a median 150-300 ms late (review). An IMAGE that
  cannot be decoded (e.g. a body shorter than its header's size says) is dropped and counted
  per reason (``undecodable_frames``; one ended the session and lost every later frame); when
  the first UNDECODABLE_LIMIT IMAGEs all fail, none decoded, the session ends naming the device
  and why (the sender's images are not readable at all).
- Other message types (e.g. TDATA, QTDATA, QTRANS) are not read (their bodies are let go
  unbuffered); their devices are listed in ``ignored_devices`` with "(type not read)", as the
  other devices heard are (up to MAX_PROBLEM_KINDS; invalid samples are counted by kind, as
  many kinds). A header declaring more than MAX_BODY_BYTES, or MAX_SMALL_BODY_BYTES for a
  TRANSFORM or POSITION, is a corrupt size: the session ends naming it.
- A transform device named ``BToA`` answers a request for ``AToB`` (inverted). The requested
  name may end in ``Transform`` (the ``.mha`` field name, as ``import --transform`` takes it):
  ``SensorToTrackerTransform`` is device ``SensorToTracker``.
- A device's name is its metadata ``IGTL_DEVICE_NAME`` when a message carries one. PLUS and the
  OpenIGTLink library put a name longer than the header's 20 bytes there, with its first 20 in
  the header. Without it, a header name of 20 bytes is taken as the start of a longer name, so
  it matches a requested name (or its inverse) that begins with it. PLUS's
  ``FetoscopeSensorToTracker`` took no sample before (review). An IMAGE of another device is
  not read, so it is listed under its header name.

Timestamps are the messages' own (the sender's clock, seconds since 1970): frame and tracker
times must come from one clock, as PLUS Server's do.
"""

from __future__ import annotations

import bisect
import errno
import functools
import itertools
import re
import select
import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fusedmosaic import _core
from fusedmosaic.io.tracking import (
    GAP_SPACINGS,
    MAX_TIME_OFFSET_S,
    MAX_TRANSLATION_MM,
    TrackingSamples,
    camera_pose_from_sample,
    interpolate_camera_poses,
    rigid_defects,
    rigid_problems,
    sample_spacing,
)

__all__ = ["IgtlImageServer", "IgtlSource", "LiveFrame", "StreamTimeout", "TrackerSample",
           "extrapolation_base", "format_address", "inverse_device_name", "parse_address",
           "parse_listen_address", "position_message_matrix"]

DEFAULT_PORT = 18944  # the OpenIGTLink port (PLUS Server's default)
# A message body above this is a corrupt header (an 8K RGB frame is 100 MB), not a frame to buffer.
MAX_BODY_BYTES = 512 * 2**20
_BACKWARDS = "timestamp not after the previous sample"
# The first IMAGE messages failing to decode, none decoded, that end a session (the sender's
# images are not readable); fewer, or after a decoded one, are dropped and counted.
UNDECODABLE_LIMIT = 10
_READ = ("IMAGE", "TRANSFORM", "POSITION")
# The header's device name field (bytes): a longer name is cut to it there, and sent whole in
# the metadata under DEVICE_NAME_KEY (header version 2; PLUS, the OpenIGTLink library).
DEVICE_NAME_BYTES = 20
DEVICE_NAME_KEY = "IGTL_DEVICE_NAME"
_CORRUPTED = "CRC64 of the body differs from the header's (corrupted message)"
# A body above this for these types (48 or 12-28 bytes of content, plus the extended header and
# metadata of header version 2: PLUS sends ~100 bytes of it) is a corrupt size field: a
# TRANSFORM declaring 200 MB read the IMAGEs after it as its body, and the session ended with
# "no frame ... in 5 s" while frames were arriving (review).
MAX_SMALL_BODY_BYTES = 64 * 2**10
_SMALL_TYPES = ("TRANSFORM", "POSITION")
_SMALL_PREFIXES = ("GET_", "STT_", "STP_")  # queries, start / stop: empty or a few bytes
# Tracker samples kept for pose_at / position_at: those of the last HISTORY_S seconds, at most
# HISTORY_MAX (~0.4 KB each: 8 MB; 15 s up to 1.3 kHz). A frame takes the sample at its time
# plus the tracker's clock offset (up to MAX_TIME_OFFSET_S either way), and the video lags the
# tracker by its latency: 128 samples were 0.128 s at 1 kHz, and with 200 ms of video latency
# every frame found its samples dropped, told as "none recent enough" (review).
HISTORY_S = MAX_TIME_OFFSET_S + 5.0
HISTORY_MAX = 20_000
_READS_PER_PASS = 16  # IgtlImageServer reads of 64 KB per client and pass (ignored)
_SEND_POLL_S = 0.05  # IgtlImageServer.send tries a client that did not take bytes this often
# IgtlImageServer.send gives a client at most max(send_timeout_s, message bytes / MIN_SEND_RATE)
# for one message, however steadily it takes bytes: a send holds the next message back from
# every client, and a client slower than 1 MB/s cannot follow a live mosaic (a 2000 x 2000
# colour view is 12 MB: 12 s a publication). With the stall rule alone (no byte for
# send_timeout_s) a send lasted size / rate however slow the client (5.4 s for 12 MB to a
# 1.5 MB/s client, still allowed), and for ever for one trickling a byte every 1.9 s (review).
MIN_SEND_RATE = 1e6  # bytes/s
_SPACING_WINDOW = 128  # the newest samples whose typical spacing bounds a sample's age
_BASELINE_WINDOW = 32  # the samples before the newest searched for an extrapolation's base
# A position past the newest sample is extrapolated along the motion since the newest sample
# at least this many typical spacings (sample_spacing) before it: the sample just before, 1 ms
# earlier for a robot reporting in pairs (1 ms then 19 ms), made 1 µm of noise ~19 µm at the
# next frame (review: position error median 6.2 µm, p95 33.3; held 2.7, 6.5).
EXTRAPOLATION_BASELINE_SPACINGS = 0.5
# Distinct invalid-sample kinds (and devices ignored) kept by name; further ones are counted
# together (bounded however long the session, as compositing.live_view's problems).
MAX_PROBLEM_KINDS = 32
OTHER_PROBLEMS = f"other problems (beyond {MAX_PROBLEM_KINDS} kinds)"
MORE_DEVICES = f"more devices heard, not listed (beyond {MAX_PROBLEM_KINDS})"
QUATERNION_NOT_UNIT = "quaternion not of unit norm (within 1e-3)"
# A stamp further ahead of the stream than its lead bound (its step from the last accepted one
# beyond the time between their arrivals) is a glitch, refused: one frame or sample stamped an
# hour ahead was accepted and every later one refused as going back in time (review). The
# bound is the longer of MIN_STAMP_LEAD_S and STAMP_LEAD_SPACINGS typical intervals of the
# stream's recent stamps (sample_spacing), at most MAX_STAMP_LEAD_S: a fixed 10 s let a frame
# stamped 3 s ahead of a 25 fps stream in, and the 75 frames of the next 3 s were refused as
# "timestamp does not increase" (review). A stamp's lead is at most its step from the last
# accepted one (arrivals do not go back): a stream without gaps in its stamps stays within an
# interval or two of lead, even as a backlog drains.
# While a backlog drains (messages queued at the sender or in the socket read faster than real
# time: PLUS Server's burst of its buffered frames to a new client, a receiver catching up),
# arrivals are compressed and any pause in the stamps (an EM sensor out of the field, PLUS's
# SendValidTransformsOnly sending nothing meanwhile; a video freeze) reads as lead: a 1 s pause
# in a 40 Hz burst read 1 ms apart had 2 samples refused and a clock jump taken (review). The
# stream is draining when, over its accepted stamps of the last DRAIN_WINDOW_S, the arrivals
# span less than DRAIN_RATIO of the stamps' span and the receiver gained more than
# MIN_STAMP_LEAD_S on them (a sender whose arrivals come in bursts of a few ms, e.g. a 1 kHz
# robot's, is no drain); the bound is then MAX_STAMP_LEAD_S, a stamp's lead saying nothing of a
# jump until the stream is read live again.
# STAMP_JUMP_CONFIRM such stamps in a row, consistent among themselves, are the sender's clock
# jumping: the last is accepted and the stream goes on from it.
MAX_STAMP_LEAD_S = 10.0
MIN_STAMP_LEAD_S = 0.5
STAMP_LEAD_SPACINGS = 10.0
_STAMP_WINDOW = 32  # the recent accepted stamps whose intervals set the bound
DRAIN_WINDOW_S = 2.0
DRAIN_RATIO = 0.5
_DRAIN_MAX = 4096  # accepted (stamp, arrival) kept for it (a shorter window beyond 2 kHz)
STAMP_JUMP_CONFIRM = 3
STAMP_JUMP = (f"a timestamp jumping ahead of the stream (beyond the time since the last "
              f"accepted one arrived by more than {MIN_STAMP_LEAD_S:g} s or "
              f"{STAMP_LEAD_SPACINGS:g} stamp intervals: a glitch in the sender's stamp?)")


class StampJumps:
    """Refuses stamps that jump ahead of a stream (beyond `lead_bound`); after
    STAMP_JUMP_CONFIRM in a row consistent with each other, takes the jump as the sender's new
    clock. `check` before accepting a stamp later than the last accepted one, `accepted`
    after."""

    def __init__(self) -> None:
        self.last: tuple[float, float] | None = None  # (stamp, arrival) last accepted
        self.pending: list[tuple[float, float]] = []  # jumped ones in a row
        self.jumps: list[float] = []  # the clock jumps taken (s)
        self._back: list[tuple[float, float]] = []  # stamped far behind, in a row
        self.steps_back: list[float] = []  # the clock's steps back seen (s)
        self._recent: deque[float] = deque(maxlen=_STAMP_WINDOW)  # accepted stamps
        # accepted (stamp, arrival) of the last DRAIN_WINDOW_S of stamps
        self._window: deque[tuple[float, float]] = deque(maxlen=_DRAIN_MAX)

    def draining(self) -> bool:
        """Whether the stream is read faster than real time (a backlog draining): over the
        accepted stamps of the last DRAIN_WINDOW_S, the arrivals span less than DRAIN_RATIO of
        the stamps' span, and the receiver gained more than MIN_STAMP_LEAD_S on them."""
        if len(self._window) < 2:
            return False
        stamps = self._window[-1][0] - self._window[0][0]
        arrivals = self._window[-1][1] - self._window[0][1]
        return arrivals < DRAIN_RATIO * stamps and stamps - arrivals > MIN_STAMP_LEAD_S

    def lead_bound(self) -> float:
        """The lead (s) beyond which a stamp is a jump: the longer of MIN_STAMP_LEAD_S and
        STAMP_LEAD_SPACINGS typical intervals of the recent accepted stamps (sample_spacing:
        a sender stamping in pairs or bursts is no faster stream), at most MAX_STAMP_LEAD_S;
        MIN_STAMP_LEAD_S before two stamps; MAX_STAMP_LEAD_S while a backlog drains
        (`draining`: a pause in the stamps is no lead then)."""
        if self.draining():
            return MAX_STAMP_LEAD_S
        if len(self._recent) < 2:
            return MIN_STAMP_LEAD_S
        return min(MAX_STAMP_LEAD_S, max(MIN_STAMP_LEAD_S,
                                         STAMP_LEAD_SPACINGS * sample_spacing(self._recent)))

    def check(self, stamp: float, arrival: float) -> str | None:
        """None: accept (a jump of the clock taken: `jumps` grows), else the refusal."""
        if self.last is None:
            return None
        lead = (stamp - self.last[0]) - (arrival - self.last[1])
        if lead <= MIN_STAMP_LEAD_S or lead <= (bound := self.lead_bound()):
            self.pending.clear()  # (the bound computed only past its floor: 1 kHz samples)
            return None
        if self.pending:
            ps, pa = self.pending[-1]
            if not (stamp > ps and (stamp - ps) - (arrival - pa) <= bound):
                self.pending.clear()
        self.pending.append((stamp, arrival))
        if len(self.pending) < STAMP_JUMP_CONFIRM:
            return STAMP_JUMP
        self.pending.clear()
        self.jumps.append(lead)
        self._recent.clear()  # (the stream's intervals start again on the new clock)
        self._window.clear()
        return None

    def accepted(self, stamp: float, arrival: float) -> None:
        self.last = (stamp, arrival)
        self._recent.append(stamp)
        self._window.append((stamp, arrival))
        while stamp - self._window[0][0] > DRAIN_WINDOW_S:
            self._window.popleft()
        self._back.clear()

    def behind(self, stamp: float, arrival: float) -> float | None:
        """For a stamp refused as not after the last accepted one: the step back (s) of the
        sender's clock when it is the STAMP_JUMP_CONFIRM-th in a row more than MAX_STAMP_LEAD_S
        behind the stream and consistent with the ones before (added to `steps_back`: told
        once per step); else None. Such stamps cannot be taken (a recording is in time order):
        a clock set back ended a session with 'timestamp does not increase' frame after frame
        and nothing said why (review)."""
        if self.last is None:
            return None
        lag = (self.last[0] - stamp) + (arrival - self.last[1])
        if lag <= MAX_STAMP_LEAD_S:
            self._back.clear()
            return None
        if self._back:
            ps, pa = self._back[-1]
            if not (stamp > ps and abs((stamp - ps) - (arrival - pa)) <= MAX_STAMP_LEAD_S):
                self._back.clear()
        self._back.append((stamp, arrival))
        if len(self._back) != STAMP_JUMP_CONFIRM:
            return None
        self.steps_back.append(lag)
        return lag


def _split_address(address: str, what: str) -> tuple[str, str | None]:
    """'HOST:PORT', '[IPV6]:PORT', 'HOST' or '[IPV6]' -> (host, port text or None); an IPv6
    address without brackets is refused (its last ':' would be taken for the port's)."""
    text = str(address)
    if text.startswith("["):
        host, bracket, rest = text[1:].partition("]")
        if not bracket or not host or (rest and not rest.startswith(":")):
            raise ValueError(f"{what} {address!r}: expected [IPV6]:PORT, e.g. [::1]:18944")
        return host, rest[1:] if rest else None
    if text.count(":") > 1:
        raise ValueError(f"{what} {address!r}: an IPv6 address goes in brackets: "
                         f"[ADDRESS]:PORT, e.g. [::1]:{DEFAULT_PORT}")
    host, sep, port = text.rpartition(":")
    return (host, port) if sep else (text, None)


def format_address(host: str, port: int) -> str:
    """'HOST:PORT', an IPv6 host in brackets ('[::1]:18944'), as parse_address reads it."""
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def _port(text: str | None, low: int) -> int:
    try:
        number = int(text)
    except (TypeError, ValueError):
        return -1
    return number if low <= number < 65536 else -1


def parse_address(address: str) -> tuple[str, int]:
    """'HOST:PORT', 'HOST' (port 18944), ':PORT' (localhost), '[IPV6]:PORT' or '[IPV6]' ->
    (host, port); ValueError."""
    what = "OpenIGTLink address"
    host, port = _split_address(address, what)
    number = DEFAULT_PORT if port is None else _port(port, 1)
    if number < 0:
        raise ValueError(f"{what} {address!r}: expected HOST:PORT with a port in 1..65535")
    return host or "127.0.0.1", number


class StreamTimeout(ValueError):
    """No frame arrived in the time given to next_frame."""


def inverse_device_name(name: str, where: str = "OpenIGTLink") -> str:
    """PLUS names a transform device <From>To<To>: 'ToolToTracker' -> 'TrackerToTool' (the
    'To' that splits is the one before a capital or digit, after at least one character)."""
    names = re.fullmatch(r"(.+?)To([A-Z0-9].*)", name or "")
    if names is None:
        raise ValueError(f"{where}: transform device {name!r} should be named like PLUS's "
                         f"<From>To<To> devices, e.g. SensorToTracker")
    return f"{names[2]}To{names[1]}"


@dataclass
class LiveFrame:
    """A received frame: image (H, W) or (H, W, 3) BGR (alpha dropped), uint8 or uint16 as
    sent (checked by the caller; run_igtl records it so and mosaics 16-bit ones in 8 bits),
    timestamp (s, the sender's), arrival (time.perf_counter() at receipt), index (0-based count
    of frames received from the device; on_frame may renumber it, e.g. to the recording's frame
    id, and `dropped` lists these numbers)."""

    image: np.ndarray
    timestamp: float
    arrival: float
    index: int


@dataclass
class TrackerSample:
    """A TRANSFORM or POSITION sample: tracker_from_sensor (4, 4) in mm, timestamp (s), valid,
    and why not."""

    timestamp: float
    matrix: np.ndarray
    valid: bool
    problem: str | None = None


class IgtlSource:
    """OpenIGTLink client for a live session; a context manager (closes the connection).

    image_device: IMAGE device name (None: the first image device heard; others are ignored and
    listed in `ignored_devices`). transform_device: TRANSFORM device of the tracked sensor (its
    inverse name is accepted, see the module docstring); None: no samples are taken (images
    alone, e.g. live ncc), every TRANSFORM / POSITION heard is listed in `ignored_devices`.
    rgb: colour images are sent RGB (PLUS) and are converted to BGR. connect_timeout_s: for
    the TCP connection.
    orientation_required: a POSITION of 12 bytes (a position alone) is an invalid sample (a
    tracker's pose needs its orientation; a robot's probe position does not: False)."""

    def __init__(self, address: str, *, transform_device: str | None,
                 image_device: str | None = None,
                 rgb: bool = True, connect_timeout_s: float = 5.0,
                 orientation_required: bool = True,
                 on_frame: Callable[[LiveFrame], None] | None = None,
                 on_sample: Callable[[TrackerSample], None] | None = None) -> None:
        import pyigtl  # noqa: F401  (fail early, naming the package, if it is missing)

        self.host, self.port = parse_address(address)
        self.where = f"OpenIGTLink {format_address(self.host, self.port)}"
        # (the .mha field name, as import takes it: its device is the name without the suffix)
        # the name as given and, for 'XToYTransform' (the .mha field name, as import takes it),
        # 'XToY' too: a device really named '...Transform' (Slicer names devices after its
        # transform nodes) stays reachable (review Z); the inverse of each
        self.transform_device = transform_device
        self._devices = _device_names(transform_device)
        self._inverse_devices = tuple(inverse_device_name(name, self.where)
                                      for name in self._devices)
        self.image_device = image_device
        self.rgb = rgb
        self.orientation_required = orientation_required
        self.on_frame, self.on_sample = on_frame, on_sample
        self.received = 0  # frames received from the image device
        self.valid_samples = 0
        self._synchronous, self._pose_calls = False, 0
        self.dropped: list[int] = []  # indices of frames replaced in the slot before being taken
        self.corrupted_frames = 0  # IMAGE messages of the image device failing their CRC64
        self.undecodable_frames: dict[str, int] = {}  # why -> IMAGE messages not decoded
        # (always: _core.crc64 releases the GIL; crcmod's pure-Python CRC, 66 ms per 400x400
        # RGB frame, left frames unchecked without its C extension)
        self.frames_crc_checked = True
        self.invalid_samples: dict[str, int] = {}  # problem (its kind) -> count
        self.invalid_sample_details: dict[str, str] = {}  # problem -> the first one's figures
        self._last_sample_time: float | None = None
        self._sample_jumps = StampJumps()  # samples stamped far ahead of the stream
        self.ignored_devices: set[str] = set()  # (at most MAX_PROBLEM_KINDS, then MORE_DEVICES)
        # valid samples in time order: the last HISTORY_S s, at most HISTORY_MAX
        self.samples: deque[TrackerSample] = deque()
        self._first_dropped: float | None = None  # stamp of the first sample dropped from it
        self.history_misses = 0  # frames whose samples had been dropped from the history
        self._receiving: tuple[str, str, int, int] | None = None  # a message partly received
        self._slot: LiveFrame | None = None
        self._cond = threading.Condition()
        self._closed = False
        self._error: BaseException | None = None
        self._stop = False
        try:
            self._socket = socket.create_connection((self.host, self.port),
                                                    timeout=connect_timeout_s)
        except OSError as exc:
            raise ValueError(f"{self.where}: cannot connect ({exc.strerror or exc}); is the "
                             f"sender (e.g. PLUS Server) running and listening there?") from None
        self._socket.settimeout(0.2)
        self._thread = threading.Thread(target=self._receive_loop, name="igtl-receive",
                                        daemon=True)
        self._thread.start()

    @property
    def sample_clock_jumps(self) -> list[float]:
        """The jumps (s) of the samples' clock taken (StampJumps: STAMP_JUMP_CONFIRM samples
        in a row stamped consistently far ahead of the stream; those before were refused)."""
        return list(self._sample_jumps.jumps)

    @property
    def sample_clock_steps_back(self) -> list[float]:
        """The steps back (s) of the samples' clock seen (StampJumps.behind): every sample
        after one is refused as going back in time."""
        return list(self._sample_jumps.steps_back)

    # ------------------------------------------------------------------ consumer side
    def next_frame(self, timeout_s: float) -> LiveFrame | None:
        """The newest frame not yet taken, waiting up to timeout_s; None when the stream has
        ended (the sender closed the connection) with no frame left. ValueError when nothing
        arrives in time, or when the receiver failed (malformed message, a reset connection,
        callback error) with no frame left: a frame received before the failure is handed over
        first."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._slot is None and not self._closed and self._error is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    what = (f"IMAGE device {self.image_device}" if self.image_device
                            else "any IMAGE device")
                    raise StreamTimeout(f"{self.where}: no frame from {what} in "
                                        f"{timeout_s:g} s{self._partly_received()}")
                self._cond.wait(left)
            if self._slot is None and self._error is not None:
                raise ValueError(f"{self.where}: {self._error}") from self._error
            frame, self._slot = self._slot, None
            return frame

    def _partly_received(self) -> str:
        """' (inside a ... message: k of n bytes received)' while the receiver is inside a
        message, else '': a sender stalled halfway, or a corrupt size swallowing the stream,
        was told as silence (review)."""
        receiving = self._receiving  # (set by the receiver thread: read once)
        if receiving is None:
            return ""
        kind, device, got, size = receiving
        what = f"a {kind} message of {device!r}" if kind else "a message header"
        return (f" (inside {what}: {_bytes_text(got)} of {_bytes_text(size)} received; a "
                f"sender stalled mid-message, or a corrupt size in its header?)")

    @property
    def history_text(self) -> str:
        """What the sample history keeps, for a frame whose samples were dropped from it."""
        return (f"the samples of the last {HISTORY_S:g} s are kept, at most {HISTORY_MAX}: "
                "the frames lag the tracker's stamps by more than that (video latency or a "
                "clock offset), or it sends faster")

    def pose_at(self, t: float, hand_eye=None, *, max_age_s: float | None = None,
                wait_s: float = 0.01) -> tuple[np.ndarray | None, float | None]:
        """Camera pose cam_from_world (6,) at frame time t through the hand-eye, and the age
        (s) of the newest sample at or before t; (None, age or None) when there is no usable
        sample (see `_around` for the samples used and the wait). With valid samples on both
        sides of t, SLERP + linear interpolation between them (as offline), else the newest one
        at or before t, held."""
        found = self._around(t, max_age_s, wait_s)
        if found[0] is None:
            return None, found[1]
        pair, age = found
        if len(pair) == 1:  # no sample after t yet (or a gap): the newest one, held
            held = pair[0]
            return camera_pose_from_sample(held.matrix[:3, 3], _quaternion(held.matrix),
                                           hand_eye), age
        samples = TrackingSamples([s.timestamp for s in pair],
                                  np.array([s.matrix[:3, 3] for s in pair]),
                                  np.array([_quaternion(s.matrix) for s in pair]))
        poses, _ = interpolate_camera_poses(samples, [t], hand_eye, max_gap=np.inf,
                                            source=self.where)
        return poses[0], age

    def position_at(self, t: float, *, max_age_s: float | None = None,
                    wait_s: float = 0.01) -> tuple[np.ndarray | None, float | None]:
        """The transform's translation (3,) (mm) at frame time t, and the age of the newest
        sample at or before t (a robot reporting the probe position: kalman-robot). Linear
        between the samples around t; past the newest sample, extrapolated along the motion
        since the newest sample at least EXTRAPOLATION_BASELINE_SPACINGS typical spacings
        before it (an accurate robot's sample held 14 ms lags the probe, and the filter,
        trusting the robot, follows the lag: see estimation.live.extrapolated_robot); held
        when there is none within max_age_s, or one sample."""
        found = self._around(t, max_age_s, wait_s, extrapolate=True)
        if found[0] is None:
            return None, found[1]
        pair, age = found
        if len(pair) == 1:
            return pair[0].matrix[:3, 3].copy(), age
        (t0, p0), (t1, p1) = ((s.timestamp, s.matrix[:3, 3]) for s in pair)
        return p0 + (p1 - p0) * ((t - t0) / (t1 - t0)), age

    def _around(self, t: float, max_age_s: float | None, wait_s: float,
                extrapolate: bool = False) -> tuple[list | None, float | None]:
        """The samples to evaluate at frame time t: [before, after] around it, [newest] at or
        before it (with extrapolate: [base, newest], base the newest sample at least
        EXTRAPOLATION_BASELINE_SPACINGS typical spacings older, when it is within max_age_s),
        or (None, age or None) when the newest one at or before t is missing or older than
        max_age_s (None: 3 x the typical spacing of the recent samples,
        io.tracking.sample_spacing: a robot reporting in pairs or bursts is no dropout); a
        time whose samples were dropped from the history (HISTORY_S) is counted in
        `history_misses`. With a frame-synchronous sender (PLUS Server sends a frame's
        transform and image with one timestamp, in either order: seen once a sample's time
        equals a frame's) and during the first 5 frames, waits up to wait_s for a sample at or
        after t; a free-running tracker's next sample is not waited for (up to a sample period
        of latency for little gain)."""
        wait = wait_s if (self._synchronous or self._pose_calls < 5) else 0.0
        self._pose_calls += 1
        deadline = time.monotonic() + wait
        with self._cond:
            while (not self._closed and self._error is None
                   and not (self.samples and self.samples[-1].timestamp >= t)):
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(left)
            if not self.samples:
                return None, None
            # (a bisection on the deque: the history holds up to HISTORY_MAX samples, and a
            # copy of it per frame cost ~1 ms at 15 000)
            before = bisect.bisect_right(self.samples, t, key=_stamp) - 1
            if before < 0:
                if self._first_dropped is not None and self._first_dropped <= t:
                    self.history_misses += 1  # (its time's samples were kept once)
                return None, None
            low = max(0, before - _BASELINE_WINDOW)
            near = [self.samples[i] for i in range(low, min(len(self.samples), before + 2))]
            recent = np.array([s.timestamp for s in itertools.islice(reversed(self.samples),
                                                                     _SPACING_WINDOW)])[::-1]
        before -= low
        times = np.array([s.timestamp for s in near])
        if times[before] == t:
            self._synchronous = True
        spacing = sample_spacing(recent) if recent.size > 1 else 0.0
        if max_age_s is None:
            max_age_s = GAP_SPACINGS * spacing if recent.size > 1 else np.inf
        age = t - times[before]
        if age > max_age_s:
            return None, age
        after = before + 1
        if times[before] == t:
            return [near[before]], age
        if after < times.size:
            if times[after] - times[before] <= max_age_s:
                return [near[before], near[after]], age
            return [near[before]], age
        base = extrapolation_base(times, before, spacing) if extrapolate else None
        if base is not None and times[before] - times[base] <= max_age_s:
            return [near[base], near[before]], age
        return [near[before]], age

    def close(self) -> None:
        self._stop = True
        self._thread.join(timeout=2.0)
        self._socket.close()

    def __enter__(self) -> IgtlSource:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ receiver thread
    def _receive_loop(self) -> None:
        from pyigtl import MessageBase

        try:
            while not self._stop:
                header = self._recv_exact(MessageBase.IGTL_HEADER_SIZE)
                if header is None:
                    break
                try:
                    fields = MessageBase.parse_header(header)
                except (UnicodeDecodeError, ValueError) as exc:
                    raise ValueError(f"malformed OpenIGTLink header (type and device name are "
                                     f"not text: {exc})") from None
                kind, device, size = (fields["message_type"], fields["device_name"],
                                      fields["body_size"])
                limit = (MAX_SMALL_BODY_BYTES if kind in _SMALL_TYPES
                         or kind.startswith(_SMALL_PREFIXES) else MAX_BODY_BYTES)
                if size > limit:
                    small = " for its type" if limit < MAX_BODY_BYTES else ""
                    raise ValueError(
                        f"malformed OpenIGTLink header: a {kind} message of {size} bytes "
                        f"(more than {limit} bytes{small}): a corrupt size field, the stream "
                        "cannot be followed past it")
                # (the bodies of messages not read are received and let go, not buffered)
                read = kind in _READ and not (kind == "IMAGE" and self.image_device is not None
                                              and not _is_device(device, None,
                                                                 self.image_device))
                body = self._recv_exact(size, (kind, device), keep=read)
                if body is None and size and not self._stop:
                    # (a sender dying right after a header was told as a normal close)
                    raise ConnectionError(
                        f"the connection closed inside a message (after the header of a "
                        f"message of type {kind}, none of its {size} body bytes)")
                if body is None:
                    break
                crc = struct.unpack(">Q", header[-8:])[0]
                if kind == "IMAGE":
                    self._on_image(fields, body, device, crc)
                elif kind in _READ:
                    self._on_transform(fields, body, device, crc)
                elif kind:
                    self._ignore(f"{kind} {device} (type not read)")
        except BaseException as exc:  # reported to the consumer, which raises it
            with self._cond:
                self._error = exc
                self._cond.notify_all()
            return
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def _recv_exact(self, size: int, message: tuple[str, str] | None = None,
                    keep: bool = True) -> bytes | None:
        """size bytes, or None when the connection ended (or close() was called) cleanly
        between messages; a connection ending inside a message is an error. message: (type,
        device) of the body received (None: a header), told while it is partly received
        (`_partly_received`); keep False: the bytes are let go (b'' returned)."""
        chunks, got = [], 0
        kind, device = message or ("", "")
        while got < size:
            if self._stop:
                return None
            if got or message is not None:
                self._receiving = (kind, device, got, size)
            try:
                chunk = self._socket.recv(min(size - got, 1 << 20))
            except TimeoutError:
                continue
            if not chunk:
                if got:
                    raise ConnectionError(f"the connection closed inside a message ({got} of "
                                          f"{size} bytes)")
                return None
            if keep:
                chunks.append(chunk)
            got += len(chunk)
        self._receiving = None
        return b"".join(chunks)

    def _direction(self, device: str, full: str | None) -> bool | None:
        """For a TRANSFORM or POSITION of header name `device` and metadata name `full`
        (None: none; see _is_device): False when it is the transform device, True when it is
        its inverse, None when neither (or no transform device is asked for)."""
        if self.transform_device is None:
            return None
        if any(_is_device(device, full, name) for name in self._devices):
            return False
        return True if any(_is_device(device, full, name)
                           for name in self._inverse_devices) else None

    def _ignore(self, device: str) -> None:
        """Lists a device heard and not read in `ignored_devices`, up to MAX_PROBLEM_KINDS
        (then MORE_DEVICES: every name heard was kept, without bound; review)."""
        if device not in self.ignored_devices:
            self.ignored_devices.add(device if len(self.ignored_devices) < MAX_PROBLEM_KINDS
                                     else MORE_DEVICES)

    def _keep(self, sample: TrackerSample) -> None:
        """Adds a valid sample (later than those kept) to the history, dropping those older
        than HISTORY_S before it or beyond HISTORY_MAX (under self._cond)."""
        self.samples.append(sample)
        oldest = sample.timestamp - HISTORY_S
        while self.samples[0].timestamp < oldest or len(self.samples) > HISTORY_MAX:
            dropped = self.samples.popleft()
            if self._first_dropped is None:
                self._first_dropped = dropped.timestamp

    def _on_image(self, fields: dict, body: bytes, device: str, crc: int) -> None:
        from pyigtl import ImageMessage

        if self.image_device is not None and not _is_device(device, None, self.image_device):
            self._ignore(f"IMAGE {device}")  # (its body was not read: the header's name)
            return
        if _core.crc64(body) != crc:
            self.corrupted_frames += 1  # (a lost frame, as a dropped one: the session goes on)
            return
        message = ImageMessage()
        problem = _unpack(message, fields, body)
        full = None if problem is not None else _full_name(message)
        if self.image_device is None:
            self.image_device = full or device
        elif full and full != self.image_device:  # another name sharing the header's 20 bytes
            self._ignore(f"IMAGE {full}")
            return
        device = full or device
        if fields["timestamp"] == 0 and self.received == 0:  # the spec's "unused"
            raise ValueError(f"the IMAGE messages of {device!r} carry no timestamp (0): frame "
                             "and tracker times must come from the sender's clock")
        # (one unstamped frame after stamped ones goes on, stamped 0: the caller refuses and
        # counts it, run_igtl's on_frame as 'no timestamp (0)'; it ended the session)
        if problem is not None:
            failed = sum(self.undecodable_frames.values()) + 1
            if self.received == 0 and failed >= UNDECODABLE_LIMIT:
                raise ValueError(f"the IMAGE messages of {device!r} cannot be decoded (the "
                                 f"first {failed}, none decoded): {problem}")
            _count(self.undecodable_frames, problem)
            return  # (a lost frame, as a corrupted one: the session goes on)
        image = _frame_image(message.image, self.rgb)
        frame = LiveFrame(image, float(fields["timestamp"]), time.perf_counter(), self.received)
        self.received += 1
        if self.on_frame is not None and self.on_frame(frame) is False:
            return  # refused by the caller (e.g. a frame of the wrong size): not offered
        with self._cond:
            if self._slot is not None:
                self.dropped.append(self._slot.index)
            self._slot = frame
            self._cond.notify_all()

    def _on_transform(self, fields: dict, body: bytes, device: str, crc: int) -> None:
        from pyigtl import TransformMessage

        kind = fields["message_type"]
        message = TransformMessage() if kind == "TRANSFORM" else _position_message_type()()
        # (decoded before its device is known: a name longer than the header's
        # DEVICE_NAME_BYTES is whole in the metadata only)
        corrupted = _core.crc64(body) != crc
        undecodable = None if corrupted else _unpack(message, fields, body)
        full = None if corrupted or undecodable is not None else _full_name(message)
        inverse = self._direction(device, full)
        if inverse is None:
            self._ignore(f"{kind} {full or device}")
            return
        problem = (_CORRUPTED if corrupted else
                   "no timestamp (0): the sender does not stamp its samples"
                   if fields["timestamp"] == 0 else undecodable)
        detail = None  # the figures of this sample's problem (not in its kind: counted by it)
        if problem is not None:
            matrix = np.full((4, 4), np.nan)
            if (size := re.fullmatch(r"(.*) \((body of \d+ bytes)\)", problem)) is not None:
                problem, detail = size[1], size[2]
        elif kind == "TRANSFORM":
            matrix = np.asarray(message.matrix, dtype=np.float64)
        else:
            matrix, problem, detail = _position_pose(message.content)
            if problem == QUATERNION_NOT_UNIT and not self.orientation_required:
                # a robot's probe position (kalman-robot, robot, ncc --transform: the
                # translation alone): its position stands, the orientation is not used (review:
                # a bad quaternion voided it)
                matrix = np.eye(4)
                matrix[:3, 3] = struct.unpack(">3f", message.content[:12])
                problem = detail = None
            if problem is None and len(message.content) == 12 and self.orientation_required:
                problem = "POSITION without an orientation (a 6-DoF pose is needed)"
        if problem is None:
            status = str(message.metadata.get("TransformStatus", "OK"))
            problem = _rigid_problem(matrix) if status.upper() == "OK" else f"status {status}"
        if problem is None and inverse:
            matrix = np.linalg.inv(matrix)
        sample = TrackerSample(float(fields["timestamp"]), matrix, problem is None, problem)
        # (one going back in time, jumping ahead of the stream, or without a time, is not
        # recorded: tracking.csv is in order)
        unrecorded = fields["timestamp"] == 0
        arrival = time.perf_counter()
        with self._cond:
            if self._last_sample_time is not None and sample.timestamp <= self._last_sample_time:
                sample.valid, sample.problem = False, sample.problem or _BACKWARDS
                unrecorded = True
                self._sample_jumps.behind(sample.timestamp, arrival)  # (steps_back)
            elif not unrecorded and (jump := self._sample_jumps.check(sample.timestamp,
                                                                      arrival)) is not None:
                sample.valid, sample.problem = False, jump
                unrecorded = True
            elif not unrecorded:
                self._last_sample_time = sample.timestamp
                self._sample_jumps.accepted(sample.timestamp, arrival)
            if not sample.valid:
                why = _count(self.invalid_samples, sample.problem)
                if detail is not None and why == sample.problem:
                    self.invalid_sample_details.setdefault(why, detail)
            else:
                self._keep(sample)
                self.valid_samples += 1
            self._cond.notify_all()
        if self.on_sample is not None and not unrecorded:
            self.on_sample(sample)  # invalid ones too: the recording keeps the dropout


def _device_names(name: str | None) -> tuple[str, ...]:
    """The devices a requested transform device names: itself and, for
    'SensorToTrackerTransform' (the .mha field name, as import's --transform takes it:
    io.plus._transform_field), 'SensorToTracker', PLUS's device of that field; () for None."""
    if name is None:
        return ()
    suffix = "Transform"
    if name.endswith(suffix) and len(name) > len(suffix):
        stripped = name[:-len(suffix)]
        try:  # (a stripped name that is no <From>To<To> is not PLUS's)
            inverse_device_name(stripped)
        except ValueError:
            return (name,)
        return (name, stripped)
    return (name,)


def _full_name(message) -> str | None:
    """A decoded message's DEVICE_NAME_KEY metadata (its whole device name), None without."""
    name = message.metadata.get(DEVICE_NAME_KEY)
    return str(name) if name else None


def _is_device(header: str, full: str | None, name: str) -> bool:
    """Whether a message is device `name`: by its metadata name `full` when it has one (None:
    none, or not decoded), else by its header name, which is `name` or, when it fills the
    header's DEVICE_NAME_BYTES, the start of `name` (cut there)."""
    if full:
        return full == name
    return header == name or (len(header.encode()) == DEVICE_NAME_BYTES
                              and name.startswith(header))


def _count(counts: dict[str, int], kind: str) -> str:
    """Counts one of `kind` in counts (kind -> count), under OTHER_PROBLEMS once
    MAX_PROBLEM_KINDS kinds are there; returns the key counted."""
    if kind not in counts and len(counts) >= MAX_PROBLEM_KINDS:
        kind = OTHER_PROBLEMS
    counts[kind] = counts.get(kind, 0) + 1
    return kind


def _stamp(sample: TrackerSample) -> float:
    return sample.timestamp


def extrapolation_base(times, i: int, spacing: float) -> int | None:
    """The index of the sample to extrapolate sample i's motion from (``times`` increasing):
    the newest one at least EXTRAPOLATION_BASELINE_SPACINGS x ``spacing`` (the samples'
    typical spacing, io.tracking.sample_spacing) before it; None when there is none (held)."""
    if i <= 0:
        return None
    times = np.asarray(times, dtype=np.float64)
    j = int(np.searchsorted(times[:i], times[i] - EXTRAPOLATION_BASELINE_SPACINGS * spacing,
                            side="right")) - 1
    return j if j >= 0 else None


def _bytes_text(n: int) -> str:
    """'58 bytes', '3.1 MB': a size for a message."""
    return (f"{n} bytes" if n < 10**4 else f"{n / 1e3:.3g} KB" if n < 10**6 else
            f"{n / 1e6:.3g} MB")


def _unpack(message, fields: dict, body: bytes) -> str | None:
    """Decodes body into the pyigtl message; None, or why it cannot be decoded."""
    try:
        message.unpack(fields, body)
    except TypeError as exc:
        if "derive from BaseException" in str(exc):  # pyigtl's raise("Unsupported encoding")
            return "its metadata is in a text encoding other than ASCII or UTF-8"
        return f"{type(exc).__name__}: {exc}"
    except (ValueError, KeyError, IndexError, struct.error, NotImplementedError,
            UnicodeDecodeError) as exc:
        what = f"unknown value {exc}" if isinstance(exc, KeyError) else str(exc)
        return f"{type(exc).__name__}: {what} (body of {len(body)} bytes)"
    return None


# OpenIGTLink POSITION content: x, y, z (mm), then the orientation quaternion ox, oy, oz, w,
# big-endian float32; 12 bytes (position only), 24 (w implied by the unit norm) or 28.
_POSITION_SIZES = (12, 24, 28)


def position_message_matrix(content: bytes) -> tuple[np.ndarray, str | None]:
    """The 4x4 pose of a POSITION message's content (identity rotation when it carries no
    quaternion) and, for an unusable one, why (the sample is then kept as invalid): a size
    other than 12, 24 or 28 bytes, values not finite, a quaternion not of unit norm (within
    1e-3; float32 on the wire: QUATERNION_NOT_UNIT). pyigtl's PositionMessage reads another,
    multi-point layout."""
    matrix, problem, _ = _position_pose(content)
    return matrix, problem


def _position_pose(content: bytes) -> tuple[np.ndarray, str | None, str | None]:
    """position_message_matrix, and the figures of its problem (the quaternion's norm): not
    in the problem, which IgtlSource counts samples by (one key per norm seen grew without
    bound; review)."""
    n = len(content)
    if n not in _POSITION_SIZES:
        return np.eye(4), f"POSITION content of {n} bytes (expected 12, 24 or 28)", None
    values = np.array(struct.unpack(f">{n // 4}f", content), dtype=np.float64)
    if not np.all(np.isfinite(values)):
        return np.eye(4), "not finite", None
    matrix = np.eye(4)
    matrix[:3, 3] = values[:3]
    if n == 12:
        return matrix, None, None
    q = values[3:]
    if n == 24:
        q = np.append(q, np.sqrt(max(0.0, 1.0 - float(q @ q))))
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > 1e-3:
        return np.eye(4), QUATERNION_NOT_UNIT, f"norm {norm:.4g}"
    from scipy.spatial.transform import Rotation

    matrix[:3, :3] = Rotation.from_quat(q / norm).as_matrix()
    return matrix, None, None


@functools.cache
def _position_message_type() -> type:
    """A pyigtl message keeping a POSITION's raw content (pyigtl parses the header, the
    extended header and the metadata; position_message_matrix the content)."""
    from pyigtl import MessageBase

    class _PositionContent(MessageBase):
        def _unpack_content(self, content: bytes) -> None:
            self.content = bytes(content)

    return _PositionContent


def _frame_image(image: np.ndarray, rgb: bool) -> np.ndarray:
    """An IMAGE message's (1, H, W[, C]) array as the (H, W) gray or (H, W, 3) BGR frame the
    mosaickers take (alpha dropped), in the machine's byte order; other layouts are returned
    as they are for the caller's checks to name."""
    image = np.asarray(image)
    # (pyigtl keeps the message's byte order: a 16-bit IMAGE sent big-endian, as the spec
    # allows, was a '>u2' array, refused as "expected ... uint16" frame after frame; review)
    image = image.astype(image.dtype.newbyteorder("="), copy=False)
    if image.ndim >= 3 and image.shape[0] == 1:
        image = image[0]
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 4:
        image = image[:, :, :3]
    if image.ndim == 3 and image.shape[2] == 3 and rgb:
        image = image[:, :, ::-1]
    return np.ascontiguousarray(image)


def _rigid_problem(matrix: np.ndarray) -> str | None:
    """Why a TRANSFORM's 4x4 (float32 on the wire: rigid to 1e-3) is not a usable sample."""
    not_finite, not_rigid, far = rigid_problems(matrix, 1e-3)
    if not_finite[0]:
        return "not a finite 4x4 matrix"
    if not_rigid[0]:
        return f"not rigid: {rigid_defects(matrix, 1e-3, brief=True)}"
    if far[0]:
        return f"translation beyond {MAX_TRANSLATION_MM:g} mm"
    return None


def _quaternion(matrix: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(matrix[:3, :3]).as_quat()


def parse_listen_address(address: str) -> tuple[str, int]:
    """'PORT' (this machine only: 127.0.0.1), 'HOST:PORT' (e.g. 0.0.0.0:18945 for every
    interface) or '[IPV6]:PORT' ([::1]:18945, [::]:18945) -> (host, port); port 0 takes a free
    one (IgtlImageServer.port); ValueError."""
    what = "OpenIGTLink server address"
    text = str(address)
    if ":" in text or text.startswith("["):
        host, port = _split_address(text, what)
    else:
        host, port = "127.0.0.1", text
    number = _port(port, 0)
    if number < 0 or not host:
        raise ValueError(f"{what} {address!r}: expected PORT, HOST:PORT or [IPV6]:PORT with a "
                         f"port in 0..65535 (0: a free one)")
    return host, number


def mosaic_ijk_to_world(origin_reference_px, scale: float = 1.0,
                        pixel_size_mm: float | None = None) -> np.ndarray:
    """4x4 ijk -> world (mm) matrix of a mosaic image for OpenIGTLink (pyigtl's ImageMessage
    ``ijk_to_world_matrix``): i the column, j the row, k the slice, each index the CENTRE of its
    pixel, as pyigtl packs it (it sends the image's centre, ijk ((n - 1) / 2), and its axes
    times the spacing, as the OpenIGTLink IMAGE header holds them).

    origin_reference_px: (x, y) of the image's pixel (0, 0) in the reference's pixels (frame
    0's grid, the homographies'; mosaic.png's ``origin_reference_px``); scale: image pixels per
    reference pixel; pixel_size_mm: the size of a reference pixel on the tissue (pCLE:
    ``pixel_size_um`` / 1000), None: 1 mm. World = the reference's pixel axes (x right, y
    down, unrotated, as the image's before) times pixel_size_mm, its origin frame 0's pixel
    (0, 0): a reference pixel keeps its world point however the mosaic's canvas grows, and
    images at different origins and scales overlay."""
    mm = 1.0 if pixel_size_mm is None else float(pixel_size_mm)
    if not (np.isfinite(mm) and mm > 0):
        raise ValueError(f"pixel_size_mm must be a number > 0, got {pixel_size_mm}")
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a number > 0, got {scale}")
    x, y = (float(v) for v in origin_reference_px)
    step = mm / float(scale)  # mm per image pixel
    return np.array([[step, 0.0, 0.0, x * mm], [0.0, step, 0.0, y * mm],
                     [0.0, 0.0, step, 0.0], [0.0, 0.0, 0.0, 1.0]])


def igtl_image_message(image: np.ndarray, *, device_name: str, timestamp: float,
                  ijk_to_world: np.ndarray | None = None):
    """The pyigtl ImageMessage of what IgtlImageServer.send sends (igtl_image_bytes packs it):
    a uint8 BGR (H, W, 3) image as RGB (as PLUS and Slicer expect colour) or a gray (H, W)
    one, one slice; ijk_to_world: a 4x4 ijk -> world (mm) matrix (see mosaic_ijk_to_world),
    None the identity (pyigtl's default: pixel (0, 0) at the origin, 1 mm spacing)."""
    import pyigtl

    image = np.asarray(image)
    if image.ndim == 3:
        image = image[:, :, ::-1]  # BGR -> RGB
    ijk_to_world = None if ijk_to_world is None else _ijk_to_world(ijk_to_world)
    return pyigtl.ImageMessage(np.ascontiguousarray(image)[None], ijk_to_world_matrix=ijk_to_world,
                               timestamp=timestamp, device_name=device_name)


def _ijk_to_world(matrix) -> np.ndarray:
    matrix = np.asarray(matrix, np.float64)
    if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
        raise ValueError(f"ijk_to_world must be a finite 4x4 matrix, got shape {matrix.shape}")
    return matrix


# OpenIGTLink IMAGE scalar types (the content header's S field), as pyigtl's
_IMAGE_SCALAR_TYPES = {np.dtype(t): code for t, code in (
    (np.int8, 2), (np.uint8, 3), (np.int16, 4), (np.uint16, 5), (np.int32, 6), (np.uint32, 7),
    (np.float32, 10), (np.float64, 11))}
_HEADER = struct.Struct(">H12s20sIIQQ")  # version, type, device name, time, body size, CRC64
# IMAGE content (version 1): version, components, scalar type, endianness (2: little),
# coordinates (2: LPS, pyigtl's default), size i j k, the i j k axes (times the spacing) and
# the image's centre (12 float32), the subvolume's start i j k and size i j k
_IMAGE_HEADER = struct.Struct(">HBBBBHHH12f6H")


def igtl_image_bytes(image: np.ndarray, *, device_name: str, timestamp: float,
                     ijk_to_world: np.ndarray | None = None) -> np.ndarray:
    """The OpenIGTLink IMAGE message of igtl_image_message(...) (same arguments) as a uint8
    array: pyigtl's pack() but for the timestamp's fraction of a second (here the nearest
    2**-32 s, pyigtl's within 1 ns of it). Packed here with one copy of the pixels (cv2 /
    numpy) and _core.crc64, both releasing the GIL. pyigtl copied the pixels four times and
    computed the CRC with crcmod, holding the GIL (review). For a 50 Mpixel colour mosaic on
    a loaded 2-core machine, pyigtl took 1.3-1.7 s and allocated 448 MB, and another thread
    (the live loop) waited up to 0.6 s; here 0.17-0.24 s, 149 MB, and 14 ms."""
    image = np.asarray(image)
    matrix = np.eye(4) if ijk_to_world is None else _ijk_to_world(ijk_to_world)
    if image.ndim not in (2, 3) or image.dtype not in _IMAGE_SCALAR_TYPES:
        raise ValueError(f"an IMAGE message holds a (rows x columns[ x components]) array of "
                         f"{', '.join(map(str, _IMAGE_SCALAR_TYPES))}, got "
                         f"{image.dtype} {'x'.join(map(str, image.shape))}")
    rows, cols = image.shape[:2]
    if max(rows, cols) > 65535:
        raise ValueError(f"an IMAGE message holds at most 65535 rows and columns, got a "
                         f"{cols}x{rows} image")
    # (pyigtl keeps the matrix in float32 and sends the image's centre, ijk (n - 1) / 2)
    matrix = matrix.astype(np.float32).astype(np.float64)
    centre = matrix @ [(cols - 1) / 2, (rows - 1) / 2, 0.0, 1.0]
    content = _IMAGE_HEADER.pack(1, 1 if image.ndim == 2 else image.shape[2],
                                 _IMAGE_SCALAR_TYPES[image.dtype], 2, 2, cols, rows, 1,
                                 *matrix[:3, :3].T.ravel(), *centre[:3], 0, 0, 0, cols, rows, 1)
    start = _HEADER.size + len(content)
    message = np.empty(start + image.nbytes, np.uint8)  # (not zeroed: every byte written)
    message[_HEADER.size:start] = np.frombuffer(content, np.uint8)
    pixels = message[start:].view(image.dtype.newbyteorder("<")).reshape(image.shape)
    if image.ndim == 3 and image.shape[2] == 3 and image.dtype == np.uint8:
        import cv2

        # BGR -> RGB into the message (50 Mpixel: 5-20 ms, numpy's [:, :, ::-1] 340-390 ms)
        cv2.cvtColor(image, cv2.COLOR_BGR2RGB, dst=pixels)
    else:
        pixels[...] = image[:, :, ::-1] if image.ndim == 3 else image
    seconds = int(timestamp)
    fraction = min(round((timestamp - seconds) * 2**32), 2**32 - 1)
    header = _HEADER.pack(1, b"IMAGE", device_name.encode(), seconds, fraction,
                          message.size - _HEADER.size, _core.crc64(message[_HEADER.size:]))
    message[:_HEADER.size] = np.frombuffer(header, np.uint8)
    return message


class IgtlImageServer:
    """Serves images over OpenIGTLink: a listening socket on ``address`` ([HOST:]PORT) that
    every client connecting (e.g. 3D Slicer's OpenIGTLinkIF in client mode) receives each
    :meth:`send` from, as IMAGE messages of ``device_name`` (igtl_image_bytes: RGB, one slice;
    placed by the ``ijk_to_world`` given to :meth:`send`, e.g. :func:`mosaic_ijk_to_world`,
    else 1 mm spacing with pixel (0, 0) at the origin). A client that fails, stalls (takes
    no byte of a message for ``send_timeout_s``; a slow link taking a large image for longer
    is not stalled) or is too slow (has not taken a whole message max(send_timeout_s, its size /
    MIN_SEND_RATE) after the send began) is dropped; what clients send is read and ignored. A
    context manager (closes the sockets)."""

    def __init__(self, address: str, *, device_name: str = "Mosaic",
                 send_timeout_s: float = 2.0) -> None:
        import pyigtl  # noqa: F401  (fail early, naming the package, if it is missing)

        self.host, self.port = parse_listen_address(address)
        self.requested_port = self.port
        self.where = f"OpenIGTLink server {format_address(self.host, self.port)}"
        self.device_name = device_name
        self.send_timeout_s = send_timeout_s
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        try:
            self._listener = socket.create_server((self.host, self.port), family=family)
        except OSError as exc:
            hint = "is the port in use?" if exc.errno == errno.EADDRINUSE else (
                "is HOST an address of this machine?")
            raise ValueError(f"{self.where}: cannot listen ({exc.strerror or exc}); "
                             f"{hint}") from None
        self.port = self._listener.getsockname()[1]
        self.address = format_address(self.host, self.port)
        self._listener.settimeout(0.2)
        self._clients: list[socket.socket] = []
        self._lock = threading.Lock()  # the client list (held briefly: accepting goes on)
        self._send_lock = threading.Lock()  # one message at a time to the clients
        self._stop = False
        self.clients_served = 0  # clients that connected
        self.messages_sent = 0  # messages sent to a client in full
        self._thread = threading.Thread(target=self._accept, name="igtl-image-server",
                                        daemon=True)
        self._thread.start()

    def _accept(self) -> None:
        while not self._stop:
            try:
                client, _ = self._listener.accept()
            except TimeoutError:
                client = None
            except OSError:
                return  # closed
            if client is not None:
                client.setblocking(False)  # (send waits for each client's progress: select)
                with self._lock:
                    self._clients.append(client)
                    self.clients_served += 1
            with self._lock:
                clients = list(self._clients)
            for c in clients:  # read and ignore what clients send
                try:
                    for _ in range(_READS_PER_PASS):  # (a client flooding us cannot hold it)
                        if not select.select([c], [], [], 0)[0]:
                            break
                        if not c.recv(65536):  # the client closed
                            self._remove(c)
                            break
                except BlockingIOError:
                    pass
                except (OSError, ValueError):  # (ValueError: closed meanwhile by send)
                    self._remove(c)

    def _remove(self, client: socket.socket) -> None:
        with self._lock:
            if client in self._clients:
                self._drop(client)

    def _drop(self, client: socket.socket) -> None:
        self._clients.remove(client)
        try:
            client.close()
        except OSError:
            pass

    @property
    def num_clients(self) -> int:
        with self._lock:
            return len(self._clients)

    def send(self, image: np.ndarray, timestamp: float | None = None, *,
             ijk_to_world: np.ndarray | None = None) -> int:
        """Sends a uint8 BGR (H, W, 3) or gray (H, W) image to every connected client; returns
        how many got it. ijk_to_world: where it lies (igtl_image_message); None: the identity."""
        message = igtl_image_bytes(image, device_name=self.device_name,
                                   timestamp=time.time() if timestamp is None else timestamp,
                                   ijk_to_world=ijk_to_world)
        with self._send_lock:
            with self._lock:  # (released while sending: a client connecting is accepted)
                clients = list(self._clients)
            sent = self._send_to(clients, message)
        self.messages_sent += sent
        return sent

    def _send_to(self, clients: list[socket.socket], message: np.ndarray) -> int:
        """Sends message to every client at once, each as fast as it takes it; drops a client
        that fails, takes no byte for send_timeout_s, or has not taken all of it by
        max(send_timeout_s, len(message) / MIN_SEND_RATE) after the start (a timeout of
        send_timeout_s on the whole sendall dropped a client 2 s into a 27 MB mosaic over a
        32 Mbit/s link, mid-message, every time; review). Returns how many got all of it."""
        data = memoryview(message)
        start = time.monotonic()
        deadline = start + max(self.send_timeout_s, len(message) / MIN_SEND_RATE)
        pending = {c: [0, start] for c in clients}  # client -> [bytes sent, last progress]
        done = 0
        while pending and not self._stop:
            now = time.monotonic()
            for c in [c for c, (_, last) in pending.items()
                      if now - last > self.send_timeout_s or now > deadline]:
                del pending[c]  # stalled or too slow: its stream is broken (part sent)
                self._remove(c)
            if not pending:
                break
            wait = min(min(last for _, last in pending.values()) + self.send_timeout_s,
                       deadline) - now
            try:
                select.select([], list(pending), [], min(max(wait, 0.0), _SEND_POLL_S))
            except (OSError, ValueError):  # a client closed meanwhile (_accept: it left)
                time.sleep(0.01)  # (its send fails below)
            # (every client tried, not only those select calls writable: a socket is writable
            # once a third of its buffer, up to 4 MB, is free, and a client reading 1.6 MB/s
            # steadily went 0.4 s without it; a send takes whatever room there is)
            for c in list(pending):
                state = pending[c]
                try:
                    state[0] += c.send(data[state[0]:])
                except BlockingIOError:
                    continue
                except (OSError, ValueError):  # closed, reset: its stream is broken
                    del pending[c]
                    self._remove(c)
                    continue
                state[1] = time.monotonic()
                if state[0] == len(data):
                    del pending[c]
                    done += 1
        return done

    def close(self) -> None:
        self._stop = True
        try:
            self._listener.close()
        except OSError:
            pass
        self._thread.join(timeout=2.0)
        with self._lock:
            for c in list(self._clients):
                self._drop(c)

    def __enter__(self) -> IgtlImageServer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
