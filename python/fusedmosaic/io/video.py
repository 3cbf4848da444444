"""Frame access: ``frames/*.png`` (in natural name order) or one ``video.*`` file, read lazily."""

from __future__ import annotations

import bisect
import math
import re
import threading
import warnings
from collections import OrderedDict
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import cv2
import numpy as np

from fusedmosaic.io._paths import is_utf8, opencv_path
from fusedmosaic.io.output import write_image_file

_DIGITS = re.compile(r"(\d+)")
VIDEO_READ_AHEAD = 8  # a request up to this many frames ahead decodes forward instead of seeking
VIDEO_RECENT_FRAMES = 4  # frames decoded on the way, kept for threads asking slightly out of order
MAX_VIDEO_FRAME_RATE = 1000.0  # a container reporting more (or <= 0, NaN) gives no frame rate
# 16-bit frames: the bit depth in use is read from this many frames evenly spaced over the
# sequence (first and last included), so that one scale serves the whole dataset.
DEPTH_SAMPLE_FRAMES = 8
# Counting a video's frames by decoding, this many undecodable frames in a row are taken as
# damage inside the file (the frames after them still count); more, as its end.
MAX_UNDECODABLE_RUN = 25
# Containers whose frame count OpenCV estimates from the duration and the nominal rate (they
# hold none: Matroska / WebM, MPEG transport and program streams)
ESTIMATED_COUNT_SUFFIXES = frozenset({".mkv", ".mka", ".webm", ".ts", ".m2ts", ".mts", ".mpg",
                                      ".mpeg", ".vob"})
# ms; a seek has landed on the frame asked for when the decoded frame's CAP_PROP_POS_MSEC is
# within this of that frame's stamp in the decoding pass (and within a quarter of the stamps'
# smallest spacing). Both come from the same packet timestamps: equal to the bit on every
# right landing of 40 random seeks each in H.264 / HEVC / MPEG-2 MP4, MKV and TS (review 46),
# while a wrong landing is a frame interval off or more (TS: every seek into the first GOP,
# frame 0 too, lands on frame G + 1; a killed recorder's AVI: anywhere).
LANDING_TOLERANCE_MS = 0.01
# FFmpeg's codes of 16-bit grey pixels (gray16le, gray16be; e.g. FFV1 video), as OpenCV reports
# them in CAP_PROP_CODEC_PIXEL_FORMAT
GREY16_PIXEL_FORMATS = (ord("Y") | ord("1") << 8 | 16 << 24, 16 | ord("1") << 16 | ord("Y") << 24)
# ... and of 8-bit grey pixels (gray: Y800, Y8, GREY; e.g. FFV1 or raw grey video)
GREY8_PIXEL_FORMATS = tuple(int.from_bytes(code, "little") for code in (b"Y800", b"Y8  ", b"GREY"))


def natural_key(name: str) -> tuple:
    """Sort key comparing digit runs by value: ``frame_2`` < ``frame_10``. For zero-padded names
    of equal width this is plain name order; ties (``f01`` vs ``f1``) fall back to the name.

    The key is a tuple of (text, number) pairs, number -1 after the last digit run, so keys of any
    two names compare (``x.png`` before ``x.png1.png``)."""
    parts = _DIGITS.split(name)  # text, digits, text, ..., text
    pairs = tuple((parts[i], int(parts[i + 1])) for i in range(0, len(parts) - 1, 2))
    return (*pairs, (parts[-1], -1)), name


def _decimal_key(name: str) -> tuple:
    """As natural_key, but a digit run right after ``<digits>.`` is a decimal fraction (compared
    as text: ``.125`` < ``.25`` < ``.5``). Fractions are recognised by their text segment being
    exactly ``.``, so two pairs with equal text are of the same kind and always compare."""
    parts = _DIGITS.split(name)
    pairs = []
    for i in range(0, len(parts) - 1, 2):
        fraction = i > 0 and parts[i] == "."
        digits = parts[i + 1]
        pairs.append((parts[i], -1, digits) if fraction else (parts[i], int(digits), ""))
    return (*pairs, (parts[-1], -1, "")), name


def _number_key(name: str) -> tuple:
    """``name`` with each number by its value: equal for names writing the same numbers with
    other zeros (``f05``, ``f5``; a decimal fraction's trailing ones, ``t_1.5``, ``t_1.50``)."""
    parts: list = _DIGITS.split(name)  # text, digits, text, ..., text
    for i in range(1, len(parts), 2):
        fraction = i > 1 and parts[i - 1] == "."  # as _decimal_key reads fractions
        parts[i] = parts[i].rstrip("0") if fraction else int(parts[i])
    return tuple(parts)


def sort_frame_names(names: Iterable[str], folder: str | Path = "frames") -> list[str]:
    """Frame file names in natural order (``frame_2.png`` before ``frame_10.png``).

    Names with decimal numbers (``1637000000.5.png``, ``t_0.08.png``) are ambiguous: a decimal
    timestamp and a version-like ``1.10`` order the other way. When reading such numbers as
    decimal fractions or as whole numbers gives different orders, raise instead of guessing;
    likewise for two names with equal numbers (``5.png`` and ``05.png``: _number_key).
    The ``.png`` suffix is left out of the comparison, so ``f1.png`` comes before ``f1.5.png``.
    """
    stems = {name: name[:-4] if name.lower().endswith(".png") else name for name in names}
    natural = sorted(stems, key=lambda n: (natural_key(stems[n]), n))
    # A name without a number among numbered frames (a thumb.png, a cover.png beside
    # 000000.png ...) was read as the last frame, timed and given a tracker pose (review 54);
    # one that begins the numbered names' pattern (frame.png before frame1.png, as some tools
    # name a sequence's first file) is a frame
    patterns = {_DIGITS.sub("", stems[n]) for n in natural if _DIGITS.search(stems[n])}
    plain = [n for n in natural if not _DIGITS.search(stems[n])
             and not any(p.startswith(stems[n]) for p in patterns)]
    if plain and patterns:
        numbered = next(n for n in natural if _DIGITS.search(stems[n]))
        more = f" (and {len(plain) - 1} more)" if len(plain) > 1 else ""
        raise ValueError(
            f"{folder}: {plain[0]!r}{more} has no number in its name, beside numbered frames "
            f"(e.g. {numbered!r}): frames are ordered by the numbers in their names; remove "
            "the files that are not frames, or rename them")
    # Two names with equal numbers (5.png and 05.png, a copy) were read as consecutive frames,
    # every later one timed a frame late against tracking.csv / robot.csv without frames.csv
    # (review 47): which of them is the frame is as ambiguous as the orders below.
    seen: dict[tuple, str] = {}
    for name in natural:
        key = _number_key(stems[name])
        if key in seen:
            numbers = _DIGITS.findall(stems[name])
            frame = f"frame {int(numbers[0])}" if len(numbers) == 1 else "the same frame"
            raise ValueError(
                f"{folder}: two files for {frame}: {seen[key]} and {name} (the frames are "
                "ordered by the numbers in their names, and theirs are equal); remove the one "
                "that is not a frame, or rename it")
        seen[key] = name
    decimal = sorted(stems, key=lambda n: (_decimal_key(stems[n]), n))
    for a, b in zip(natural, decimal, strict=True):
        if a != b:  # a precedes b by whole numbers, b precedes a by decimals
            raise ValueError(
                f"{folder}: frame names order differently when their numbers are read as "
                f"decimals or as whole numbers (e.g. {a!r} and {b!r}); rename the frames with "
                "zero-padded frame numbers (000000.png, 000001.png, ...)"
            )
    return natural


