"""Placing frames on a mosaic canvas."""

from fusedmosaic.compositing.canvas import CanvasTooLargeError, canvas_bounds, compose_mosaic

__all__ = ["CanvasTooLargeError", "canvas_bounds", "compose_mosaic"]
