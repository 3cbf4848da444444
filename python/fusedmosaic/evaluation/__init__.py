"""Accuracy metrics of seed 000 (Eq. 28-29) and seed 004 (position statistics)."""

from fusedmosaic.evaluation.metrics import (
    PositionStats,
    compare_position_errors,
    drift_ratio,
    evaluate_output,
    frame_errors,
    grid_points,
    mosaic_difference,
    mosaic_error,
    position_errors_um,
    position_stats,
)

__all__ = [
    "PositionStats",
    "compare_position_errors",
    "drift_ratio",
    "evaluate_output",
    "frame_errors",
    "grid_points",
    "mosaic_difference",
    "mosaic_error",
    "position_errors_um",
    "position_stats",
]