# Files named video.* that are a recording's sidecars (subtitles, metadata, notes), not videos.
NOT_VIDEO_SUFFIXES = frozenset({".srt", ".vtt", ".ass", ".ssa", ".sub", ".json", ".xml", ".csv",
                                ".txt", ".md", ".yaml", ".yml", ".log", ".nfo", ".sha256",
                                ".md5"})


# Image files in frames/ that are not frames (only PNG is): named when found there.
OTHER_IMAGE_SUFFIXES = frozenset({".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp", ".gif",
                                  ".pgm", ".ppm", ".pnm", ".jp2", ".exr", ".dng", ".raw"})


def _named(names: list[str], shown: int = 3) -> str:
    return ", ".join(names[:shown]) + (", ..." if len(names) > shown else "")


class FrameSource(Sequence):
    """Sequence of frames read from disk on demand; no image is kept in memory (a video source
    keeps at most ``VIDEO_RECENT_FRAMES`` decoded frames it skipped over).

    ``frame_rate``: the frame rate a video's container reports (frames/s; None for PNG frames, or
    a video reporting none in (0, MAX_VIDEO_FRAME_RATE]); read_dataset takes the frame times
    from it when the dataset has no frames.csv. It is the nominal rate: a variable-frame-rate
    video is timed by its own stamps instead (``presentation_times``, one decoding pass).
    A video's frame count is its header's, checked at its end (``counted_by`` says when the
    frames had to be counted by decoding).

    Items are uint8 (H, W) or (H, W, 3) BGR as stored (an alpha channel is dropped). A video is
    decoded to BGR, except a grey one, decoded to grey (H, W) as grey PNG frames are: a 16-bit
    grey video (pixel format gray16), and an 8-bit video that is grey, which is decided ONCE
    for the whole video (``video_grey``), before its first frame is handed out: its pixel
    format is grey (GREY8_PIXEL_FORMATS, e.g. an FFV1 grey video), or each of
    ``DEPTH_SAMPLE_FRAMES`` frames evenly spaced over it (first and last included; those that
    do not decode left out) has B == G == R everywhere, not all of them all-black (an MJPG
    ``.avi`` written with ``isColor=False`` is stored as yuvj420p, I420, with neutral chroma).
    Never per frame: a black or grey frame inside a colour video stays BGR. A grey video's
    frames are then their grey plane (cv2.COLOR_BGR2GRAY: channel 0 of a frame with B == G ==
    R). With ``expected_size=(w, h)`` every image is checked against it, and every image must
    have the channel count and bit depth of the first one read (all grey or all BGR; all 8-bit
    or all 16-bit).

    A frame that cannot be read (a PNG that is damaged or gone, a video frame that does not
    decode) raises ValueError naming it; with ``blank_unreadable`` it is read as an all-zero
    image of the dataset's size and channels instead (no visual content: the methods place it
    from their priors, as a black frame) and recorded in ``unreadable`` (index -> message), so
    that a run can flag it and leave it out of the mosaic. Images of another size, channel
    count or bit depth still raise: they are not damage but another recording's frames.

    16-bit frames (pCLE exports are 16-bit PNG; 16-bit grey video, e.g. FFV1) are converted to
    8 bits with ONE scale for the whole dataset, so that the mosaic does not flicker and the
    registrations' thresholds (NCC, feature detectors) see the same contrast in every frame:
    the bit depth in use, b, is the smallest in 8..16 holding the largest value of
    ``DEPTH_SAMPLE_FRAMES`` frames evenly spaced over the sequence (first and last included),
    and a value v becomes round(v * 255 / (2^b - 1)). So a 12-bit sensor's data (0-4095) maps
    4095 to 255, data scaled to the full 16 bits 65535 to 255; the scale is not stretched to
    the frames' contrast (dim data stays dim, as it would in 8 bits). A frame with values above
    2^b - 1 (possible only outside the sample) is clipped to 255, with a warning naming it (once
    per source). ``bits_in_use`` holds b once a 16-bit frame was read (None before, and for
    8-bit frames). Other pixel types (float, 32-bit, signed) are refused.

    Thread-safe: a video is decoded sequentially under a lock (seek + decode are one step), seeking
    only for jumps backwards or more than ``VIDEO_READ_AHEAD`` frames ahead. A seek's landing is
    checked against the stamps of the decoding pass every video has when opened (the frame it
    reached, not the one OpenCV reports); frame 0, frames a seek failed to reach and every
    frame of a video whose stamps cannot tell its frames apart are reached by opening it again
    and decoding forward.
    """

    def __init__(
        self,
        paths: list[Path] | None = None,
        *,
        video: Path | None = None,
        expected_size: tuple[int, int] | None = None,
        size_source: str = "camera.yaml",
        blank_unreadable: bool = False,
    ) -> None:
        if (paths is None) == (video is None):
            raise ValueError("FrameSource: give exactly one of paths or video")
        self.paths = None if paths is None else [Path(p) for p in paths]
        self.video = None if video is None else Path(video)
        if self.video is not None:  # only OpenCV reads it: every use below passes this name
            opencv_path(self.video, "read a video")
        self.expected_size = expected_size
        self.size_source = size_source
        self._capture: cv2.VideoCapture | None = None
        self._next = 0  # index the capture will decode next; -1 = unknown, seek first
        self._recent: OrderedDict[int, np.ndarray] = OrderedDict()  # skipped decoded frames
        self._lock = threading.Lock()  # guards the capture, _next and _recent
        self._channels: tuple[int, str] | None = None  # channel count of the first image, its name
        self._dtype: tuple[np.dtype, str] | None = None  # pixel type of the first image, its name
        self._depth_lock = threading.Lock()  # guards bits_in_use (taken without self._lock)
        self.bits_in_use: int | None = None  # 16-bit frames: the bit depth in use (see above)
        self._grey_lock = threading.Lock()  # guards video_grey (taken without self._lock)
        # an 8-bit video: decoded to grey (see above); None until its first frame is read, and
        # for PNG frames
        self.video_grey: bool | None = None
        self._clipped = False  # a 16-bit frame exceeded 2^bits_in_use - 1 (warned once)
        self.frame_rate: float | None = None
        self._seek_limit: int | None = None  # frames from here on are reached by decoding
        # frames up to this one are reached by decoding from the start, not by a seek (frame 0
        # never is; raised by a seek that landed elsewhere; the length: no seeking)
        self._seek_floor = 0
        self._missed_landings = 0  # seeks that landed on another frame than the one asked for
        self._times: np.ndarray | None = None  # presentation times (ms) from a decoding pass
        # the stamps that check a seek's landing and their tolerance (ms), or None when they
        # cannot (not one per frame, not strictly increasing); decided on the first seek
        self._landing_stamps: tuple[np.ndarray, float] | None | bool = False
        self.counted_by = "its header"  # a video's frame count: its header's, or "decoding"
        self.blank_unreadable = blank_unreadable
        self.unreadable: dict[int, str] = {}  # with blank_unreadable: index -> why (see above)
        self._alpha_noted = False  # (_check: a non-opaque alpha warned about once)
        self._blank: np.ndarray | None = None  # the all-zero frame given for unreadable ones
        if self.paths is not None:
            self._length = len(self.paths)
        else:
            capture = self._open_capture()
            rate = float(capture.get(cv2.CAP_PROP_FPS))
            if np.isfinite(rate) and 0.0 < rate <= MAX_VIDEO_FRAME_RATE:
                self.frame_rate = rate
            self._length = header = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
            judged = False  # (whether the warning below judged its last frame)
            # The header's count is checked at its end. Fewer frames than the file holds (a
            # recorder that crashed before updating it): frames decoding after the last counted
            # one. More (Matroska / WebM have no count: OpenCV estimates duration x nominal rate,
            # wrong for a variable frame rate; or a file truncated): its last frame does not
            # decode. Either way the frames are counted by decoding, as without a count.
            if self._length > 0:
                last, beyond = self._probe_end(capture, self._length)
                # closed at the end: the first read opens it again, at frame 0 (a seek to frame
                # 0 is not made: in an MPEG transport stream it lands on the second keyframe)
                self.close()
                if beyond:  # OpenCV's seeks stop at the header's last frame: frames past it
                    # are decoded forward from there (slower random access, the right images)
                    self._seek_limit = self._length
                if beyond or not last:
                    capture, self._length = self._open_capture(), 0
                else:
                    self._check_decodes_in_order()
            if self._length <= 0:
                times = _decode_times(capture)
                self._length, self._times = len(times), np.array(times, dtype=np.float64)
                self.counted_by = "decoding"
                self.close()
                if 0 < self._length < header:
                    lost = _avi_frames_lost_inside(self.video, header)
                    if lost is not None:
                        raise ValueError(
                            f"{self.video}: its header counts {header} frames but decoding it "
                            f"gives {self._length}, and the file is whole at its end: {lost}; "
                            "the decoder passes the loss without an error, so every frame "
                            "after it would be read under another frame's number (its time, "
                            "its tracker or robot sample); repair the file, or give the frames "
                            "that decode as frames/*.png with frames.csv (each one's frame "
                            "number and time)")
                    read = f"the {self._length} are read"
                    if self._leave_out_part_frame():
                        read = (f"the {self._length} whole ones are read; frame {self._length}, "
                                "cut inside its chunk at the file's end and decoded in part, is "
                                "left out")
                    warnings.warn(
                        f"{self.video}: its header counts {header} frames but "
                        f"{len(times)} decode ({self._fewer_frames_why()}): {read}",
                        stacklevel=2)
                    judged = True
            # a file cut inside its last frame's chunk whose count still holds (the header
            # counting the frames that decode), or one without a count (a recorder that stopped
            # before writing it): the same part-decoded last frame
            if not judged and self._leave_out_part_frame():
                warnings.warn(
                    f"{self.video}: the file ends inside frame {self._length}'s chunk (cut "
                    "short, or its recorder stopped mid-frame): that frame decodes in part and "
                    f"is left out; the {self._length} whole ones are read", stacklevel=2)
        if self._length <= 0 and self.video is not None and header > 0:
            raise ValueError(
                f"{self.video}: its header counts {header} frames ({_codec(self.video)}) but "
                "none decodes: a codec this OpenCV's FFmpeg cannot decode, or a damaged file; "
                "re-encode it (e.g. H.264, MJPG or FFV1) or give the frames as frames/*.png")
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
        blank_unreadable: bool = False,
    ) -> FrameSource:
        """Find ``frames/*.png`` (``.PNG`` too) or a single ``video.*`` under ``dataset_root``
        (sidecar files such as video.srt or video.json, NOT_VIDEO_SUFFIXES, are not videos);
        both at once are refused (which one is the recording?). Frames are in natural name order
        (digit runs by value: ``frame_2.png`` before ``frame_10.png``); names whose decimal
        numbers make that order ambiguous are refused (see sort_frame_names)."""
        root = Path(dataset_root)
        frames_dir = root / "frames"
        videos = sorted(p for p in root.glob("video.*") if p.is_file()
                        and p.suffix.lower() not in NOT_VIDEO_SUFFIXES)
        if frames_dir.is_dir() and videos:
            raise ValueError(f"{root}: both frames/ and {videos[0].name}; a dataset holds its "
                             "frames one way: move one of them out")
        if frames_dir.is_dir():
            # As the shell's frames/*.png: hidden files (e.g. macOS ._000005.png) are not frames.
            files = [p for p in frames_dir.iterdir() if not p.name.startswith(".") and p.is_file()]
            found = [p.name for p in files if p.suffix.lower() == ".png"]
            others = sorted(p.name for p in files if p.suffix.lower() in OTHER_IMAGE_SUFFIXES)
            if not found:
                kinds = sorted({Path(n).suffix.lower() for n in others})
                raise ValueError(
                    f"{frames_dir}: no frames (*.png)" + (
                        f": it holds {len(others)} {'/'.join(kinds)} file(s) ({_named(others)}), "
                        "and only PNG frames are read; convert them to PNG (lossless), or give "
                        "the recording as one video.* file" if others else ""))
            if others:  # (a stray JPEG was left out without a word; review)
                warnings.warn(
                    f"{frames_dir}: {len(others)} image file(s) that are not PNG left out "
                    f"({_named(others)}): only frames/*.png are frames", stacklevel=2)
            paths = [frames_dir / name for name in sort_frame_names(found, frames_dir)]
            return cls(paths, expected_size=expected_size, size_source=size_source,
                       blank_unreadable=blank_unreadable)
        if len(videos) > 1:
            raise ValueError(
                f"{root}: several video files ({', '.join(p.name for p in videos)}), expected one"
            )
        if not videos:
            hints = []
            for p in sorted(root.iterdir() if root.is_dir() else ()):
                if p.name == "frames" and not p.is_dir():
                    hints.append("frames is a file, not a folder of PNG frames")
                elif p.name == "video" and p.is_file():
                    hints.append("video has no extension: name it video.<ext> (video.mp4, ...)")
                elif p.name.lower() == "frames" or (
                        p.stem.lower() == "video" and p.is_file()
                        and p.suffix.lower() not in NOT_VIDEO_SUFFIXES):
                    hints.append(f"found {p.name}: the names are case-sensitive (frames/, "
                                 "video.<ext>); rename it")
            raise ValueError(
                f"{root}: no frames (neither frames/*.png nor a video.* file)"
                + "".join(f"; {h}" for h in hints))
        return cls(video=videos[0], expected_size=expected_size, size_source=size_source,
                   blank_unreadable=blank_unreadable)

    def __len__(self) -> int:
        return self._length

    def __getitem__(self, index: int) -> np.ndarray:
        if not isinstance(index, (int, np.integer)):
            raise TypeError(f"FrameSource indices must be integers, not {type(index).__name__}")
        i = int(index) + (self._length if index < 0 else 0)
        if not 0 <= i < self._length:
            raise IndexError(f"frame index {index} out of range for {self._length} frames")
        image, name = self._raw(i)
        if image is None and self.blank_unreadable:
            self.unreadable[i] = self._unreadable_message(name)  # (one store: thread-safe)
            return self._blank_frame()
        return self._check(image, name)

    def _raw(self, i: int) -> tuple[np.ndarray | None, str | Path]:
        """Frame i as stored (None if it cannot be read) and its name for messages."""
        if self.paths is not None:
            image = read_png(self.paths[i])
            if image is not None and image.ndim == 3 and image.shape[2] == 4 and _grey_alpha_png(
                    self.paths[i]):
                image = np.ascontiguousarray(image[:, :, 0])  # OpenCV expands it to BGRA
            return image, self.paths[i]
        return self._read_video(i), f"{self.video} frame {i}"

    def __iter__(self) -> Iterator[np.ndarray]:
        for i in range(self._length):
            yield self[i]

    def __del__(self) -> None:
        self.close()

    def close(self) -> None:
        lock = getattr(self, "_lock", None)
        if lock is None:  # __init__ failed early
            return
        with lock:
            if self._capture is not None:
                self._capture.release()
                self._capture = None
            self._recent.clear()

    def _open_capture(self) -> cv2.VideoCapture:
        if self._capture is None:
            self._capture = cv2.VideoCapture(str(self.video))
            self._next = 0
            if not self._capture.isOpened():
                self._capture = None
                size = self.video.stat().st_size if self.video.is_file() else None
                raise ValueError(
                    f"{self.video}: cannot open video"
                    + (" (an empty file)" if size == 0 else
                       " (not a video this OpenCV's FFmpeg reads, or a recording that stopped "
                       "before it was finished: an MP4 / MOV without its index, 'moov atom "
                       "not found')" if size else ""))
            if int(self._capture.get(cv2.CAP_PROP_CODEC_PIXEL_FORMAT)) in GREY16_PIXEL_FORMATS:
                # OpenCV's BGR conversion keeps a 16-bit grey video's high byte only (12-bit
                # data comes out as 0-15): its 16-bit frames take the PNGs' conversion instead
                self._capture.set(cv2.CAP_PROP_CONVERT_RGB, 0)
        return self._capture

    def _check_decodes_in_order(self) -> None:
        """A video whose header's count is confirmed at its end is decoded once from the start
        (its presentation times kept): the decoder passes frames damaged in the middle without
        a failed grab (an AVI or Matroska with bytes lost), so fewer frames decode than the
        header counts, and every frame after the damage would be read as another (a seek lands
        on the same wrong frames): its number, time and tracker sample another frame's (60 kB
        lost in a 60-frame AVI: frames 30-55 showed frames 34-59, e_M 155 px instead of 0.26,
        without a word). Refused, naming where the stamps show the loss when they do."""
        capture = cv2.VideoCapture(str(self.video))  # its own: the reads' stays where it is
        try:
            times = _decode_times(capture)
        finally:
            capture.release()
        if len(times) >= self._length:
            self._times = np.array(times, dtype=np.float64)  # (presentation_times')
            return
        where, lost = "", self._length - len(times)
        t = np.array(times)
        if self.frame_rate is not None and t.size > 1:
            jumps = np.flatnonzero(np.diff(t) > 1.5e3 / self.frame_rate)
            if jumps.size:
                k = int(jumps[0])
                where = (f"; its stamps jump from {t[k]:.6g} to {t[k + 1]:.6g} ms after the "
                         f"{k + 1}th decoded frame")
        raise ValueError(
            f"{self.video}: its header counts {self._length} frames and its last frame is "
            f"there, but decoding it from the start gives {len(times)}: "
            f"{lost} {'frame is' if lost == 1 else 'frames are'} damaged and passed without "
            f"an error by the decoder{where}, so every frame after would be read under another "
            "frame's number (its time, its tracker or robot sample); repair the file, or give "
            "the frames that decode as frames/*.png with frames.csv")

    def _leave_out_part_frame(self) -> bool:
        """Whether the video's last decoded frame lies past its whole chunks (an AVI cut inside
        that frame's chunk: FFmpeg decodes what it has of it, an MJPG frame's top with another
        view below; one such frame moved a 27-frame lba-emt run's e_M 0.14 -> 5.7 px); if so it
        is left out (the frame count and the stamps shortened by one)."""
        if self._length < 2 or _avi_whole_frames(self.video) != self._length - 1:
            return False
        self._length -= 1
        if self._times is not None:
            self._times = self._times[:self._length]
        return True

    def _fewer_frames_why(self) -> str:
        """Why a video decodes fewer frames than its header counts, for the warning: the
        possible causes, and where its stamps show frames lost in the middle when they do."""
        if self.video.suffix.lower() not in ESTIMATED_COUNT_SUFFIXES:
            # (no sign tells a file cut short from one damaged in the middle when the stamps
            # are counted, as an AVI's: both decode fewer frames than it counts)
            return ("a truncated file, or frames damaged in the middle, which the decoder "
                    "passes without a word: every frame after them is then read under an "
                    "earlier frame's number, time and tracker or robot sample; check that the "
                    "file was only cut short")
        why = ("a count estimated from the duration, as Matroska's and MPEG streams' are, a "
               "truncated file, or frames lost in the middle")
        frames = np.flatnonzero(np.isfinite(self._times))  # those that decode
        t = self._times[frames]
        steps = np.diff(t)
        if steps.size > 1 and (steps > 0).all():
            # a constant-rate file (its other intervals within 25 % of the median) whose stamps
            # jump by over 1.5 intervals (a variable-rate file's stamps prove nothing)
            interval = float(np.median(steps))
            jump = steps > 1.5 * interval
            rest = steps[~jump]
            if jump.any() and rest.max() - rest.min() <= 0.25 * interval:
                k = int(np.flatnonzero(jump)[0])
                why += (f": its stamps jump from {t[k]:.6g} ms (frame {frames[k]}) to "
                        f"{t[k + 1]:.6g} ms (frame {frames[k + 1]}), frames lost there; timed by "
                        "its stamps (without frames.csv or --fps), the frames after keep their "
                        "own times")
        return why

    def _probe_end(self, capture: cv2.VideoCapture, count: int) -> tuple[bool, bool]:
        """(frame count-1 decodes, frame count decodes too); the capture is then at the end:
        the caller closes it."""
        capture.set(cv2.CAP_PROP_POS_FRAMES, count - 1)
        self._next = -1
        # a seek may land on another frame (beyond an undecodable one): then not trusted
        last = capture.grab() and capture.get(cv2.CAP_PROP_POS_FRAMES) == count
        return last, last and capture.grab()

    def presentation_times(self) -> np.ndarray | None:
        """A video's frame times as its container stamps them, s after the first frame, from
        one decoding pass (cached; OpenCV's CAP_PROP_POS_MSEC of each decoded frame): what a
        variable-frame-rate video holds instead of a rate. None for PNG frames, and when the
        stamps are not usable (not one per frame, or those of the frames that decode not
        strictly increasing). A frame that does not decode has no stamp: it is given a time
        between its neighbours' (it is read as unreadable anyway), so that the frames after it
        keep their own (a Matroska file with one frame lost in the middle was timed at its
        frame rate: the frames after the loss got earlier frames' times and tracker samples,
        15 mm off; review 46); before the first stamp, or after the last, one frame interval
        apart (the frame rate's, else the stamps' median spacing)."""
        if self.video is None:
            return None
        t = self._decoded_times()
        finite = np.isfinite(t)
        if t.size != self._length or not finite.any() or (np.diff(t[finite]) <= 0).any():
            return None
        if not finite.all():
            k, known = np.arange(t.size), np.flatnonzero(finite)
            if self.frame_rate is not None:
                interval = 1e3 / self.frame_rate
            elif known.size > 1:
                interval = float(np.median(np.diff(t[known]) / np.diff(known)))
            else:
                return None
            t = np.interp(k, known, t[known])  # (constant beyond the ends: extended below)
            t += np.where(k < known[0], (k - known[0]) * interval, 0.0)
            t += np.where(k > known[-1], (k - known[-1]) * interval, 0.0)
        return (t - t[0]) / 1e3

    def _decoded_times(self) -> np.ndarray:
        """The decoding pass's stamps (ms; NaN for a frame that does not decode), made once
        (every video has had it when opened; else here, with its own capture)."""
        if self._times is None:
            capture = cv2.VideoCapture(str(self.video))  # its own: the reads' stays where it is
            try:
                times = _decode_times(capture, self._length + 1)
            finally:
                capture.release()
            self._times = np.array(times, dtype=np.float64)
        return self._times

    def _read_video(self, i: int) -> np.ndarray | None:
        """Frame i, or None when it does not decode (undecodable frames before it are passed:
        each failed grab is one frame). Frames are decoded forward from the start, or from a
        seek whose landing is checked (_seek_start, _landed): OpenCV reports the frame asked
        for whichever it reached (CAP_PROP_POS_FRAMES), and a seek may land elsewhere without
        a word (an MPEG transport stream: every seek into the first GOP, frame 0 included,
        lands on frame G + 1; an AVI left by a crashed recorder: anywhere), so every frame was
        read as another (e_M 354 px for 0.22, exit 0; review 46)."""
        with self._lock:  # one cv2.VideoCapture: concurrent seek/decode crashes FFmpeg
            image = self._recent.pop(i, None)
            if image is not None:
                return image
            capture = self._open_capture()
            seeked = None  # the frame a seek went to, until its landing is checked
            if self._next < 0 or not 0 <= i - self._next <= VIDEO_READ_AHEAD:
                start = self._seek_start(i)
                if start < 0:  # from the start, unless decoding on from here gets there
                    if not 0 <= self._next <= i:
                        capture = self._reopen()
                elif not start <= self._next <= i:  # else decoding on from here is shorter
                    capture.set(cv2.CAP_PROP_POS_FRAMES, start)
                    self._next = seeked = start
            while True:
                ok, image = capture.read()
                if seeked is not None:
                    if not (ok and self._landed(capture, seeked)):
                        # landed on another frame, or on one that does not decode (the frame
                        # asked for does: it has a stamp): decoded from the start instead
                        self._missed(capture.get(cv2.CAP_PROP_POS_MSEC) if ok else None,
                                     seeked)
                        capture, seeked = self._reopen(), None
                        continue
                    seeked = None
                if not ok:
                    if self._next >= i:
                        self._next = -1  # position unknown after a failed decode
                        return None
                    # an undecodable frame on the way: the next grab decodes the frame after it
                    self._next += 1  # (as _decode_times counts them)
                    continue
                self._next += 1
                if self._next > i:
                    return image
                self._recent[self._next - 1] = image  # skipped: another thread may want it
                if len(self._recent) > VIDEO_RECENT_FRAMES:
                    self._recent.popitem(last=False)

    def _reopen(self) -> cv2.VideoCapture:
        """The capture opened again, at frame 0 (what a seek to frame 0 does not do reliably:
        an MPEG transport stream lands on its second keyframe; a one-frame video's end does
        not seek back)."""
        if self._capture is not None:
            self._capture.release()
            self._capture = None
        return self._open_capture()

    def _seek_start(self, i: int) -> int:
        """The frame a seek for frame i goes to (i; the last frame before _seek_limit; the
        nearest frame before with a stamp), or -1: frame i is reached by decoding from the start
        (it is at or below _seek_floor, or no stamps can check a landing)."""
        stamps = self._stamps_for_landing()
        if stamps is None:
            return -1
        t = stamps[0]
        start = i if self._seek_limit is None else min(i, self._seek_limit - 1)
        while start > self._seek_floor and not np.isfinite(t[start]):
            start -= 1  # a frame that does not decode: its landing cannot be checked
        return start if start > self._seek_floor else -1

    def _stamps_for_landing(self) -> tuple[np.ndarray, float] | None:
        """(the decoding pass's stamps of the frames, ms; the landing tolerance), or None when
        they cannot tell one frame from another: fewer than the frames, or none left once the
        stamps out of order are set aside: such a video is never sought in. The stamps kept
        are a longest strictly increasing run of them (in frame order); the others (an MPEG
        program stream's or a B-frame AVI's last frame stamped 0) are unknown, their frames
        reached from a stamped frame before them (one such stamp stopped all seeking: 20
        random reads of a 1500-frame AVI took 0.95 s, 0.04 s with it set aside; review 46)."""
        if self._landing_stamps is False:
            t = self._decoded_times()[:self._length].astype(np.float64)
            ordered = _longest_increasing(t)
            t = np.where(ordered, t, np.nan)
            steps = np.diff(t[ordered])
            usable = t.size == self._length and bool(ordered.any())
            if not usable:
                self._seek_floor = self._length
            tolerance = min(LANDING_TOLERANCE_MS, float(steps.min()) / 4 if steps.size else
                            LANDING_TOLERANCE_MS)
            self._landing_stamps = (t, tolerance) if usable else None
        return self._landing_stamps

    def _landed(self, capture: cv2.VideoCapture, start: int) -> bool:
        """The frame just decoded after a seek to ``start`` is that frame: its stamp
        (CAP_PROP_POS_MSEC) is the decoding pass's for it."""
        t, tolerance = self._landing_stamps
        return abs(capture.get(cv2.CAP_PROP_POS_MSEC) - t[start]) <= tolerance

    def _missed(self, stamp: float | None, start: int) -> None:
        """A seek to ``start`` landed elsewhere (the decoded frame's stamp, None when it did
        not decode): frames up to that one are reached from the start from now on (in an MPEG
        transport stream, the first GOP: the seek landed on frame G + 1); after a second such
        seek, every frame is (an AVI without its index, whose seeks land anywhere)."""
        self._missed_landings += 1
        if self._missed_landings > 1:
            self._seek_floor = self._length
            return
        t, tolerance = self._landing_stamps
        landed = start
        if stamp is not None:
            found = np.flatnonzero(np.abs(t - stamp) <= tolerance)
            if found.size and found[0] > start:
                landed = int(found[0]) - 1  # the frames before the one it landed on
        self._seek_floor = max(self._seek_floor, landed)

    def _unreadable_message(self, name) -> str:
        if self.video is not None:
            return f"{name}: cannot read image (video truncated or corrupt?)"
        return f"{name}: cannot read image"

    def _blank_frame(self) -> np.ndarray:
        """The all-zero frame standing for unreadable ones: the size and channels of the first
        frame that reads (ValueError when none does)."""
        if self._blank is None:
            for j in range(self._length):
                image, name = self._raw(j)
                if image is not None:
                    self._blank = np.zeros_like(self._check(image, name))
                    break
            else:
                where = self.video if self.video is not None else self.paths[0].parent
                raise ValueError(f"{where}: none of its {self._length} frames can be read "
                                 f"(e.g. {self._unreadable_message(self._raw(0)[1])})")
        return self._blank.copy()

    def _check(self, image: np.ndarray | None, name) -> np.ndarray:
        if image is None:
            raise ValueError(self._unreadable_message(name))
        if image.dtype not in (np.uint8, np.uint16):
            raise ValueError(f"{name}: {image.dtype} pixels; frames must be 8-bit or 16-bit "
                             "unsigned integers (e.g. PNG)")
        if self._dtype is None:
            with self._lock:
                if self._dtype is None:
                    self._dtype = (image.dtype, str(name))
        if image.dtype != self._dtype[0]:
            first, first_name = self._dtype
            raise ValueError(f"{name}: {_bits(image.dtype)} but {first_name} is "
                             f"{_bits(first)}; frames must be all 8-bit or all 16-bit")
        if image.ndim == 3 and image.shape[2] == 4:
            if not self._alpha_noted and (image[:, :, 3] < image[:, :, 3].max()).any():
                with self._lock:  # (once per source: an alpha mask repeats on every frame)
                    if not self._alpha_noted:
                        self._alpha_noted = True
                        warnings.warn(
                            f"{name}: its alpha channel is not opaque everywhere, and is "
                            "ignored (the colours are read as they are); a field of view "
                            "given as alpha goes into camera.yaml as fov_mask_radius", stacklevel=3)
            image = np.ascontiguousarray(image[:, :, :3])
        if image.ndim == 3 and image.shape[2] == 1:
            image = image[:, :, 0]
        if (self.video is not None and image.dtype == np.uint8 and image.ndim == 3
                and self._is_grey_video()):
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)  # (exactly channel 0 when grey)
        if image.dtype == np.uint16:
            image = self._to_8_bits(image, name)
        if self.expected_size is not None:
            w, h = self.expected_size
            if image.shape[1] != w or image.shape[0] != h:
                raise ValueError(
                    f"{name}: image is {image.shape[1]}x{image.shape[0]} but "
                    f"{self.size_source} says {w}x{h}"
                )
        channels = 1 if image.ndim == 2 else image.shape[2]
        if self._channels is None:
            with self._lock:
                if self._channels is None:
                    self._channels = (channels, str(name))
        if channels != self._channels[0]:
            first, first_name = self._channels
            raise ValueError(
                f"{name}: {_describe(channels)} but {first_name} has {_describe(first)}; "
                "frames must be all grey or all colour"
            )
        return image

    def _to_8_bits(self, image: np.ndarray, name) -> np.ndarray:
        """A 16-bit frame on the dataset's 8-bit scale (see the class docstring)."""
        if self.bits_in_use is None:
            with self._depth_lock:
                if self.bits_in_use is None:
                    self.bits_in_use = self._depth_in_use()
        full = (1 << self.bits_in_use) - 1
        peak = int(image.max())
        if peak > full and not self._clipped:
            self._clipped = True
            warnings.warn(
                f"{name}: 16-bit values up to {peak}, above the {self.bits_in_use}-bit range "
                f"(0-{full}) that {DEPTH_SAMPLE_FRAMES} frames spread over the sequence use: "
                f"clipped to 255 when converted to 8 bits (one scale for all frames; further "
                "frames above the range are clipped without a warning)", stacklevel=4)
        return to_8_bits(image, self.bits_in_use)

    def _is_grey_video(self) -> bool:
        """video_grey, decided on the first call (see the class docstring)."""
        if self.video_grey is None:
            with self._grey_lock:
                if self.video_grey is None:
                    self.video_grey = self._decide_grey()
        return self.video_grey

    def _decide_grey(self) -> bool:
        """An 8-bit video is grey: a grey pixel format, or B == G == R in every readable sample
        frame (DEPTH_SAMPLE_FRAMES evenly spaced), not all of them all-black."""
        with self._lock:
            code = int(self._open_capture().get(cv2.CAP_PROP_CODEC_PIXEL_FORMAT))
        if code in GREY8_PIXEL_FORMATS:
            return True
        seen = lit = False
        for image in self._sample_frames():
            if image is None or image.dtype != np.uint8 or image.ndim != 3:
                continue
            if image.shape[2] not in (3, 4):
                continue
            b, g, r = image[:, :, 0], image[:, :, 1], image[:, :, 2]
            if not (np.array_equal(b, g) and np.array_equal(g, r)):
                return False
            seen = True
            lit = lit or bool(b.any())
        return seen and lit

    def _sample_frames(self) -> Iterator[np.ndarray | None]:
        """The DEPTH_SAMPLE_FRAMES frames evenly spaced over the sequence (first and last
        included) as stored, None for one that cannot be read: what the bit depth in use and a
        video's greyness are decided from."""
        count = min(DEPTH_SAMPLE_FRAMES, self._length)
        for k in np.unique(np.round(np.linspace(0, self._length - 1, count)).astype(int)):
            yield self._raw(int(k))[0]

    def _depth_in_use(self) -> int:
        """The bits holding the largest value of the sample frames (8..16), whichever frame is
        read first. A sample frame that cannot be read, or is not 16-bit, is left out (it is
        refused when read)."""
        peak = 0
        for image in self._sample_frames():
            if image is not None and image.dtype == np.uint16:
                colour = image.ndim == 3 and image.shape[2] == 4  # the alpha channel is dropped
                peak = max(peak, int((image[:, :, :3] if colour else image).max()))
        return bits_holding(peak)


