"""GAGAvatar (NeurIPS 2024) in Rust: one photo -> an animatable 3D Gaussian head.

    import gagavatar as ga
    eng = ga.Engine.demo()                      # or ga.Engine("GAGAvatar.pt", flame="FLAME_with_eye.pt")
    src = eng.track("me.jpg")                   # record + 512 crop (or an [H, W, 3] uint8 array)
    drv = eng.track("clip.mp4", progress=print) # records, frame names and rate (cached by content)
    av = eng.avatar(src)                        # reconstruct once
    frames = av.render(drv)                     # uint8 [N, S, S, 3]
    for f in av.frames(drv):                    # the same, one frame at a time, for long clips
        ...
    both = ga.render_many([(av, drv.records[0]), (av2, drv.records[0])])   # one batched pass
    img = av.render_codes(expression=e, jaw=j, eyes=y, camera=T)
    av.export_ply("avatar.ply")
    ga.write_video("out.mp4", frames, fps=25)

Records come from `Engine.track`, `gagavatar track` (a tracked folder), a release `optim.pkl` or
a JSON record (`read_record`, `read_driver`), as dicts of NumPy arrays in the release's names.
Frames carry the visible "AI-generated" label unless `watermark=False`. Every failure raises
`gagavatar.Error` with the CLI's one-line message. Computation releases the GIL.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, List, Optional, Sequence, Union

import numpy as np

from . import _native
from ._native import Error

__all__ = [
    "Engine",
    "Avatar",
    "Driver",
    "Tracked",
    "Error",
    "render_many",
    "read_record",
    "read_driver",
    "write_video",
]

#: The release's record fields.
RECORD_KEYS = ("shapecode", "expcode", "posecode", "eyecode", "transform_matrix", "bbox")

PathLike = Union[str, "os.PathLike[str]"]
Record = dict


def _record_json(record) -> str:
    if isinstance(record, (str, os.PathLike)):
        return _native._read_record(os.fspath(record), None)
    if not isinstance(record, dict):
        raise Error(f"a record is a dict of the release's fields or a path, not {type(record).__name__}")
    out = {}
    for k in RECORD_KEYS:
        v = record.get(k)
        if v is None:
            continue
        a = np.asarray(v, dtype=np.float64)
        out[k] = a.reshape(3, 4).tolist() if k == "transform_matrix" else a.reshape(-1).tolist()
    return json.dumps(out)


def _record_dict(text: str) -> Record:
    raw = json.loads(text)
    return {k: np.asarray(v, dtype=np.float32) for k, v in raw.items() if v is not None}


def read_record(path: PathLike, key: Optional[str] = None) -> Record:
    """One tracked frame: a JSON record, or frame `key` of a release `optim.pkl`."""
    return _record_dict(_native._read_record(os.fspath(path), key))


@dataclass
class Driver:
    """A driving sequence: frame names, records and the frame rate."""

    names: List[str]
    records: List[Record]
    fps: float

    def __len__(self) -> int:
        return len(self.records)


@dataclass
class Tracked(Driver):
    """What `Engine.track` made: the records in frame order (a video's smoothed ones), their
    frame names and rate, and for a photo its 512 crop (matted, as the folder stores it). `dir`
    is the tracked folder (`None` for an array tracked in memory); `cached` says it was found in
    the tracking cache. A tracked photo is a source for `Engine.avatar`, a tracked video a driver
    for `Avatar.render`."""

    kind: str = "video"
    dir: Optional[str] = None
    crop: Optional[np.ndarray] = None
    cached: bool = False

    @property
    def record(self) -> Record:
        """The first (a photo's only) record."""
        return self.records[0]


def read_driver(path: PathLike) -> Driver:
    """A tracked folder (`gagavatar track` or the release's), a `.pkl` or a JSON sequence."""
    names, records, fps = _native._read_driver(os.fspath(path))
    return Driver(names, [_record_dict(r) for r in records], fps)


def write_video(path: PathLike, frames, fps: float = 25.0, watermark: bool = False) -> None:
    """Writes uint8 frames `[N, H, W, 3]` to .mp4 (H.264), .gif, or a folder of PNGs, atomically."""
    arr = np.ascontiguousarray(frames, dtype=np.uint8)
    if arr.ndim == 3:
        arr = arr[None]
    _native.write_video(os.fspath(path), arr, float(fps), bool(watermark))


class Engine:
    """The model and FLAME, loaded once.

    `flame=None` uses the asset the weights name (the built-in synthetic one for the demo model;
    the release's weights need `FLAME_with_eye.pt`). `device` is `cpu`, `gpu` or `auto`.
    `precision` is the CPU model's arithmetic: `f32` (the release's) or `bf16` (bf16 products
    with f32 sums; faster on CPUs with AVX512-BF16, an `Error` on others). `gpu_precision` is
    the GPU renderer's convolutions: `auto` (f16 on the tensor cores where the GPU has them,
    else f32), `f32`, or `f16` (an `Error` on a GPU without tensor cores).
    """

    def __init__(
        self,
        ckpt: PathLike,
        flame: Optional[PathLike] = None,
        device: str = "cpu",
        preset: Optional[str] = None,
        fresh_noise: bool = False,
        precision: str = "f32",
        gpu_precision: str = "auto",
    ):
        self._e = _native.Engine(
            os.fspath(ckpt),
            None if flame is None else os.fspath(flame),
            device,
            preset,
            fresh_noise,
            precision,
            gpu_precision,
        )

    @classmethod
    def demo(
        cls, device: str = "cpu", precision: str = "f32", gpu_precision: str = "auto"
    ) -> "Engine":
        """The shipped demo model (the `tiny` preset trained on synthetic heads)."""
        return cls(
            demo_file("weights.safetensors"),
            device=device,
            precision=precision,
            gpu_precision=gpu_precision,
        )

    @property
    def image_size(self) -> int:
        return self._e.image_size

    @property
    def warnings(self) -> List[str]:
        return self._e.warnings

    @property
    def flame(self) -> str:
        return self._e.flame

    @property
    def device(self) -> str:
        return self._e.device

    def track(self, source, output: Optional[PathLike] = None, progress=None) -> Tracked:
        """Tracks a photo, a video or a folder of images (a path), or a photo given as an
        `[H, W, 3]` uint8 array (in memory, nothing written), with this engine's FLAME.

        A path goes into `output` (a folder in the release's layout) or, by default, into the
        tracking cache, where a later call with the same bytes finds it. `progress(stage, done,
        total)` is called as it works; an exception it raises, or Ctrl-C, stops the call and
        nothing is left half-written. Raises `Error` ("no face found in ...") for a photo
        without a face."""
        if isinstance(source, (str, os.PathLike)):
            kind, d, names, records, crop, fps, cached = self._e._track_file(
                os.fspath(source), None if output is None else os.fspath(output), progress
            )
            return Tracked(
                names, [_record_dict(r) for r in records], fps, kind, d, crop, cached
            )
        if output is not None:
            raise Error("output is for a path; an array is tracked in memory")
        arr = np.ascontiguousarray(source)
        if arr.dtype != np.uint8 or arr.ndim != 3:
            raise Error(f"the image must be [H, W, 3] uint8 RGB, got {arr.dtype} {arr.shape}")
        record, crop = self._e._track_array(arr, "the image")
        return Tracked(["image_0"], [_record_dict(record)], 25.0, "photo", None, crop, False)

    def avatar(self, image, record=None) -> "Avatar":
        """Reconstructs an avatar from the source crop (a path, or an `[H, W, 3]` uint8 array)
        and its record (a dict or a path), or from a tracked photo (`Engine.track`) alone."""
        if isinstance(image, Tracked):
            if record is not None:
                raise Error("a tracked photo carries its own record")
            if image.kind != "photo" or image.crop is None:
                raise Error("a tracked video is a driver, not a source: track a photo")
            image, record = image.crop, image.record
        if record is None:
            raise Error("give the source's record, or a tracked photo (Engine.track)")
        rec = _record_json(record)
        if isinstance(image, (str, os.PathLike)):
            return Avatar(self._e._avatar_from_file(os.fspath(image), rec))
        arr = np.ascontiguousarray(image)
        if arr.dtype != np.uint8 or arr.ndim != 3:
            raise Error(f"the image must be [H, W, 3] uint8 RGB, got {arr.dtype} {arr.shape}")
        return Avatar(self._e._avatar_from_array(arr, rec))


class Avatar:
    """A reconstructed avatar; render it with any expression and camera."""

    def __init__(self, native):
        self._a = native
        self._source = _record_dict(native._source_json())

    @property
    def source(self) -> Record:
        """The record the avatar was made from (a copy)."""
        return {k: v.copy() for k, v in self._source.items()}

    @property
    def image_size(self) -> int:
        return self._a.image_size

    @property
    def frames_rendered(self) -> int:
        """Frames this avatar's drive has rendered so far."""
        return self._a.frames_rendered

    @property
    def library_seconds(self) -> float:
        """Seconds spent inside the Rust library's rendering (codes in, RGB frames out)."""
        return self._a.library_seconds

    def render(self, driver, batch: int = 4, watermark: bool = True) -> np.ndarray:
        """All frames of `driver` (records, a `Driver`, or a path) as `[N, S, S, 3]` uint8."""
        return self._render(_driver_records(driver), batch, watermark)

    def frames(self, driver, batch: int = 4, watermark: bool = True) -> Iterator[np.ndarray]:
        """The frames of `driver` one at a time (`[S, S, 3]`), `batch` rendered at once: a long
        clip never holds more than a batch of frames."""
        records = _driver_records(driver)
        for i in range(0, len(records), batch):
            yield from self._render(records[i : i + batch], batch, watermark)

    def _render(self, records, batch, watermark):
        if len(records) == 0:
            raise Error("nothing to render (no frames)")
        e, p, y, c = _code_arrays(records)
        return self._a._render_arrays(e, p, y, c, batch, watermark)

    def render_codes(
        self,
        expression: Sequence[float] = (),
        jaw: Sequence[float] = (0.0, 0.0, 0.0),
        eyes: Sequence[float] = (0.0,) * 6,
        camera=None,
        watermark: bool = True,
    ) -> np.ndarray:
        """One frame `[S, S, 3]` from codes: expression (zero-padded), jaw and eyes (axis-angle),
        camera (3x4; default: the source's)."""
        cam = self._source["transform_matrix"] if camera is None else camera
        pose = np.zeros((1, 6), dtype=np.float32)
        pose[0, 3:] = np.asarray(jaw, dtype=np.float32).reshape(3)
        return self._a._render_arrays(
            np.asarray(expression, dtype=np.float32).reshape(1, -1),
            pose,
            np.asarray(eyes, dtype=np.float32).reshape(1, 6),
            np.asarray(cam, dtype=np.float64).reshape(1, 3, 4),
            1,
            watermark,
        )[0]

    def orbit(self, yaw: float = 30.0, pitch: float = 10.0, frames: int = 60, batch: int = 4,
              watermark: bool = True) -> np.ndarray:
        """`gagavatar orbit`'s figure-eight around the head (degrees): `[frames, S, S, 3]`."""
        return self._a.orbit(yaw, pitch, frames, batch, watermark)

    def export_ply(self, path: PathLike, expression=None) -> None:
        """The avatar as a 3DGS `.ply`, expression Gaussians placed for `expression` (a record;
        default: the source's own)."""
        rec = None if expression is None else _record_json(expression)
        self._a._export_ply(os.fspath(path), rec)


def render_many(jobs, watermark: bool = True) -> np.ndarray:
    """Frames of several avatars (of one engine) in one batched pass, as a server gathers
    requests: `jobs` is a list of `(avatar, record)`; returns `[N, S, S, 3]` uint8, frame `i`
    as `jobs[i][0].render([jobs[i][1]])` (up to the batched sums' rounding)."""
    jobs = list(jobs)
    if not jobs:
        raise Error("render_many needs at least one (avatar, record)")
    natives, index, records = [], [], []
    for i, job in enumerate(jobs):
        try:
            av, rec = job
        except (TypeError, ValueError):
            raise Error(f"job {i} is not an (avatar, record) pair") from None
        if not isinstance(av, Avatar):
            raise Error(f"job {i}: {type(av).__name__} is not an Avatar")
        k = next((j for j, n in enumerate(natives) if n is av._a), None)
        if k is None:
            natives.append(av._a)
            k = len(natives) - 1
        index.append(k)
        records.append(rec)
    e, p, y, c = _code_arrays(records)
    return _native._render_many(natives, index, e, p, y, c, watermark)


def _code_arrays(records):
    """Records as the native code arrays: expcode `[N, E]`, posecode and eyecode `[N, 6]`
    (float32), cameras `[N, 3, 4]` (float64)."""
    for i, r in enumerate(records):
        if not isinstance(r, dict):
            raise Error(f"driver record {i} is a {type(r).__name__}, not a dict")
        if r.get("transform_matrix") is None:
            raise Error(f"driver record {i}: no transform_matrix (the camera)")

    def rows(key, n=None):
        vals = [np.asarray(r.get(key, ()), dtype=np.float32).reshape(-1) for r in records]
        width = n if n is not None else max(len(v) for v in vals)
        out = np.zeros((len(vals), width), dtype=np.float32)
        for i, v in enumerate(vals):
            if n is not None and len(v) != n:
                raise Error(f"driver record {i}: {key} has {len(v)} values, expected {n}")
            out[i, : len(v)] = v
        return out

    cams = np.stack(
        [np.asarray(r["transform_matrix"], dtype=np.float64).reshape(3, 4) for r in records]
    )
    return rows("expcode"), rows("posecode", 6), rows("eyecode", 6), cams


def _driver_records(driver) -> List:
    if isinstance(driver, Driver):
        return driver.records
    if isinstance(driver, (str, os.PathLike)):
        return read_driver(driver).records
    if isinstance(driver, dict):
        return [driver]
    return list(driver)


def demo_file(name: str) -> str:
    """A file of the shipped demo model (`weights.safetensors`, `source.png`, `source.json`,
    `driver.json`), written once to a cache folder; returns its path."""
    data = _native._demo_file(name)
    cache = os.environ.get("GAGAVATAR_CACHE")
    root = Path(cache) / "demo" if cache else Path(tempfile.gettempdir()) / "gagavatar-demo"
    path = root / hashlib.sha256(data).hexdigest()[:16] / name
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{name}.{os.getpid()}")
        tmp.write_bytes(data)
        os.replace(tmp, path)
    return str(path)
