"""Review E of compositing (findings 2, 3, 4, 7): the OpenIGTLink mosaic's geometry, grey
video decoded to grey, the creation video's downscaling, the video's frame rate."""

from __future__ import annotations

import socket
import struct
import time

import cv2
import numpy as np
import pyigtl
import pytest

from fusedmosaic.compositing import incremental
from fusedmosaic.compositing.incremental import IncrementalCanvas
from fusedmosaic.compositing.live_view import LiveMosaicView
from fusedmosaic.io.igtl import IgtlImageServer, igtl_image_message, mosaic_ijk_to_world
from fusedmosaic.io.video import FrameSource
from fusedmosaic.runner import playback_rate

W, H = 64, 48
MARK = (5, 7)  # a frame-0 pixel (x, y) marked in the frames below


def _shift(dx: float, dy: float) -> np.ndarray:
    return np.array([[1.0, 0, dx], [0, 1, dy], [0, 0, 1]])


def _marked_frame() -> np.ndarray:
    image = np.full((H, W), 60, np.uint8)
    image[MARK[1], MARK[0]] = 250
    return image


class _Recorder:
    """A server stand-in keeping what LiveMosaicView sends."""
    address, device_name, clients_served, messages_sent = "-", "Mosaic", 0, 0

    def __init__(self) -> None:
        self.sent: list[tuple[np.ndarray, np.ndarray]] = []

    def send(self, image, timestamp=None, *, ijk_to_world=None):
        self.sent.append((image.copy(), ijk_to_world))
        return 0


def _unpack(packed: bytes) -> pyigtl.ImageMessage:
    """A packed message as a receiver (Slicer, pyigtl's client) reads it."""
    header = pyigtl.MessageBase.parse_header(packed[:pyigtl.MessageBase.IGTL_HEADER_SIZE])
    message = pyigtl.MessageBase.create_message(header["message_type"])
    message.unpack(header, packed[pyigtl.MessageBase.IGTL_HEADER_SIZE:])
    return message


def _world(matrix: np.ndarray, i: float, j: float) -> np.ndarray:
    return (np.asarray(matrix, float) @ [i, j, 0.0, 1.0])[:3]


def _published(frames: list[tuple[np.ndarray, np.ndarray]], **kwargs):
    server = _Recorder()
    view = LiveMosaicView(W, H, server=server, interval_s=0.0, **kwargs)
    for image, G in frames:
        view.add(image, G)
    view.close()
    assert view.problems == {} and server.sent
    return view, server.sent[-1]


# -- finding 2: the OpenIGTLink mosaic keeps its place in the world ----------------------------

def test_igtl_mosaic_keeps_reference_pixels_at_one_world_point():
    """Two canvases with different origins (frame 0 alone; frame 0 and a frame up and left of
    it): packed and unpacked, the marked frame-0 pixel and reference pixel (0, 0) are at the
    same world point (mm) in both. Before, every image had pixel (0, 0) at the world's origin
    (pyigtl's identity), so the mosaic jumped by the canvas's growth."""
    worlds, zeros = [], []
    for frames in ([(_marked_frame(), np.eye(3))],
                   [(_marked_frame(), np.eye(3)), (np.full((H, W), 60, np.uint8),
                                                   _shift(-100, -60))]):
        view, (image, M) = _published(frames)
        bx0, by0 = view.canvas.bounds[:2]
        assert view.summary()["origin_reference_px"] == [bx0, by0]
        message = _unpack(igtl_image_message(image, device_name="Mosaic", timestamp=1.0,
                                             ijk_to_world=M).pack())
        pixels = np.asarray(message.image).reshape(image.shape)
        np.testing.assert_array_equal(pixels, image)
        j, i = np.unravel_index(np.argmax(pixels), pixels.shape)
        worlds.append(_world(message.ijk_to_world_matrix, i, j))
        zeros.append(_world(message.ijk_to_world_matrix, -bx0, -by0))
    assert view.canvas.bounds[:2] == (-101, -61)  # the second canvas starts elsewhere
    for world, zero in zip(worlds, zeros, strict=True):
        np.testing.assert_allclose(world, [*MARK, 0.0], atol=1e-4)  # 1 reference px = 1 mm
        np.testing.assert_allclose(zero, [0.0, 0.0, 0.0], atol=1e-4)


