"""Type stubs for fusedmosaic._core, the C++ core (cpp/bindings).

Conventions (seed 000, Sec. 3): a pose is ``[rx, ry, rz, tx, ty, tz]``, angle-axis (rad) and
translation (mm) of cam_from_world (X_cam = R X_world + t); the plane is ``pi = n / d`` (1/mm),
the plane ``n.X + d = 0`` seen from the virtual camera at the world origin. All arrays are
float64 unless stated. Bad input raises ValueError (IndexError for an unknown frame id). A
(6,) pose or (3,) plane may also be given as a (6, 1) column or (1, 6) row; any other shape is
refused naming the argument and the shape got. pi = 0 (the plane at infinity) is refused.
"""

from typing import Any

import numpy as np
import numpy.typing as npt
from typing_extensions import Never  # (typing.Never: Python 3.11 on; stubs may use this)

__version__: str

_Array = npt.NDArray[np.float64]
_IntArray = npt.NDArray[np.int32]
_Float32Array = npt.NDArray[np.float32]
_ArrayLike = npt.ArrayLike

# ---------------------------------------------------------------- geometry (bind_geometry.cc)

def rotation_from_angle_axis(angle_axis: _ArrayLike) -> _Array:
    """R = exp([r]_x).

    angle_axis : (3,) radians. Returns (3, 3).
    """

def angle_axis_from_rotation(rotation: _ArrayLike) -> _Array:
    """Angle-axis vector (3,) of a rotation matrix.

    rotation : (3, 3), orthonormal with det +1.
    """

def compose_poses(c_from_b: _ArrayLike, b_from_a: _ArrayLike) -> _Array:
    """c_from_a = c_from_b * b_from_a.

    c_from_b, b_from_a : (6,) poses. Returns (6,).
    """

def invert_pose(b_from_a: _ArrayLike) -> _Array:
    """a_from_b.

    b_from_a : (6,) pose. Returns (6,).
    """

def camera_plane_distance(cam_from_world: _ArrayLike, plane: _ArrayLike) -> float:
    """Distance (mm) from the camera centre to the plane.

    cam_from_world : (6,); plane : (3,) pi = n / d, non-zero.
    """

def induced_homography(
    cam_from_world: _ArrayLike, plane: _ArrayLike, camera_matrix: _ArrayLike | None = None
) -> _Array:
    """H_k = K (R - t pi^T) K^-1 (Eq. 5): virtual-camera pixels -> frame-k pixels.

    cam_from_world : (6,); plane : (3,); camera_matrix : (3, 3) or None (normalised
    coordinates). Returns (3, 3).
    """

def transfer_homography(
    cam_l_from_world: _ArrayLike,
    cam_m_from_world: _ArrayLike,
    plane: _ArrayLike,
    camera_matrix: _ArrayLike | None = None,
) -> _Array:
    """H_l H_m^-1 (Eq. 13): frame-m points -> frame-l points, normalised to H[2, 2] = 1.

    cam_l_from_world, cam_m_from_world : (6,); plane : (3,); camera_matrix : (3, 3) or None.
    Returns (3, 3).
    """

def transfer_points(
    points: _ArrayLike,
    cam_l_from_world: _ArrayLike,
    cam_m_from_world: _ArrayLike,
    plane: _ArrayLike,
    camera_matrix: _ArrayLike | None = None,
) -> _Array:
    """Transfers points of frame m into frame l through the plane (Eq. 13).

    points : (N, 2) pixels (normalised coordinates when camera_matrix is None).
    Returns (N, 2).
    """

def frame_to_reference(
    cams_from_world: _ArrayLike, plane: _ArrayLike, camera_matrix: _ArrayLike, reference: int = 0
) -> _Array:
    """Frame -> reference pixel homographies G_k = H_ref H_k^-1, each with G[2, 2] = 1.

    cams_from_world : (N, 6); plane : (3,); camera_matrix : (3, 3); reference : row index
    (IndexError outside [0, N)). Returns (N, 3, 3).
    """

# ---------------------------------------------------------------- residuals (bind_residuals.cc)

DEFAULT_EMT_SIGMA: _Array
"""(6,) EMT prior standard deviations [0.017 rad x3, 1 mm x3] (appendix Eq. 30)."""

DEFAULT_MOTION_SIGMA: _Array
"""(6,) constant-velocity prior standard deviations [0.0044 rad x3, 15.2178 mm x3] (Eq. 30)."""

