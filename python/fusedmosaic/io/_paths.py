"""File names handed to OpenCV.

On Linux a file name is bytes; one that is not UTF-8 (a Latin-1 'é' from a Windows share, an old
ZIP, a USB stick) reaches Python with each such byte as a lone surrogate ('\\udce9'). OpenCV's
Python bindings convert a path to UTF-8 without checking the result and dereference NULL on
such a name: cv2.imread, cv2.FileStorage, cv2.VideoCapture and cv2.VideoWriter died with
SIGSEGV (exit 139, no message, staging folders left behind; review 47). Files that Python can
read for OpenCV are read so (camera.yaml, PNG frames with such a name); a video, which only
OpenCV opens, is refused by name with opencv_path.
"""

from __future__ import annotations

from pathlib import Path, PurePath


def is_utf8(path: str | PurePath) -> bool:
    """The name encodes as UTF-8 (as OpenCV needs it): no lone surrogate in it."""
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def shown_path(path: str | PurePath) -> str:
    """The name for messages, each byte that is not UTF-8 written ``\\xe9`` (as on disk; a lone
    surrogate that is no such byte, ``\\ud800``): printable whatever the terminal's encoding."""
    return "".join(_shown_char(c) for c in str(path))


def _shown_char(c: str) -> str:
    code = ord(c)
    if 0xDC80 <= code <= 0xDCFF:  # surrogateescape's stand-in for the byte code - 0xDC00
        return f"\\x{code - 0xDC00:02x}"
    if 0xD800 <= code <= 0xDFFF:
        return f"\\u{code:04x}"
    return c


def opencv_path(path: str | PurePath, action: str = "open a file") -> str:
    """``str(path)`` to give OpenCV, or ValueError naming the file when its name (the file's or
    a folder's on its path) is not UTF-8: OpenCV cannot ``action`` ("read a video") by such a
    name, and crashes when asked to."""
    name = str(path)
    if is_utf8(name):
        return name
    raise ValueError(not_utf8_message(path, f"OpenCV cannot {action} by such a name"))


def not_utf8_message(path: str | PurePath, consequence: str) -> str:
    """"<path>: the folder name '<part>' is not UTF-8 (...), and <consequence>; rename it",
    naming the first part of the path (a folder's name or the file's) that is not UTF-8."""
    part = next((p for p in Path(path).parts if not is_utf8(p)), str(path))
    codes = list(dict.fromkeys(_shown_char(c) for c in part if not is_utf8(c)))
    which = "file" if part == Path(path).name else "folder"
    held = f"the byte {codes[0]}" if len(codes) == 1 else f"the bytes {', '.join(codes)}"
    return (f"{shown_path(path)}: the {which} name '{shown_path(part)}' is not UTF-8 ({held}: "
            f"Latin-1 or another legacy encoding?), and {consequence}; rename it")