def test_igtl_mosaic_geometry_at_a_scale_and_a_physical_pixel_size():
    """scale 0.5 and 2 µm pixels (pCLE's pixel_size_um 2): an image pixel is 4 µm, and
    reference pixel (0, 0) stays at world (0, 0, 0) (pyigtl: ijk are pixel centres; OpenIGTLink
    sends the image centre, which the receiver turns back into the origin)."""
    for frames in ([(_marked_frame(), np.eye(3))],
                   [(_marked_frame(), np.eye(3)), (_marked_frame(), _shift(-90, -40))]):
        view, (image, M) = _published(frames, scale=0.5, pixel_size_mm=0.002)
        summary = view.summary()
        x0, y0 = summary["origin_reference_px"]
        assert (summary["scale"], summary["pixel_size_mm"]) == (0.5, 0.002)
        assert (summary["width"], summary["height"]) == (image.shape[1], image.shape[0])
        assert (x0, y0) == (view.canvas.bounds[0] / 0.5, view.canvas.bounds[1] / 0.5)
        message = _unpack(igtl_image_message(image, device_name="Mosaic", timestamp=1.0,
                                             ijk_to_world=M).pack())
        T = message.ijk_to_world_matrix
        np.testing.assert_allclose(np.linalg.norm(T[:3, :3], axis=0), 0.004, rtol=1e-6)
        # reference pixel (x, y) is image pixel ((x - x0) * 0.5, (y - y0) * 0.5)
        np.testing.assert_allclose(_world(T, -x0 * 0.5, -y0 * 0.5), 0.0, atol=1e-6)
        np.testing.assert_allclose(_world(T, (10 - x0) * 0.5, (20 - y0) * 0.5),
                                   [0.02, 0.04, 0.0], atol=1e-6)


def test_mosaic_ijk_to_world_refuses_bad_values_and_default_is_unchanged():
    with pytest.raises(ValueError, match="pixel_size_mm"):
        mosaic_ijk_to_world((0, 0), 1.0, 0.0)
    with pytest.raises(ValueError, match="scale"):
        mosaic_ijk_to_world((0, 0), np.nan)
    with pytest.raises(ValueError, match="pixel_size_mm"):
        LiveMosaicView(W, H, pixel_size_mm=-1.0)
    image = np.zeros((4, 6, 3), np.uint8)
    plain = igtl_image_message(image, device_name="Mosaic", timestamp=1.0).pack()
    np.testing.assert_array_equal(_unpack(plain).ijk_to_world_matrix, np.eye(4))


def _read_message(client: socket.socket) -> bytes:
    def exactly(n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = client.recv(n - len(data))
            assert chunk, "the server closed the connection"
            data += chunk
        return data
    header = exactly(pyigtl.MessageBase.IGTL_HEADER_SIZE)
    size = struct.unpack("> Q", header[42:50])[0]
    return header + exactly(size)


@pytest.mark.realtime
def test_igtl_server_sends_the_mosaic_geometry():
    """End to end over a socket: the images the server sends are placed so that frame 0's
    marked pixel is at the same world point however far the canvas grew up and left."""
    with IgtlImageServer("127.0.0.1:0") as server:
        client = socket.create_connection(("127.0.0.1", server.port), timeout=10)
        try:
            for _ in range(500):  # until the server has accepted the client
                if server.num_clients:
                    break
                time.sleep(0.01)
            view = LiveMosaicView(W, H, server=server, interval_s=0.0)
            view.add(_marked_frame(), np.eye(3))
            for _ in range(500):  # published (the first view: frame 0 alone)
                if view.published:
                    break
                time.sleep(0.01)
            view.add(np.full((H, W), 60, np.uint8), _shift(-100, -60))
            view.close()
            assert view.published == server.messages_sent == 2
            first, last = _unpack(_read_message(client)), _unpack(_read_message(client))
        finally:
            client.close()
    for message in (first, last):
        pixels = np.asarray(message.image).reshape(message.image.shape[-2:])
        j, i = np.unravel_index(np.argmax(pixels), pixels.shape)
        np.testing.assert_allclose(_world(message.ijk_to_world_matrix, i, j), [*MARK, 0.0],
                                   atol=1e-4)
    assert first.image.shape != last.image.shape


# -- finding 3: a grey video gives grey frames -------------------------------------------------

def _texture(k: int) -> np.ndarray:
    rng = np.random.default_rng(k)
    return cv2.GaussianBlur(rng.integers(0, 256, (H, W), np.uint8), (0, 0), 1.5)


def _write_video(path, frames, fourcc: str = "MJPG", colour: bool = True):
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 25.0, (W, H),
                             isColor=colour)
    if not writer.isOpened():
        pytest.skip(f"no {fourcc} writer in this OpenCV")
    for f in frames:
        writer.write(f)
    writer.release()
    return path