def evaluate_visual_transfer(
    cam_l_from_world: _ArrayLike,
    cam_m_from_world: _ArrayLike,
    plane: _ArrayLike,
    points_l: _ArrayLike,
    points_m: _ArrayLike,
    camera_matrix: _ArrayLike,
    sigma_v_px: float = 1.0,
    loss: str = "none",
    loss_scale_px: float = 2.0,
    jacobians: str = "analytic",
    fixed_cameras: str = "none",
    condense: bool = False,
) -> tuple[_Array, tuple[_Array, ...]]:
    """Visual transfer residual (Eq. 13, 18) of one pair block and its Jacobians.

    points_l, points_m : (N, 2) pixels, row i of points_m transfers to row i of points_l.
    loss : 'none' | 'huber' | 'cauchy', applied per point (|r_i'|^2 = rho(|r_i|^2)).
    jacobians : 'analytic' (the solvers' cost function) | 'autodiff' (ceres::AutoDiffCostFunction
    of the same functor, the reference) | 'none' (residuals only, an empty tuple).
    fixed_cameras : 'none' | 'l' | 'm' | 'both': cameras that are constants of the block, as in
    a sliding-window step (no Jacobian is returned for them).
    condense : the condensed form (P + 1 residuals, P free parameters, with the pair's J^T J,
    J^T r and cost; residuals only: [0, ..., 0, |r|]).
    Returns (residuals (2N,), (J_l (2N, 6), J_m (2N, 6), J_plane (2N, 3))); residuals are
    (mu - p_l) / sigma_v interleaved x, y per point.
    """

def crc64(data: Any) -> int:
    """CRC-64/ECMA-182 of a contiguous buffer (bytes, bytearray, memoryview, a C-contiguous
    array), OpenIGTLink's message body check: polynomial 0x42F0E1EBA9EA3693, MSB first, initial
    value 0, no final xor. The GIL is released while it runs. TypeError for what is not a
    buffer (a str); ValueError / BufferError for one that is not contiguous.
    """

def match_hamming(
    query: _ArrayLike, train: _ArrayLike, ratio: float = 0.8
) -> tuple[_IntArray, _IntArray, _IntArray]:
    """Exact Hamming nearest neighbours of binary descriptors, ratio test, one-to-one.

    query : (Nq, B) uint8, train : (Nt, B) uint8 (ORB: B = 32; another dtype: ValueError, not
    a cast); ratio in (0, 1]. Row counts and B above 2**31 - 1: ValueError.
    Returns (query_idx, train_idx, distance), int32, of the kept matches, ascending query
    order: a query is kept if its nearest train descriptor is nearer than ratio x the second
    nearest, and of the queries kept for one train descriptor only the nearest (the first on a
    tie). The matches of
    cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(k=2) with these filters, counted with popcount.
    """

def match_hamming_guided(
    query: _ArrayLike,
    query_xy: _ArrayLike,
    train: _ArrayLike,
    train_xy: _ArrayLike,
    radius: float,
    ratio: float = 0.8,
    max_distance: int = -1,
) -> tuple[_IntArray, _IntArray, _IntArray]:
    """match_hamming restricted to train keypoints within `radius` px of each query's predicted
    position query_xy (Nq, 2) in the train image (non-finite: not matched); train_xy (Nt, 2).
    The ratio test compares the two nearest candidates in the radius; a single candidate is
    kept if its distance <= max_distance bits, or, with max_distance < 0 (default), if it
    passes the ratio test against the nearest of all the other train descriptors (what the
    exhaustive match_hamming tests it against). Same input rules and output as match_hamming.
    """

def match_l2_guided(
    query: _ArrayLike,
    query_xy: _ArrayLike,
    train: _ArrayLike,
    train_xy: _ArrayLike,
    radius: float,
    ratio: float = 0.8,
    max_distance: float = -1.0,
) -> tuple[_IntArray, _IntArray, _Float32Array]:
    """match_hamming_guided for float descriptors (SIFT) under the Euclidean distance.

    query : (Nq, D), train : (Nt, D), converted to float32; query_xy, train_xy, radius, ratio
    and max_distance (< 0: the ratio test against all other train rows) as in
    match_hamming_guided, distances in descriptor units. The ratio test compares Euclidean
    distances (as cv2.BFMatcher(cv2.NORM_L2)'s). Returns (query_idx, train_idx, distance):
    int32, int32, float32, ascending query order. A descriptor with a non-finite element
    matches nothing; so does one whose squared distances leave float32's range (elements
    from about 2e19 overflow, below about 1e-22 the distances underflow to ties): scale such
    descriptors first (SIFT's are 0-512).
    """

