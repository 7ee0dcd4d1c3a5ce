"""Type stubs of the compiled module ``rgbid._rgbid`` (see the package docstring for units
and frames)."""

from os import PathLike
from typing import Any, Dict, Iterator, List, Mapping, Optional, Tuple, Union

import numpy as np
import numpy.typing as npt

__version__: str
_Path = Union[str, PathLike]
_Config = Union[None, Mapping[str, Any], _Path]

class RgbidError(RuntimeError):
    """A failure inside rgbid (I/O, GPU, tracking), with the library's message."""

class Camera:
    """Pinhole camera: focal lengths and principal point in pixels, size in pixels, optional
    Brown-Conrady distortion ``(k1, k2, p1, p2, k3)`` and rolling-shutter ``readout`` (s)."""

    def __init__(
        self,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        width: int,
        height: int,
        distortion: Optional[Tuple[float, float, float, float, float]] = None,
        readout: float = 0.0,
    ) -> None: ...
    @staticmethod
    def preset(name: str) -> "Camera":
        """``tum_fr1``, ``tum_fr2``, ``tum_fr3``, ``default``, or a camera file."""
    @property
    def fx(self) -> float: ...
    @property
    def fy(self) -> float: ...
    @property
    def cx(self) -> float: ...
    @property
    def cy(self) -> float: ...
    @property
    def width(self) -> int: ...
    @property
    def height(self) -> int: ...
    @property
    def distortion(self) -> Tuple[float, float, float, float, float]: ...
    @property
    def readout(self) -> float:
        """Rolling-shutter readout, seconds from the first row to the last (0: global)."""
    @property
    def depth_factor(self) -> Optional[float]:
        """Depth units per metre of the preset, ``None`` for a camera built from numbers."""
    @property
    def matrix(self) -> npt.NDArray[np.float64]:
        """``K`` as ``float64[3, 3]``."""

class Odometry:
    """Dense RGB-D odometry with inverse depth."""

    def __init__(
        self,
        camera: Camera,
        config: _Config = None,
        backend: str = "auto",
        model: Optional[Dict[str, Any]] = None,
    ) -> None:
        """``model``: ``None`` (frame-to-reference) or a dict with any of ``voxel`` (metres),
        ``cast_level``, ``fill_holes`` for frame-to-model tracking against a TSDF."""
    def track(
        self,
        image: npt.NDArray[np.uint8],
        depth: Union[npt.NDArray[np.uint16], npt.NDArray[np.float32]],
        depth_factor: Optional[float] = None,
        timestamp: float = 0.0,
    ) -> Dict[str, Any]:
        """``world_from_camera`` ``float64[4, 4]`` (or ``None``), ``cur_from_ref``,
        ``covariance`` ``float64[6, 6]`` or ``None``, ``status``, ``stats``, ``model_ms``
        (``ray_cast`` and ``integrate`` ms with a model, else ``None``), ``rust_ms``."""
    def set_initial_pose(self, world_from_camera: npt.NDArray[np.float64]) -> None: ...
    @property
    def backend(self) -> str: ...
    @property
    def camera(self) -> Camera: ...

class EventStream(Iterator[Dict[str, Any]]):
    """SLAM events waiting now, one dict each with ``kind``."""

    def __iter__(self) -> "EventStream": ...
    def __next__(self) -> Dict[str, Any]: ...
    @property
    def dropped(self) -> Dict[str, int]: ...

class SlamResult:
    """What a finished ``Slam`` produced."""

    @property
    def trajectory(self) -> npt.NDArray[np.float64]:
        """``float64[N, 8]``, TUM columns."""
    @property
    def odometry(self) -> npt.NDArray[np.float64]: ...
    @property
    def keyframes(self) -> npt.NDArray[np.float64]: ...
    @property
    def loops(self) -> List[Dict[str, Any]]: ...
    @property
    def points(self) -> npt.NDArray[np.float64]:
        """``float64[N, 3]`` world points, metres."""
    @property
    def colors(self) -> npt.NDArray[np.uint8]:
        """``uint8[N, 3]`` RGB: the keyframes' colour when the frames had colour and
        ``keyframe_colour`` is on, else grey (the intensity in all three channels)."""
    @property
    def statuses(self) -> List[str]: ...
    def save_map(self, path: _Path) -> None: ...

