"""Simulators with exact ground truth: the fetoscopy SYN replica (+ hand-held variant) of paper
000 and the robot-scanned pCLE setup of paper 004, and their procedural textures."""

from fusedmosaic.simulation.fetoscopy import (
    PAPER_BLACK_FRAMES,
    FetoscopyOptions,
    FetoscopyScene,
    frame_to_reference_truth,
    generate_fetoscopy,
    induced_homographies,
    simulate_fetoscopy,
)
from fusedmosaic.simulation.pcle import PcleOptions, PcleScene, generate_pcle, simulate_pcle
from fusedmosaic.simulation.textures import cell_texture, fibre_bundle_pattern, placenta_texture

__all__ = [
    "PAPER_BLACK_FRAMES",
    "FetoscopyOptions",
    "FetoscopyScene",
    "PcleOptions",
    "PcleScene",
    "cell_texture",
    "fibre_bundle_pattern",
    "frame_to_reference_truth",
    "generate_fetoscopy",
    "generate_pcle",
    "induced_homographies",
    "placenta_texture",
    "simulate_fetoscopy",
    "simulate_pcle",
]