def evaluate_pose_prior(
    cam_from_world: _ArrayLike, measurement: _ArrayLike, sigma: _ArrayLike = ...
) -> tuple[_Array, tuple[_Array]]:
    """EMT pose prior (Eq. 19): residuals S (x - z), S = diag(1 / sigma); the rotation part
    with z's angle-axis vector the one of its rotation nearest x's (near |r| = pi one rotation
    has two vectors 2 pi apart), else the plain difference.

    cam_from_world, measurement : (6,); sigma : (6,) standard deviations (default
    DEFAULT_EMT_SIGMA). Returns (residuals (6,), (J (6, 6),)).
    """

def evaluate_constant_velocity(
    cam_km2_from_world: _ArrayLike,
    cam_km1_from_world: _ArrayLike,
    cam_k_from_world: _ArrayLike,
    sigma: _ArrayLike = ...,
    ratio: float = 1.0,
) -> tuple[_Array, tuple[_Array, _Array, _Array]]:
    """Constant-velocity prior (Eq. 15, 16, 20): S_p (x_k - mu_p), the rotation part with
    mu_p's angle-axis vector the one of its rotation nearest x_k's (as evaluate_pose_prior).

    mu_p = T_{k-1} T_{k-2}^-1 T_{k-1} (poses as rigid transforms); with ratio != 1 (frames not
    evenly spaced, (t_k - t_{k-1}) / (t_{k-1} - t_{k-2})) mu_p = exp(ratio m) T_{k-1}, m the
    6-vector of T_{k-1} T_{k-2}^-1.

    Poses : (6,) for frames k-2, k-1, k; sigma : (6,) standard deviations (default
    DEFAULT_MOTION_SIGMA). Returns (residuals (6,), (J_km2, J_km1, J_k), each (6, 6)).
    """

# ---------------------------------------------------------------- problem (bind_problem.cc)

class BundleAdjusterOptions:
    """Options of BundleAdjuster; defaults from seed 000 (Sec. 4.2, appendix Eq. 30).

    Keyword construction: ``BundleAdjusterOptions(loss="huber", use_emt=False)``; an unknown
    keyword raises TypeError. Values are checked when a BundleAdjuster is built (ValueError).
    """

    sigma_v_px: float
    """sigma_v, pixels (Sec. 4.2: 1 px)."""
    emt_sigma: _Array
    """(6,) EMT prior standard deviations (rad x3, mm x3); a copy: assign the whole array."""
    motion_sigma: _Array
    """(6,) constant-velocity prior standard deviations (rad x3, mm x3); a copy."""
    loss: str
    """'none' | 'huber' | 'cauchy', applied per correspondence."""
    loss_scale_px: float
    """Robust kernel scale, pixels (default 2)."""
    linear_solver: str
    """'auto' (= 'sparse_schur', measured in bench/bench_solvers.py), 'dense_schur',
    'sparse_schur', 'sparse_normal_cholesky', 'dense_qr', 'dense_normal_cholesky',
    'iterative_schur'."""
    trust_region: str
    """'levenberg_marquardt' (default) or 'dogleg' (Ceres' trust region strategy)."""
    residual_blocks: str
    """'per_pair' (default: one block per image pair) or 'per_point'."""
    condense_pairs: bool
    """Per-pair blocks enter Ceres condensed: P + 1 residuals with the pair's J^T J, J^T r and
    cost instead of 2N (the same steps to rounding, less per-residual work). Default True."""
    max_iterations: int
    function_tolerance: float
    gradient_tolerance: float
    parameter_tolerance: float
    num_threads: int
    use_emt: bool
    """Add the EMT pose prior (Eq. 19) for frames with a measurement."""
    use_motion_prior: bool
    """Add the constant-velocity prior (Eq. 20) for present frame ids k-2, k-1, k."""
    motion_gate_chi2: float
    """Motion gate (not in the paper): after a solve, the C_p blocks whose whitened squared
    norm is above this and the largest among their neighbours (frames within 2) are left out of
    the solve and the problem solved again, in rounds, at most a quarter of the blocks. Default
    22.46 (chi2(6) 0.999); inf: off."""
    plane_std: bool
    """Compute SolveSummary.plane_relative_std (dense in 6 N + 3: small problems, e.g. the
    sequential start-up). Default False."""
    plane_std_paired_only: bool
    """With plane_std, only the poses of frames in a pair enter the covariance; the others are
    held at their values (conditioned on: a lower bound). Dense in 6 M + 3 for M paired frames.
    Default False."""

    def __init__(self, **kwargs: Any) -> None: ...
    def validate(self) -> None:
        """Raises ValueError naming the first invalid field."""

