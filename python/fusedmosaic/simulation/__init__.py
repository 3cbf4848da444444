"""Simulators with exact ground truth: the fetoscopy SYN replica (+ hand-held variant) of paper
000 and the robot-scanned pCLE setup of paper 004, their procedural textures, and image-free
geometric scenes (poses, plane, exact correspondences) for the solver core; and tracked
checkerboard recordings for calibrating the camera and the hand-eye transform."""

from fusedmosaic.simulation.checkerboard import (
    CheckerboardOptions,
    CheckerboardScene,
    generate_checkerboard,
    simulate_checkerboard,
)
from fusedmosaic.simulation.fetoscopy import (
    PAPER_BLACK_FRAMES,
    FetoscopyOptions,
    FetoscopyScene,
    frame_to_reference_truth,
    generate_fetoscopy,
    induced_homographies,
    simulate_fetoscopy,
)
from fusedmosaic.simulation.geometric import circle_scene, plane_point_pairs
from fusedmosaic.simulation.pcle import PcleOptions, PcleScene, generate_pcle, simulate_pcle
from fusedmosaic.simulation.textures import cell_texture, fibre_bundle_pattern, placenta_texture

__all__ = [
    "CheckerboardOptions",
    "CheckerboardScene",
    "PAPER_BLACK_FRAMES",
    "FetoscopyOptions",
    "FetoscopyScene",
    "PcleOptions",
    "PcleScene",
    "cell_texture",
    "circle_scene",
    "fibre_bundle_pattern",
    "frame_to_reference_truth",
    "generate_checkerboard",
    "generate_fetoscopy",
    "generate_pcle",
    "induced_homographies",
    "placenta_texture",
    "plane_point_pairs",
    "simulate_checkerboard",
    "simulate_fetoscopy",
    "simulate_pcle",
]