class Slam:
    """RGB-ID SLAM."""

    def __init__(
        self,
        camera: Camera,
        config: _Config = None,
        backend: str = "auto",
        map_path: Optional[_Path] = None,
        vocabulary: Optional[_Path] = None,
    ) -> None: ...
    def process(
        self,
        image: npt.NDArray[np.uint8],
        depth: Union[npt.NDArray[np.uint16], npt.NDArray[np.float32]],
        depth_factor: Optional[float] = None,
        timestamp: float = 0.0,
    ) -> Dict[str, Any]: ...
    def events(self) -> EventStream: ...
    def finish(self, voxel: float = ...) -> SlamResult: ...
    @property
    def frames(self) -> int: ...
    @property
    def backend(self) -> str: ...

class TsdfVolume:
    """Sparse TSDF volume in the world frame (blocks of 8^3 voxels): integrate frames at known
    poses, ray cast, extract a coloured mesh, save and load."""

    def __init__(
        self,
        camera: Camera,
        voxel: float = 0.01,
        min_depth: float = 0.3,
        max_depth: float = 4.0,
        backend: str = "auto",
        device_blocks: Optional[int] = None,
    ) -> None: ...
    @staticmethod
    def load(path: _Path, camera: Optional[Camera] = None, backend: str = "auto") -> "TsdfVolume": ...
    def save(self, path: _Path) -> None: ...
    def integrate(
        self,
        depth: Union[npt.NDArray[np.uint16], npt.NDArray[np.float32]],
        depth_factor: Optional[float],
        world_from_camera: npt.NDArray[np.float64],
        image: Optional[npt.NDArray[np.uint8]] = None,
    ) -> int:
        """Blocks the frame touched."""
    def ray_cast(
        self, world_from_camera: npt.NDArray[np.float64], camera: Optional[Camera] = None
    ) -> Dict[str, Any]:
        """``depth`` ``float32[H, W]`` metres (0 = no surface), ``normals``
        ``float32[H, W, 3]`` (camera frame), ``colour`` ``uint8[H, W, 3]``."""
    def extract_mesh(
        self,
    ) -> Tuple[
        npt.NDArray[np.float32],
        npt.NDArray[np.uint32],
        npt.NDArray[np.float32],
        npt.NDArray[np.uint8],
    ]:
        """``(vertices float32[N, 3] metres world frame, triangles uint32[M, 3], normals
        float32[N, 3], colours uint8[N, 3])``."""
    @property
    def params(self) -> Dict[str, Any]: ...
    @property
    def paging(self) -> Dict[str, int]:
        """``resident_blocks``, ``host_blocks``, ``peak_resident_blocks``, ``page_outs``,
        ``page_ins``."""
    @property
    def block_count(self) -> int: ...
    @property
    def frames(self) -> int: ...
    @property
    def backend(self) -> str: ...
    @property
    def camera(self) -> Camera: ...

_Frame = Tuple[float, npt.NDArray[np.uint8], npt.NDArray[np.uint16], float]

class Sequence:
    """Frames as stored: ``(timestamp, image, depth, depth_factor)``."""

    def __len__(self) -> int: ...
    def __getitem__(self, index: int) -> _Frame: ...
    def __iter__(self) -> Iterator[_Frame]: ...
    @property
    def camera(self) -> Camera: ...
    @property
    def depth_factor(self) -> float: ...
    @property
    def timestamps(self) -> List[float]: ...
    @property
    def groundtruth(self) -> Optional[npt.NDArray[np.float64]]: ...
    @property
    def path(self) -> Optional[str]: ...

def read_sequence(
    path: _Path, camera: Union[None, Camera, str] = None, max_frames: Optional[int] = None
) -> Sequence: ...
def synth_render(
    scene: str,
    trajectory: str,
    frames: int,
    seed: int,
    width: int = 320,
    out: Optional[_Path] = None,
    noise: bool = True,
) -> Sequence: ...
def read_trajectory(path: _Path) -> npt.NDArray[np.float64]: ...
def write_trajectory(path: _Path, trajectory: npt.NDArray[np.float64]) -> None: ...
def evaluate(
    gt: npt.NDArray[np.float64],
    est: npt.NDArray[np.float64],
    delta: float = 1.0,
    max_diff: float = 0.02,
    scale: bool = False,
) -> Dict[str, Any]: ...
def graph_optimize(
    path: _Path, cost: str = "geodesic", max_iterations: Optional[int] = None
) -> Tuple[npt.NDArray[np.float64], Dict[str, Any]]: ...
def read_run(folder: _Path) -> Dict[str, Any]: ...
def default_config(command: str) -> Dict[str, Any]: ...