def read_png(path: Path) -> np.ndarray | None:
    """cv2.imread(path, IMREAD_UNCHANGED): the image as stored, None when it cannot be read. A
    name that is not UTF-8, which crashes OpenCV (io._paths), is read by Python and decoded in
    memory; other names still by imread: reading the bytes first costs 2-4 % more CPU (400x400
    PNG 2.80 against 2.66 ms, 1920x1080 34.4 against 33.1 ms; cv2 on one thread, review 47)."""
    if is_utf8(path):
        return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    try:
        data = np.fromfile(path, np.uint8)
    except OSError:  # gone, a folder, no permission: as imread
        return None
    return cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None  # (empty: asserts)


def _grey_alpha_png(path: Path) -> bool:
    """A PNG file of colour type 4, grey with alpha (its IHDR chunk's byte 25): OpenCV reads it
    as BGRA, B == G == R; it is a grey frame (its alpha dropped), not a colour one (a grey
    recording with such frames was refused as grey and colour mixed; review)."""
    try:
        with open(path, "rb") as f:
            head = f.read(26)
    except OSError:
        return False
    return (len(head) == 26 and head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR"
            and head[25] == 4)


def bits_holding(peak: int) -> int:
    """The bit depth in use of 16-bit data whose largest value is `peak`: the smallest b in
    8..16 with peak <= 2^b - 1 (FrameSource's scale; a live session's, io.igtl)."""
    return max(8, int(peak).bit_length())


