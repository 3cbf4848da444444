"""Camera intrinsics: ``camera.yaml`` in OpenCV FileStorage format (dataset contract)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np


@dataclass(eq=False)
class Camera:
    """Image size and optional intrinsics of the endoscope camera.

    camera_matrix : (3, 3) float64 K, needed by the pose methods only.
    distortion : (k,) OpenCV distortion coefficients, or None.
    pixel_size_um : µm per pixel (pCLE robot methods convert robot µm to pixels with it).
    fov_mask_radius : px, radius of the circular field of view centred on the image centre.
    source : where the camera came from, used in error messages.
    """

    width: int
    height: int
    camera_matrix: np.ndarray | None = None
    distortion: np.ndarray | None = None
    pixel_size_um: float | None = None
    fov_mask_radius: float | None = None
    source: str = field(default="camera.yaml", compare=False, repr=False)

    def __post_init__(self) -> None:
        if int(self.width) != self.width or int(self.height) != self.height:
            raise ValueError(
                f"{self.source}: image size must be integer, got {self.width}x{self.height}"
            )
        self.width, self.height = int(self.width), int(self.height)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(
                f"{self.source}: image size must be positive, got {self.width}x{self.height}"
            )
        if self.camera_matrix is not None:
            K = np.asarray(self.camera_matrix, dtype=np.float64)
            if K.shape != (3, 3):
                got = "x".join(map(str, K.shape)) if K.ndim == 2 else f"shape {K.shape}"
                raise ValueError(f"{self.source}: camera_matrix: expected a 3x3 matrix, got {got}")
            if not np.all(np.isfinite(K)):
                raise ValueError(f"{self.source}: camera_matrix contains NaN or inf")
            if K[0, 0] <= 0 or K[1, 1] <= 0:
                raise ValueError(
                    f"{self.source}: camera_matrix: focal lengths must be positive, "
                    f"got fx={K[0, 0]!r}, fy={K[1, 1]!r}"
                )
            self.camera_matrix = K
        if self.distortion is not None:
            d = np.asarray(self.distortion, dtype=np.float64).reshape(-1)
            if not np.all(np.isfinite(d)):
                raise ValueError(f"{self.source}: distortion_coefficients contain NaN or inf")
            self.distortion = d
        for name in ("pixel_size_um", "fov_mask_radius"):
            value = getattr(self, name)
            if value is not None:
                value = float(value)
                if not np.isfinite(value) or value <= 0:
                    raise ValueError(f"{self.source}: {name} must be positive, got {value!r}")
                setattr(self, name, value)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.width, self.height

    def fov_mask(self) -> np.ndarray | None:
        """(H, W) uint8 mask, 255 inside the circular field of view; None without a radius."""
        if self.fov_mask_radius is None:
            return None
        y, x = np.ogrid[: self.height, : self.width]
        cx, cy = (self.width - 1) / 2.0, (self.height - 1) / 2.0
        inside = (x - cx) ** 2 + (y - cy) ** 2 <= self.fov_mask_radius**2
        return np.where(inside, np.uint8(255), np.uint8(0))

    def require_camera_matrix(self, method: str) -> np.ndarray:
        """Return K, or raise naming the file and the method that needs it."""
        if self.camera_matrix is None:
            raise ValueError(
                f"{self.source}: no camera_matrix; method {method!r} needs the camera intrinsics"
            )
        return self.camera_matrix

    def require_pixel_size(self, method: str) -> float:
        """Return pixel_size_um, or raise naming the file and the method that needs it."""
        if self.pixel_size_um is None:
            raise ValueError(
                f"{self.source}: no pixel_size_um; method {method!r} needs the "
                "pixel size to convert robot positions (µm) to pixels"
            )
        return self.pixel_size_um


def read_camera_yaml(path: str | Path) -> Camera:
    """Read ``camera.yaml`` (keys: image_width, image_height, [camera_matrix,
    distortion_coefficients, pixel_size_um, fov_mask_radius])."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: file not found")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        opened = fs.isOpened() and fs.root().isMap()
    except Exception as e:  # cv2.error, or SystemError wrapping it
        raise ValueError(f"{path}: cannot parse as OpenCV FileStorage YAML ({e})") from None
    if not opened:
        raise ValueError(f"{path}: cannot parse as OpenCV FileStorage YAML")
    try:

        def number(key: str, required: bool = False) -> float | None:
            node = fs.getNode(key)
            if node.empty() or node.isNone():
                if required:
                    raise ValueError(f"{path}: missing key {key!r}")
                return None
            if not (node.isInt() or node.isReal()):
                raise ValueError(f"{path}: {key}: expected a number")
            value = node.real()
            if np.isnan(value):
                raise ValueError(f"{path}: {key} is NaN")
            return value

        def matrix(key: str) -> np.ndarray | None:
            node = fs.getNode(key)
            if node.empty() or node.isNone():
                return None
            if node.isSeq():  # plain YAML list; 9 numbers are read as a row-major 3x3
                values = np.array([node.at(i).real() for i in range(node.size())])
                return values.reshape(3, 3) if values.size == 9 else values[None, :]
            mat = node.mat() if node.isMap() else None
            if mat is None:
                raise ValueError(f"{path}: {key}: expected an !!opencv-matrix or a list")
            return np.asarray(mat, dtype=np.float64)

        return Camera(
            width=number("image_width", required=True),
            height=number("image_height", required=True),
            camera_matrix=matrix("camera_matrix"),
            distortion=matrix("distortion_coefficients"),
            pixel_size_um=number("pixel_size_um"),
            fov_mask_radius=number("fov_mask_radius"),
            source=str(path),
        )
    finally:
        fs.release()


def write_camera_yaml(path: str | Path, camera: Camera) -> None:
    """Write ``camera`` as OpenCV FileStorage YAML (readable by cv2 and read_camera_yaml)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("image_width", int(camera.width))
        fs.write("image_height", int(camera.height))
        if camera.camera_matrix is not None:
            fs.write("camera_matrix", np.asarray(camera.camera_matrix, dtype=np.float64))
        if camera.distortion is not None:
            fs.write(
                "distortion_coefficients",
                np.asarray(camera.distortion, dtype=np.float64).reshape(1, -1),
            )
        if camera.pixel_size_um is not None:
            fs.write("pixel_size_um", float(camera.pixel_size_um))
        if camera.fov_mask_radius is not None:
            fs.write("fov_mask_radius", float(camera.fov_mask_radius))
    finally:
        fs.release()