def _decoded(path) -> list[np.ndarray]:
    capture = cv2.VideoCapture(str(path))
    out = []
    while True:
        ok, image = capture.read()
        if not ok:
            break
        out.append(image)
    capture.release()
    return out


def test_grey_mjpg_video_reads_as_grey(tmp_path):
    """MJPG written with isColor=False: OpenCV reports I420 and decodes 3 equal channels; the
    frames are read as their grey plane (channel 0), as grey PNG frames would be, whichever
    frame is read first."""
    path = _write_video(tmp_path / "video.avi", [_texture(k) for k in range(12)], colour=False)
    bgr = _decoded(path)
    assert bgr[0].ndim == 3 and all((f[:, :, 0] == f[:, :, 2]).all() for f in bgr)
    for first in (0, 7):
        source = FrameSource(video=path, expected_size=(W, H))
        image = source[first]
        assert source.video_grey is True
        assert image.shape == (H, W) and image.dtype == np.uint8
        np.testing.assert_array_equal(image, bgr[first][:, :, 0])
        assert all(source[k].shape == (H, W) for k in range(len(source)))


def test_grey_ffv1_video_reads_as_grey(tmp_path):
    """FFV1 grey (pixel format Y800): grey by its pixel format."""
    path = _write_video(tmp_path / "video.avi", [_texture(k) for k in range(4)], "FFV1",
                        colour=False)
    source = FrameSource(video=path)
    np.testing.assert_array_equal(source[2], _texture(2))  # (lossless)
    assert source.video_grey is True


def test_a_black_or_grey_frame_does_not_make_a_colour_video_grey(tmp_path):
    """Decided once for the video, not per frame: a colour video whose first frame is black
    and another grey stays BGR in every frame (no 'all grey or all colour' error); an
    all-black video too (nothing says it is grey)."""
    colour = [cv2.merge([_texture(k), _texture(k + 50), _texture(k + 99)]) for k in range(10)]
    colour[0][:] = 0
    colour[5] = cv2.cvtColor(_texture(5), cv2.COLOR_GRAY2BGR)
    path = _write_video(tmp_path / "video.avi", colour, "FFV1")
    source = FrameSource(video=path)
    assert [source[k].shape for k in range(10)] == [(H, W, 3)] * 10
    assert source.video_grey is False
    black = _write_video(tmp_path / "black.avi", [np.zeros((H, W), np.uint8)] * 4,
                         colour=False)
    source = FrameSource(video=black)
    assert source[0].shape == (H, W, 3) and source.video_grey is False


