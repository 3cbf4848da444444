"""Pieces shared by the simulators' option dataclasses (FetoscopyOptions, PcleOptions)."""

from __future__ import annotations

from dataclasses import field


def option(default, help_text: str, choices: tuple | None = None):
    """A dataclass field whose default, one-line help and allowed values (used by the CLI) sit
    together."""
    metadata = {"help": help_text}
    if choices is not None:
        metadata["choices"] = choices
    return field(default=default, metadata=metadata)


def check_signs(options, *, positive=(), non_negative=()) -> None:
    """Raise ValueError naming the first field of `positive` not > 0, then of `non_negative`
    not >= 0 (NaN fails both)."""
    cls = type(options).__name__
    for names, ok, rule in ((positive, lambda v: v > 0, "> 0"),
                            (non_negative, lambda v: v >= 0, ">= 0")):
        for name in names:
            value = getattr(options, name)
            if not ok(value):
                raise ValueError(f"{cls}.{name}: must be {rule}, got {value}")
