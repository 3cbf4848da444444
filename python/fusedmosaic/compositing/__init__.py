"""Placing frames on a mosaic canvas: blending (linear + border, multi-band, average, last, gain
compensation), one-piece and tiled rendering, a live incremental canvas, and creation videos."""

from fusedmosaic.compositing.blending import (
    BLENDS,
    BlendOptions,
    FrameWarper,
    SpecularMasks,
    compensate_gains,
)
from fusedmosaic.compositing.canvas import (
    CanvasOptions,
    CanvasPlan,
    CanvasTooLargeError,
    NoFrameToComposeError,
    RenderedMosaic,
    canvas_bounds,
    compose_mosaic,
    frame_gains,
    plan_canvas,
    render_mosaic,
    screen_frames,
    usable_frames,
    write_mosaic_png,
)
from fusedmosaic.compositing.incremental import IncrementalCanvas
from fusedmosaic.compositing.png import PngStreamWriter
from fusedmosaic.compositing.video import MosaicVideoWriter, write_creation_video

__all__ = [
    "BLENDS",
    "BlendOptions",
    "CanvasOptions",
    "CanvasPlan",
    "CanvasTooLargeError",
    "FrameWarper",
    "IncrementalCanvas",
    "MosaicVideoWriter",
    "NoFrameToComposeError",
    "PngStreamWriter",
    "RenderedMosaic",
    "SpecularMasks",
    "canvas_bounds",
    "compensate_gains",
    "compose_mosaic",
    "frame_gains",
    "plan_canvas",
    "render_mosaic",
    "screen_frames",
    "usable_frames",
    "write_creation_video",
    "write_mosaic_png",
]