def to_8_bits(image: np.ndarray, bits: int) -> np.ndarray:
    """A uint16 image (grey or colour) in 8 bits on the scale of bit depth `bits`:
    v -> round(v * 255 / (2^bits - 1)), values above 2^bits - 1 clipped to 255."""
    return cv2.convertScaleAbs(image, alpha=255.0 / ((1 << bits) - 1))  # rounds, saturates


def _decode_times(capture: cv2.VideoCapture, limit: int | None = None) -> list[float]:
    """Decodes the video from the capture's position to its end (at most ``limit`` frames):
    each frame's CAP_PROP_POS_MSEC, NaN for undecodable frames followed by decodable ones (each
    failed grab passes one frame, so the count stays right: frames.csv's rows and the frame
    numbers after them); the end at more than MAX_UNDECODABLE_RUN failures in a row."""
    times: list[float] = []
    run = 0  # failed grabs since the last decoded frame
    while limit is None or len(times) < limit:
        if capture.grab():
            times += [math.nan] * run
            run = 0
            times.append(capture.get(cv2.CAP_PROP_POS_MSEC))
        else:
            run += 1
            if run > MAX_UNDECODABLE_RUN:
                break
    return times


# An AVI's idx1 index, the last chunk of the file, is looked for in this much of its end (16
# bytes per chunk: 4M chunks), and the movi list that its offsets count from in this much of its
# start (the headers before it; OpenCV's writer: 8 kB).
AVI_INDEX_TAIL_BYTES = 64 << 20
AVI_MOVI_HEAD_BYTES = 1 << 20
_AVI_VIDEO_CHUNKS = (int.from_bytes(b"dc", "little"), int.from_bytes(b"db", "little"))