class SolveSummary:
    """Result of BundleAdjuster.solve(). Costs are Ceres' 1/2 sum of squared whitened residuals
    (robust-kernel values for the visual term when a loss is set); NaN where they could not be
    evaluated (a FAILURE termination, e.g. a camera centre on the plane)."""

    def __init__(self, *args: Never, **kwargs: Never) -> None:
        """Not constructible: BundleAdjuster.solve() returns one."""

    @property
    def iterations(self) -> int:
        """Ceres iterations (not counting its iteration 0, the evaluation at the start): at
        most max_iterations per run, summed over the motion gate's runs."""
    @property
    def initial_cost(self) -> float: ...
    @property
    def final_cost(self) -> float: ...
    @property
    def visual_cost(self) -> float: ...
    @property
    def emt_cost(self) -> float: ...
    @property
    def motion_cost(self) -> float: ...
    @property
    def solve_time_s(self) -> float: ...
    @property
    def termination(self) -> str:
        """'CONVERGENCE', 'NO_CONVERGENCE', 'FAILURE', ..."""
    @property
    def message(self) -> str: ...
    @property
    def full_report(self) -> str: ...
    @property
    def linear_solver(self) -> str:
        """The linear solver used, lower case ('auto' resolved)."""
    @property
    def num_residual_blocks(self) -> int: ...
    @property
    def num_residuals(self) -> int: ...
    @property
    def num_parameters(self) -> int:
        """All parameters in the problem, constant ones included."""
    @property
    def num_free_parameters(self) -> int:
        """Optimised (tangent-space) parameters."""
    @property
    def num_visual_blocks(self) -> int: ...
    @property
    def num_emt_blocks(self) -> int: ...
    @property
    def num_motion_blocks(self) -> int: ...
    @property
    def gauge_fixed_by_constraints(self) -> bool:
        """True when no EMT prior was present and the BAVis gauge (first frame constant, |pi|
        fixed) was applied."""
    @property
    def plane_relative_std(self) -> float:
        """sqrt(trace(Cov_pi)) / |pi| at the solution with options.plane_std (pi free, EMT priors,
        per-pair blocks); NaN otherwise, inf: pi unobservable."""
    @property
    def plane_std_time_s(self) -> float:
        """Seconds plane_relative_std took (not in solve_time_s); 0 when not computed."""
    @property
    def motion_released_ids(self) -> list[int]:
        """Frames whose C_p block the motion gate released in this solve
        (options.motion_gate_chi2); iterations and solve_time_s cover every round."""

    def as_dict(self) -> dict[str, Any]:
        """All fields except full_report, JSON-serialisable."""

class BundleAdjuster:
    """Bundle adjustment of frame poses and the plane: BAVis (use_emt=False) and BAVis+EMT
    (seed 000, Eq. 17). Owns the parameters, keyed by frame id. Without EMT priors the gauge
    is fixed by holding the first (lowest-id) frame constant and |plane| fixed. Calls from
    other threads wait while solve() runs; they release the GIL as they wait, so only the
    calling thread does.
    """

    def __init__(self, camera_matrix: _ArrayLike, options: BundleAdjusterOptions = ...) -> None:
        """camera_matrix : (3, 3) K, invertible."""

    @property
    def options(self) -> BundleAdjusterOptions:
        """A copy of the options (fixed at construction)."""

    @property
    def camera_matrix(self) -> _Array:
        """(3, 3)."""

    @property
    def num_frames(self) -> int: ...
    @property
    def num_pairs(self) -> int: ...
    @property
    def num_correspondences(self) -> int: ...
    def add_frame(
        self,
        frame_id: int,
        cam_from_world: _ArrayLike,
        emt_measurement: _ArrayLike | None = None,
        motion_ratio: float = 1.0,
        motion_sigma_scale: float = 1.0,
    ) -> None:
        """Adds a frame. cam_from_world : (6,) initial pose; emt_measurement : (6,) z_k or None;
        motion_ratio, motion_sigma_scale : timing of the constant-velocity prior over frames
        id-2, id-1, id (1, 1 for evenly spaced frames; 0, inf: no prior across a long gap;
        estimation.motion.motion_timing). ValueError for a duplicate id, a ratio that is not
        finite and >= 0 or a sigma scale that is not > 0."""

    def add_pair(
        self, frame_l: int, frame_m: int, points_l: _ArrayLike, points_m: _ArrayLike
    ) -> None:
        """Adds a pair's correspondences; the residual transfers frame m -> frame l.

        points_l, points_m : (N, 2) pixels, N >= 1, row i corresponds to row i.
        IndexError for an unknown frame id.
        """

    def set_plane(self, plane: _ArrayLike) -> None:
        """plane : (3,) pi = n / d, non-zero."""

    def set_pose(self, frame_id: int, pose: _ArrayLike) -> None:
        """pose : (6,) cam_from_world."""

    def set_constant_frame(self, frame_id: int, constant: bool = True) -> None:
        """Holds a frame's pose constant during solve() (or frees it again)."""

    def set_constant_plane(self, constant: bool = True) -> None:
        """Holds the plane constant during solve() (or frees it again)."""

    def solve(self) -> SolveSummary:
        """Runs Ceres with the GIL released; the stored poses and plane are updated."""

    def poses(self) -> tuple[npt.NDArray[np.int64], _Array]:
        """(ids (N,) int64 ascending, poses (N, 6) cam_from_world)."""

    def pose(self, frame_id: int) -> _Array:
        """(6,) pose of one frame; IndexError for an unknown id."""

    def plane(self) -> _Array:
        """(3,) pi = n / d; ValueError before set_plane."""