def test_png_frames_are_not_sampled(tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    cv2.imwrite(str(frames / "0.png"), cv2.cvtColor(_texture(0), cv2.COLOR_GRAY2BGR))
    source = FrameSource.open(tmp_path)
    assert source[0].shape == (H, W, 3) and source.video_grey is None


# -- finding 4: a canvas below the frames' resolution is area-averaged -------------------------

def test_downscaled_canvas_is_area_averaged_not_point_sampled():
    """Vertical stripes of period 2 (0 / 255) at scale 0.25: area averaging gives their mean,
    ~128, inside the footprint (linear: within a few grey levels near the edge, where the
    feathering weights of neighbouring columns differ). Warping the full-size frame
    point-sampled them: every canvas pixel fell on a 0 stripe (x = 4 c), a black mosaic."""
    image = np.zeros((96, 128), np.uint8)
    image[:, 1::2] = 255
    for blend in ("linear", "average", "last"):
        canvas = IncrementalCanvas(128, 96, blend=blend, scale=0.25)
        canvas.add(image, _shift(8, 4))
        inside = canvas.render()[2:-2, 2:-2].astype(float)
        assert abs(inside.mean() - 127.5) < 1.0, blend
        assert np.abs(inside - 127.5).max() < (20 if blend == "linear" else 1), blend


def test_downscaled_canvas_keeps_the_geometry():
    """A linear ramp (area averaging keeps its value at each pixel's centre) placed by a
    rotation, translation and zoom, at scales 0.5 and 0.3: each canvas pixel c holds the ramp
    at frame point G^-1(c / scale) (a half-pixel error in the shrunk grid's map would be 2-4
    grey levels off), and the covered area is the footprint's."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    a, b, c0 = 3.0, 1.0, 5.0
    image = np.clip(np.rint(a * x + b * y + c0), 0, 255).astype(np.uint8)
    angle = np.deg2rad(10)
    G = np.array([[1.2 * np.cos(angle), -1.2 * np.sin(angle), 13.3],
                  [1.2 * np.sin(angle), 1.2 * np.cos(angle), -7.7], [0, 0, 1]])
    for scale in (0.5, 0.3):
        canvas = IncrementalCanvas(W, H, blend="linear", scale=scale)
        canvas.add(image, G)
        view = canvas.render().astype(float)
        j, i = np.mgrid[0:view.shape[0], 0:view.shape[1]]
        x0, y0 = canvas.bounds[:2]
        ref = np.stack([(i + x0) / scale, (j + y0) / scale, np.ones(i.shape)], -1)
        src = ref @ np.linalg.inv(G).T
        sx, sy = src[..., 0] / src[..., 2], src[..., 1] / src[..., 2]
        m = 2 / scale + 1  # (the frame's edge: 2 canvas pixels)
        inside = (sx > m) & (sx < W - 1 - m) & (sy > m) & (sy < H - 1 - m)
        error = (view - (a * sx + b * sy + c0))[inside]
        # measured: mean 0.01 / -0.02, max 1.0 / 1.5 (rounding); the shrunk grid mapped
        # without its half-pixel shift: mean 2.0 / 4.7
        assert inside.sum() > 150 and abs(error.mean()) < 0.3, scale
        assert np.abs(error).max() < 2.0, scale
        covered = (view > 0).sum()  # (the ramp is > 0)
        footprint, rim = W * H * (1.2 * scale) ** 2, 2 * (W + H) * 1.2 * scale
        assert footprint - rim < covered < footprint + rim, scale


def test_canvas_at_scale_one_or_more_is_warped_as_before(monkeypatch):
    """scale >= 1 keeps the full-size warp (bit-identical to FrameWarper.warp's patches)."""
    def refuse(*args, **kwargs):
        raise AssertionError("shrunk at scale >= 1")

    monkeypatch.setattr(incremental, "_warp_shrunk", refuse)
    for scale in (1.0, 1.5):
        canvas = IncrementalCanvas(W, H, blend="linear", scale=scale)
        canvas.add(_texture(0), _shift(3.3, 2.2))
        canvas.add(_texture(1), _shift(20.7, 9.1))
        assert canvas.frames_added == 2


def test_downscaled_colour_canvas_with_a_mask_and_gain():
    """Colour, a circular field of view and a gain: each canvas pixel inside is the area mean
    of the (gained) frame's pixels under it, within a grey level, away from the edge."""
    rng = np.random.default_rng(3)
    image = rng.integers(0, 200, (192, 256, 3), np.uint8)
    mask = np.zeros((192, 256), np.uint8)
    cv2.circle(mask, (128, 96), 90, 255, -1)
    canvas = IncrementalCanvas(256, 192, mask=mask, blend="average", scale=0.25)
    canvas.add(image, np.eye(3), gain=1.2)
    view = canvas.render().astype(float)
    # view pixel i is canvas pixel i + x0, frame point 4 (i + x0); shrunk pixel u is frame
    # point 4 u + 1.5: u = i + x0 - 0.375
    x0, y0 = canvas.bounds[:2]
    M = np.float32([[1, 0, 0.375 - x0], [0, 1, 0.375 - y0]])

    def shrunk(a):
        return cv2.warpAffine(cv2.resize(a, (64, 48), interpolation=cv2.INTER_AREA), M,
                              (view.shape[1], view.shape[0]))

    expected = shrunk(np.clip(image * 1.2, 0, 255).astype(np.float32))
    inner = cv2.erode(shrunk(mask.astype(np.float32)), None, iterations=2) > 254.5
    assert inner.sum() > 1000
    assert np.abs(view - expected).max(axis=2)[inner].max() < 1.0


# -- finding 7: the video's frame rate --------------------------------------------------------

def test_playback_rate_is_rounded():
    """frames.csv at 25 frames/s (0.04 s steps, written as decimals) gave 24.99999999999998."""
    times = np.array([float(f"{k * 0.04:.2f}") for k in range(40)])
    assert repr(playback_rate(times)) == "25.0"
    assert repr(playback_rate(np.array([float(f"{k * 0.1:.1f}") for k in range(288)]))) == "10.0"
    assert playback_rate(np.arange(4) / 30.0) == 30.0
    assert playback_rate(np.arange(4) * 0.06) == 16.6667
