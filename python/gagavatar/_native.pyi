"""Type stub of the compiled module `gagavatar._native` (PyO3); use the `gagavatar` package."""

from os import PathLike
from typing import Any, Callable, List, Optional, Tuple, Union

import numpy as np
import numpy.typing as npt

_Path = Union[str, PathLike[str]]

class Error(Exception):
    """Every failure of the package: one line, as the CLI prints it."""

class Engine:
    def __init__(
        self,
        ckpt: _Path,
        flame: Optional[_Path] = None,
        device: str = "cpu",
        preset: Optional[str] = None,
        fresh_noise: bool = False,
        precision: str = "f32",
        gpu_precision: str = "auto",
    ) -> None: ...
    @property
    def image_size(self) -> int: ...
    @property
    def warnings(self) -> List[str]: ...
    @property
    def flame(self) -> str: ...
    @property
    def device(self) -> str: ...
    def _avatar_from_array(self, image: npt.NDArray[np.uint8], record_json: str) -> Avatar: ...
    def _avatar_from_file(self, path: _Path, record_json: str) -> Avatar: ...
    def _track_file(
        self,
        path: _Path,
        output: Optional[_Path] = None,
        progress: Optional[Callable[[str, int, Optional[int]], Any]] = None,
    ) -> Tuple[str, str, List[str], List[str], Optional[npt.NDArray[np.uint8]], float, bool]: ...
    def _track_array(
        self, image: npt.NDArray[np.uint8], label: str
    ) -> Tuple[str, npt.NDArray[np.uint8]]: ...

class Avatar:
    @property
    def image_size(self) -> int: ...
    @property
    def frames_rendered(self) -> int: ...
    @property
    def library_seconds(self) -> float: ...
    def _source_json(self) -> str: ...
    def _render_arrays(
        self,
        expcode: npt.NDArray[np.float32],
        posecode: npt.NDArray[np.float32],
        eyecode: npt.NDArray[np.float32],
        cameras: npt.NDArray[np.float64],
        batch: int = 4,
        watermark: bool = True,
    ) -> npt.NDArray[np.uint8]: ...
    def orbit(
        self,
        yaw: float = 30.0,
        pitch: float = 10.0,
        frames: int = 60,
        batch: int = 4,
        watermark: bool = True,
    ) -> npt.NDArray[np.uint8]: ...
    def _export_ply(self, path: _Path, record_json: Optional[str] = None) -> None: ...

def _read_driver(path: _Path) -> Tuple[List[str], List[str], float]: ...
def _read_record(path: _Path, key: Optional[str] = None) -> str: ...
def _demo_file(name: str) -> bytes: ...
def _render_many(
    avatars: List[Avatar],
    index: List[int],
    expcode: npt.NDArray[np.float32],
    posecode: npt.NDArray[np.float32],
    eyecode: npt.NDArray[np.float32],
    cameras: npt.NDArray[np.float64],
    watermark: bool = True,
) -> npt.NDArray[np.uint8]: ...
def write_video(
    path: _Path, frames: npt.NDArray[np.uint8], fps: float = 25.0, watermark: bool = False
) -> None: ...