# ------------------------------------------------------- LBA window (bind_sliding_window.cc)

class SlidingWindowOptions:
    """Options of the LBA sliding window (seed 000, Sec. 4.2): W, chi_e and the cost settings."""

    window_size: int
    num_new: int
    costs: BundleAdjusterOptions
    fold_fixed_cameras: bool  # fixed cameras enter costs as values, not parameters (faster)
    full_report: bool  # keep Ceres' FullReport() in each step summary
    plane_max_relative_std: float
    """Plane observability gate: a step whose costs leave pi with a relative standard deviation
    sqrt(trace(Cov_pi)) / |pi| above this is solved again with pi held (0: gate and std
    computation off)."""

    def __init__(
        self, window_size: int = 5, num_new: int = 3, costs: BundleAdjusterOptions | None = None
    ) -> None: ...

class WindowStepSummary:
    """Result of SlidingWindow.step() / redo(). Costs as SolveSummary's (NaN where they could
    not be evaluated)."""

    def __init__(self, *args: Never, **kwargs: Never) -> None:
        """Not constructible: SlidingWindow.step() / redo() return one."""

    @property
    def frame_ids(self) -> list[int]: ...
    @property
    def fixed_ids(self) -> list[int]: ...
    @property
    def keyframe_ids(self) -> list[int]: ...
    @property
    def emt_mahalanobis2(self) -> list[float]:
        """Per estimated frame, NaN without a tracker sample."""
    @property
    def iterations(self) -> int:
        """Ceres iterations as SolveSummary's (iteration 0 not counted), summed over the
        step's runs (motion gate rounds, the plane gate's second solve)."""
    @property
    def initial_cost(self) -> float: ...
    @property
    def final_cost(self) -> float: ...
    @property
    def visual_cost(self) -> float: ...
    @property
    def emt_cost(self) -> float: ...
    @property
    def motion_cost(self) -> float: ...
    @property
    def solve_time_s(self) -> float: ...
    @property
    def step_time_s(self) -> float: ...
    @property
    def termination(self) -> str: ...
    @property
    def message(self) -> str:
        """Ceres' summary message of the step's last solve (why it stopped); empty without a
        solve (NO_RESIDUALS)."""
    @property
    def num_visual_blocks(self) -> int: ...
    @property
    def num_correspondences(self) -> int: ...
    @property
    def num_window_correspondences(self) -> int: ...
    @property
    def num_keyframe_correspondences(self) -> int: ...
    @property
    def num_loop_correspondences(self) -> int: ...
    @property
    def num_temporal_correspondences(self) -> int:
        """With the window_size - 1 frames before the first new one, outside the window."""
    @property
    def num_fixed_pair_correspondences(self) -> int:
        """In pairs of two fixed cameras: constrain pi only."""
    @property
    def num_residuals(self) -> int: ...
    @property
    def num_free_parameters(self) -> int: ...
    @property
    def plane_relative_std(self) -> float:
        """sqrt(trace(Cov_pi)) / |pi before the step| from the step's costs; NaN: no visual cost
        or the gate off; inf: pi unobservable; for a step the gate held, its first solve's value."""
    @property
    def plane_held(self) -> bool:
        """pi kept its value from before the step (no visual cost, or the gate)."""
    @property
    def motion_released_ids(self) -> list[int]:
        """Estimated cameras whose C_p the motion gate released in this step or redo."""
    @property
    def preprocessor_time_s(self) -> float: ...
    @property
    def evaluation_time_s(self) -> float: ...
    @property
    def linear_solver_time_s(self) -> float: ...
    @property
    def full_report(self) -> str: ...

