"""A reader for dlib's binary serialization format (the `.dat` model files).

Written from dlib's documented format (dlib/serialize.h, dlib/float_details.h,
dlib/cuda/tensor.h, dlib/dnn/*.h of dlib 20.0.1): no dlib code is used or needed.

* integers: one control byte (low 4 bits = number of little-endian magnitude bytes that
  follow, 1..8; bit 0x80 = negative), then the magnitude bytes (zero is size 1, byte 0).
* float/double: a `float_details`, i.e. the integer mantissa (int64) then the integer
  exponent (int16); value = mantissa * 2**exponent; exponents 32000/32001/32002 mean
  +inf/-inf/NaN.
* bool: the ASCII byte '1' or '0'.
* std::string: length (integer) then the raw bytes.
* std::vector<T>: length (integer) then the elements.
* dlib::matrix: -rows, -cols (integers), then the elements row-major.
* dnn tensors (resizable_tensor): version int (2), num_samples, k, nr, nc, then the floats as
  raw little-endian IEEE float32.
* alias_tensor: version int (1), num_samples, k, nr, nc (no data).
"""

import math
import struct

import numpy as np


class DlibStreamError(Exception):
    pass


class DlibStream:
    def __init__(self, data: bytes):
        self.data = data
        self.pos = 0

    def remaining(self) -> int:
        return len(self.data) - self.pos

    def _take(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise DlibStreamError(f"unexpected end of stream at byte {self.pos} (wanted {n} bytes)")
        b = self.data[self.pos:self.pos + n]
        self.pos += n
        return b

    def int(self, signed: bool = True) -> int:
        ctrl = self._take(1)[0]
        if signed:
            neg = bool(ctrl & 0x80)
            size = ctrl & 0x0F
        else:
            neg = False
            size = ctrl & 0x8F
        if size == 0 or size > 8:
            raise DlibStreamError(f"bad integer control byte {ctrl:#x} at byte {self.pos - 1}")
        v = int.from_bytes(self._take(size), "little")
        return -v if neg else v

    def uint(self) -> int:
        return self.int(signed=False)

    def float(self) -> float:
        if self.data[self.pos] & 0x70:
            raise DlibStreamError(f"old ASCII float format at byte {self.pos} is not supported")
        mantissa = self.int()
        exponent = self.int()
        if exponent == 32000:
            return math.inf
        if exponent == 32001:
            return -math.inf
        if exponent == 32002:
            return math.nan
        return math.ldexp(float(mantissa), exponent)

    def float32(self) -> np.float32:
        # dlib converts float_details to float with ldexp((float)mantissa, exponent); every
        # float that dlib wrote has a mantissa of at most 24 significant bits, so this is exact.
        return np.float32(self.float())

    def bool(self) -> bool:
        c = self._take(1)
        if c == b"1":
            return True
        if c == b"0":
            return False
        raise DlibStreamError(f"bad bool byte {c!r} at byte {self.pos - 1}")

    def string(self) -> str:
        n = self.uint()
        return self._take(n).decode("latin-1")

    def expect_string(self, *allowed: str) -> str:
        at = self.pos
        s = self.string()
        if s not in allowed:
            raise DlibStreamError(f"expected one of {allowed} at byte {at}, found {s!r}")
        return s

    def expect_int(self, value: int, what: str) -> None:
        at = self.pos
        v = self.int()
        if v != value:
            raise DlibStreamError(f"{what}: expected {value} at byte {at}, found {v}")

    def float_matrix(self) -> np.ndarray:
        nr = -self.int()
        nc = -self.int()
        if nr < 0 or nc < 0:
            raise DlibStreamError("matrix with negative size")
        vals = [self.float32() for _ in range(nr * nc)]
        return np.array(vals, dtype=np.float32).reshape(nr, nc)

    def tensor(self) -> np.ndarray:
        self.expect_int(2, "tensor version")
        n, k, nr, nc = (self.int() for _ in range(4))
        count = n * k * nr * nc
        raw = self._take(4 * count)
        return np.frombuffer(raw, dtype="<f4").astype(np.float32).reshape(n, k, nr, nc)

    def alias_tensor(self) -> tuple:
        self.expect_int(1, "alias_tensor version")
        return tuple(self.int() for _ in range(4))


def f32_bits_equal(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and a.astype("<f4").tobytes() == b.astype("<f4").tobytes()


def write_safetensors(path, tensors: dict, metadata: dict) -> None:
    """Writes a safetensors file (the format is a little-endian u64 header length, a JSON
    header, then the raw tensor bytes), keys in sorted order, 8-byte aligned header."""
    import json

    dtypes = {np.dtype("float32"): "F32", np.dtype("float16"): "F16", np.dtype("uint32"): "U32",
              np.dtype("int64"): "I64", np.dtype("uint8"): "U8"}
    header = {}
    blobs = []
    offset = 0
    for name in sorted(tensors):
        arr = np.ascontiguousarray(tensors[name])
        if arr.dtype not in dtypes:
            raise ValueError(f"{name}: unsupported dtype {arr.dtype}")
        raw = arr.astype(arr.dtype.newbyteorder("<")).tobytes()
        header[name] = {"dtype": dtypes[arr.dtype], "shape": list(arr.shape),
                        "data_offsets": [offset, offset + len(raw)]}
        blobs.append(raw)
        offset += len(raw)
    header["__metadata__"] = {k: str(v) for k, v in metadata.items()}
    hjson = json.dumps(header, separators=(",", ":"), sort_keys=True).encode()
    hjson += b" " * ((8 - len(hjson) % 8) % 8)
    import os

    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "wb") as f:
        f.write(struct.pack("<Q", len(hjson)))
        f.write(hjson)
        for raw in blobs:
            f.write(raw)
    os.replace(tmp, path)