def _avi_whole_frames(video: Path) -> int | None:
    """How many video chunks of an AVI's movi list lie whole in the file (walked from its start,
    as a file cut short has lost its index); None when it is not an AVI or its chunks cannot be
    walked. A truncated AVI whose decoding gives one frame more ends inside that frame's chunk:
    the decoder gives what it has of it, a frame decoded in part (FrameSource)."""
    if video.suffix.lower() != ".avi":
        return None
    try:
        data = np.memmap(video, np.uint8, mode="r")
    except (OSError, ValueError):
        return None
    size = len(data)
    head = bytes(data[:min(size, AVI_MOVI_HEAD_BYTES)])
    movi = head.find(b"movi", 12)
    while movi >= 0 and head[movi - 8:movi - 4] != b"LIST":
        movi = head.find(b"movi", movi + 1)
    if head[:4] != b"RIFF" or head[8:12] != b"AVI " or movi < 0:
        return None
    end = min(size, movi + int.from_bytes(head[movi - 4:movi], "little"))
    at, whole = movi + 4, 0
    while at + 8 <= end:
        chunk = bytes(data[at:at + 8])
        length = int.from_bytes(chunk[4:], "little")
        if chunk[:4] == b"LIST":  # a 'rec ' list: its chunks are walked
            at += 12
            continue
        if not chunk[:4].isascii():
            return None  # (not a chunk id: the walk lost its way)
        if at + 8 + length > size:
            break  # the chunk the file ends inside
        if int.from_bytes(chunk[2:4], "little") in _AVI_VIDEO_CHUNKS:
            if length == 0:
                return None  # (a dropped frame's empty chunk: decoders differ on counting it)
            whole += 1
        at += 8 + length + (length & 1)
    return whole


