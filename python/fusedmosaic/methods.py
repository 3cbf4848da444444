"""The registry of mosaicking methods behind `fusedmosaic run --method M`.

Each method is a function `(dataset, *, progress, options=None) -> MethodResult` in its own
module of `fusedmosaic.estimation`; the registry maps the CLI name to "module:function" so that
running one method does not import the others.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

# CLI name -> (module:function, what the paper calls it). Order = preference for the demo.
REGISTRY: dict[str, tuple[str, str]] = {
    "lba-emt": ("fusedmosaic.estimation.sequential:run_lba_emt", "LBAVis+EMT"),
    "ba-emt": ("fusedmosaic.estimation.bundle:run_ba_emt", "BAVis+EMT"),
    "ba": ("fusedmosaic.estimation.bundle:run_ba", "BAVis"),
    "emt": ("fusedmosaic.estimation.bundle:run_emt", "EMT poses + estimated plane"),
    "pairwise": ("fusedmosaic.estimation.pairwise:run_pairwise", "PairVis"),
    "kalman-robot": (
        "fusedmosaic.estimation.translation:run_kalman_robot",
        "X_f (robot-prior Kalman)",
    ),
    "ncc": ("fusedmosaic.estimation.translation:run_ncc", "X_m (NCC chain)"),
    "robot": ("fusedmosaic.estimation.translation:run_robot", "X_r (robot only)"),
}


@dataclass
class MethodResult:
    """What a method hands to the output writer.

    homographies: (N, 3, 3) frame -> reference, all-NaN rows for frames that could not be placed.
    status: per frame, "placed", "prior-only" (placed from priors without visual evidence),
        "dead-reckoned" (lba-emt, ba-emt: placed with no anchor at all, see FrameResult),
        "prior-only (solver failed)" (lba-emt: its window step could not be solved; composed
        as prior-only) or "unplaced: <reason>".
    """

    homographies: np.ndarray
    status: list[str]
    poses: np.ndarray | None = None  # (N, 6) cam_from_world
    plane: np.ndarray | None = None  # (3,) pi = n / d
    timings: dict[str, float] = field(default_factory=dict)  # stage -> seconds
    parameters: dict = field(default_factory=dict)
    details: dict = field(default_factory=dict)  # method-specific report entries
    # how run composes mosaic.png by default: "linear" (seed 000, Sec. 4.2), "average" (seed 004)
    blend: str = "linear"
    # The homographies hold between undistorted pixels (camera.yaml's lens distortion removed
    # from the keypoints), so the mosaic is composed from undistorted frames; False: raw pixels
    # (the translation methods register raw frames by NCC). Same thing without distortion.
    undistorted: bool = True
    # run's default for BlendOptions.mask_specular: specular highlights (saturated white spots
    # fixed to the camera) are not pasted into the mosaic; pCLE's confocal frames have none.
    mask_specular: bool = True
    # The method looked at every frame it calls "placed" (False: emt places from the tracker
    # alone): run checks the others for a black image before pasting them into the mosaic.
    images_seen: bool = True


def ms_stats(values_ms) -> dict | None:
    """{"median", "p95", "max"} of per-frame times in ms (report.json), None without any."""
    values_ms = np.asarray(values_ms, dtype=np.float64)
    if values_ms.size == 0:
        return None
    return {"median": float(np.median(values_ms)), "p95": float(np.percentile(values_ms, 95)),
            "max": float(values_ms.max())}


def listed_ids(ids, shown: int = 10) -> str:
    """The first ``shown`` frame ids, comma-separated, then ", ... (N more)": how the methods'
    warnings name a set of frames."""
    ids = [int(k) for k in ids]
    more = f", ... ({len(ids) - shown} more)" if len(ids) > shown else ""
    return ", ".join(map(str, ids[:shown])) + more


def available() -> list[str]:
    """Registered names, best first (the demo runs the first)."""
    return list(REGISTRY)


def get(name: str) -> Callable[..., MethodResult]:
    if name not in REGISTRY:
        known = ", ".join(REGISTRY) or "none yet"
        raise ValueError(f"unknown method {name!r}; available: {known}")
    module, func = REGISTRY[name][0].split(":")
    return getattr(importlib.import_module(module), func)