class SlidingWindow:
    """Local bundle adjustment over a sliding window with keyframes (LBAVis+EMT, Eqs. 24-27).
    Calls from other threads wait while step() or redo() runs (GIL released: only they wait)."""

    @property
    def num_frames(self) -> int: ...
    @property
    def num_pairs(self) -> int: ...
    @property
    def num_correspondences(self) -> int: ...

    def __init__(
        self, camera_matrix: _ArrayLike, options: SlidingWindowOptions = ...
    ) -> None: ...
    def add_frame(
        self,
        frame_id: int,
        initial: _ArrayLike | None = None,
        emt_measurement: _ArrayLike | None = None,
        fixed: bool = False,
        motion_ratio: float = 1.0,
        motion_sigma_scale: float = 1.0,
    ) -> None:
        """initial, emt_measurement : (6,) cam_from_world or None; ids must increase.
        fixed : already estimated (enters the window fixed; needs initial). The window's first
        frame needs initial or emt_measurement (no predecessors to predict it from): ValueError.
        motion_ratio, motion_sigma_scale : timing of the constant-velocity prior linking this
        camera to the two preceding ones (1, 1: evenly spaced; 0, inf: no prior across a long
        gap, the camera starting at the preceding one; see BundleAdjuster.add_frame)."""

    def set_emt_sigma_scale(self, frame_id: int, scale: float) -> None:
        """Inflates a frame's tracker standard deviations (gating), scale >= 1."""

    def drop_emt_measurement(self, frame_id: int) -> None:
        """Drops a frame's tracker measurement (an unusable sample, e.g. one putting the camera
        centre on the plane): no C_EMT term, and its pose is initialised again from the
        constant-velocity prediction by the next step or redo that estimates it. ValueError for
        the window's first frame while pending (no predecessors to predict it from)."""

    def set_motion_timing(
        self, frame_id: int, motion_ratio: float, motion_sigma_scale: float
    ) -> None:
        """The timing of a frame's constant-velocity prior (as add_frame's), from the next
        step or redo that estimates it on."""

    def add_pair(
        self, frame_l: int, frame_m: int, points_l: _ArrayLike, points_m: _ArrayLike
    ) -> None:
        """points_l, points_m : (N, 2) pixels; transfer m -> l."""

    def set_plane(self, plane: _ArrayLike) -> None:
        """plane : (3,) pi = n / d, non-zero."""

    def step(self, keyframe_ids: list[int] = ..., hold_plane: bool = False) -> WindowStepSummary:
        """Estimates the pending frames and the plane (GIL released), then fixes them;
        hold_plane: pi keeps its value (plane_held in the summary)."""

    def redo(self, frame_ids: list[int], keyframe_ids: list[int] = ...,
             hold_plane: bool = False) -> WindowStepSummary:
        """Re-estimates the last frames (after set_emt_sigma_scale). frame_ids, distinct, must
        hold every frame from the first of them on (the last step's frames, and any added since,
        pending), with no pending frame before them, the window's first frame among them only
        with a tracker sample, and keyframe_ids fixed frames not among them; ValueError
        otherwise (IndexError for an unknown id), with nothing changed."""

    def forget(self, frame_ids: list[int]) -> None:
        """Drops fixed frames outside the window, with their pairs (unknown ids ignored).
        ValueError, nothing dropped, for a pending frame, one in the window, or one of the two
        frames before the first pending one (its constant-velocity prior links it to them)."""

    def pose(self, frame_id: int) -> _Array:
        """(6,) cam_from_world; IndexError for an unknown id, ValueError for a pending frame
        added without an initial pose (it gets one at its step)."""
    def plane(self) -> _Array:
        """(3,) pi = n / d; ValueError before set_plane."""
    def pending_ids(self) -> list[int]: ...
    def window_ids(self) -> list[int]: ...