def _avi_frames_lost_inside(video: Path, count: int) -> str | None:
    """Where an AVI that decodes fewer frames than its header's ``count`` shows frames lost
    inside it, for the refusal; None when it does not (not an AVI; no intact idx1 at its end;
    every frame's chunk where its index says), and the file may only be cut short (the warning).

    The seek to the header's last frame that confirms the count (FrameSource._probe_end) fails
    when bytes are lost inside an AVI (the index's offsets after the loss shift), so its
    decoding pass is not checked as one whose last frame is there (_check_decodes_in_order) and
    a lost frame went by with the truncated file's warning: every frame after it read under the
    next one's number, time and tracker sample (review 51: 12-frame MJPG AVI, frame 5's chunk
    cut out or its id damaged; frames 5-10 were read as frames 6-11). The stamps of such an
    AVI count its packets, as a truncated file's do: they show nothing. Its index does: written
    last, it is gone from a file cut short; a file that ends with a whole idx1 listing the
    ``count`` frames was not cut short, and an entry that does not find its frame's chunk id at
    its offset (bytes lost before that chunk, or its id damaged) shows the loss inside. An
    index whose entries all find their chunks (the last frames' data does not decode: the
    frames decoded are the first ones, right) and an OpenDML AVI (its index elsewhere) are
    left to the warning."""
    if video.suffix.lower() != ".avi":
        return None
    try:
        size = video.stat().st_size
        with open(video, "rb") as f:
            head = f.read(min(size, AVI_MOVI_HEAD_BYTES))
            tail_size = min(size, AVI_INDEX_TAIL_BYTES)
            f.seek(size - tail_size)
            tail = f.read(tail_size)
    except OSError:
        return None
    movi = head.find(b"movi", 12)
    while movi >= 0 and head[movi - 8:movi - 4] != b"LIST":
        movi = head.find(b"movi", movi + 1)
    if head[:4] != b"RIFF" or head[8:12] != b"AVI " or movi < 0:
        return None
    at = tail.rfind(b"idx1")
    while at >= 0:  # the idx1 chunk that ends the file (a pad byte allowed)
        length = int.from_bytes(tail[at + 4:at + 8], "little")
        if at + 8 + length in (len(tail), len(tail) - 1):
            break
        at = tail.rfind(b"idx1", 0, at)
    if at < 0:
        return None
    entries = np.frombuffer(tail, np.dtype([("id", "<u4"), ("flags", "<u4"), ("offset", "<u4"),
                                            ("size", "<u4")]), length // 16, at + 8)
    video_chunk = np.isin(entries["id"] >> 16, _AVI_VIDEO_CHUNKS)
    streams, counts = np.unique(entries["id"][video_chunk] & 0xFFFF, return_counts=True)
    if not streams.size or counts.max() < count:
        return None  # (an index listing fewer frames than the header counts proves nothing)
    frames = entries[video_chunk & ((entries["id"] & 0xFFFF) == streams[np.argmax(counts)])]
    data = np.memmap(video, np.uint8, mode="r")
    # the offsets count from the movi list's id (AVI 1.0), or from the file's start; as FFmpeg,
    # the one under which more chunks are found
    best, sized = None, None
    for base in (movi, 0, movi + 4 - int(frames["offset"][0])):
        at_chunk = base + frames["offset"].astype(np.int64)
        inside = (at_chunk >= 0) & (at_chunk + 8 <= size)
        found, same_size = np.zeros(len(frames), bool), np.zeros(len(frames), bool)
        header = data[at_chunk[inside, None] + np.arange(8)].view("<u4")  # (id, size)
        found[inside] = header[:, 0] == frames["id"][inside]
        same_size[inside] = found[inside] & (header[:, 1] == frames["size"][inside])
        if best is None or found.sum() > best.sum():
            best, sized = found, same_size
    if best.all():
        return None
    k = int(np.flatnonzero(~best)[0])
    if sized[0] and not sized[:k].all():  # its sizes tell sooner (a chunk cut out: the entry
        k = int(np.flatnonzero(~sized)[0])  # of the lost frame finds the next one's id there)
    return (f"its index (idx1) lists {len(frames)} frames, and frame {k}'s chunk is not where "
            f"it says ({int((~best).sum())} of the {len(frames)} are not): bytes lost or "
            f"damaged inside the file at frame {k}")


def _codec(video: Path) -> str:
    """'codec AV01': the four-character code of the video's stream, for messages."""
    capture = cv2.VideoCapture(str(video))
    try:
        code = int(capture.get(cv2.CAP_PROP_FOURCC))
    finally:
        capture.release()
    text = "".join(chr((code >> 8 * k) & 0xFF) for k in range(4))
    return f"codec {text.strip()}" if code > 0 and text.isprintable() else "codec unknown"


def _bits(dtype) -> str:
    return "8-bit" if dtype == np.uint8 else f"{np.dtype(dtype).itemsize * 8}-bit"


def _describe(channels: int) -> str:
    kind = {1: "grey", 3: "BGR colour"}.get(channels, "unsupported")
    return f"{channels} channel(s) ({kind})"


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
        try:  # (encoded in memory: any name, and a failed last write is reported)
            write_image_file(path, image)
        except OSError as error:
            raise ValueError(f"{path}: the image could not be written ({error.strerror}: a "
                             "full disk, or no write permission there?)") from None
    return count


def _longest_increasing(t: np.ndarray) -> np.ndarray:
    """(N,) bool: the finite entries of `t` in a longest strictly increasing subsequence
    (patience sorting, O(N log N))."""
    tails: list[float] = []  # the least last value of an increasing run of each length
    tail_at: list[int] = []  # its index
    previous = np.full(t.size, -1)
    for i in np.flatnonzero(np.isfinite(t)):
        k = bisect.bisect_left(tails, t[i])
        if k == len(tails):
            tails.append(t[i])
            tail_at.append(int(i))
        else:
            tails[k], tail_at[k] = t[i], int(i)
        previous[i] = tail_at[k - 1] if k else -1
    keep = np.zeros(t.size, bool)
    i = tail_at[-1] if tail_at else -1
    while i >= 0:
        keep[i] = True
        i = previous[i]
    return keep
