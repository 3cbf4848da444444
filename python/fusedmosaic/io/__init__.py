"""Reading and writing the dataset and output contracts (see design.md)."""

from fusedmosaic.io.calibration import (
    Camera,
    LensUndistortion,
    UndistortedFrames,
    read_camera_yaml,
    write_camera_yaml,
)
from fusedmosaic.io.dataset import Dataset, read_dataset, write_dataset
from fusedmosaic.io.homographies import (
    read_homographies_csv,
    read_poses_csv,
    write_homographies_csv,
    write_poses_csv,
)
from fusedmosaic.io.output import OutputWriter, to_jsonable
from fusedmosaic.io.tracking import (
    RobotSamples,
    TrackingSamples,
    camera_pose_from_sample,
    interpolate_camera_poses,
    interpolate_robot,
    read_hand_eye,
    read_robot_csv,
    read_tracking_csv,
    write_hand_eye,
    write_robot_csv,
    write_tracking_csv,
)
from fusedmosaic.io.video import FrameSource, write_frames

__all__ = [
    "Camera",
    "Dataset",
    "FrameSource",
    "LensUndistortion",
    "OutputWriter",
    "RobotSamples",
    "TrackingSamples",
    "UndistortedFrames",
    "camera_pose_from_sample",
    "interpolate_camera_poses",
    "interpolate_robot",
    "read_camera_yaml",
    "read_dataset",
    "read_hand_eye",
    "read_homographies_csv",
    "read_poses_csv",
    "read_robot_csv",
    "read_tracking_csv",
    "to_jsonable",
    "write_camera_yaml",
    "write_dataset",
    "write_frames",
    "write_hand_eye",
    "write_homographies_csv",
    "write_poses_csv",
    "write_robot_csv",
    "write_tracking_csv",
]
