"""PC2 point caches (the format Blender's Mesh Cache modifier plays), written and read with numpy.

Layout, little-endian:
  header (32 bytes): signature b'POINTCACHE2\\0' (12 bytes), int32 version = 1, int32 num_points,
                     float32 start_frame, float32 sample_rate, int32 num_samples;
  body: num_samples × num_points × (x, y, z) float32, sample-major.
Sample s holds the positions at frame start_frame + s · sample_rate. Blender's Mesh Cache modifier in
'FRAME' time mode ignores start_frame and sample_rate and plays sample (frame · frame_scale − frame_start),
so the bake sets its frame_start; other readers (Maya, 3ds Max) use the header fields.

No bpy here: this module is plain numpy so it can be tested and reused outside Blender.
"""

from __future__ import annotations

import os
import struct
import tempfile
from pathlib import Path
from types import TracebackType

import numpy as np

SIGNATURE = b"POINTCACHE2\0"
VERSION = 1
_HEADER = struct.Struct("<12siiffi")
HEADER_SIZE = _HEADER.size  # 32
_SAMPLES_OFFSET = HEADER_SIZE - 4  # where num_samples sits, patched when the writer commits


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


class PC2Error(ValueError):
    """A PC2 file is malformed, or data does not fit the cache being written."""


def pack_header(num_points: int, start_frame: float, sample_rate: float, num_samples: int) -> bytes:
    return _HEADER.pack(SIGNATURE, VERSION, int(num_points), float(start_frame), float(sample_rate),
                        int(num_samples))


def read_header(path: str | os.PathLike) -> tuple[int, float, float, int]:
    """(num_points, start_frame, sample_rate, num_samples) of the PC2 file at `path`, checked against
    the file size. Raises PC2Error when the file is not a well-formed PC2 cache."""
    path = Path(path)
    with path.open("rb") as f:
        raw = f.read(HEADER_SIZE)
    if len(raw) != HEADER_SIZE:
        raise PC2Error(f"{path.name}: too short for a PC2 header ({len(raw)} bytes)")
    signature, version, num_points, start_frame, sample_rate, num_samples = _HEADER.unpack(raw)
    if signature != SIGNATURE:
        raise PC2Error(f"{path.name}: not a PC2 file (signature {signature!r})")
    if version != VERSION or num_points < 0 or num_samples < 0:
        raise PC2Error(f"{path.name}: unsupported PC2 header (version {version}, {num_points} points, "
                       f"{num_samples} samples)")
    expected = HEADER_SIZE + 12 * num_points * num_samples
    size = path.stat().st_size
    if size != expected:
        raise PC2Error(f"{path.name}: {size} bytes, but the header announces {num_samples} samples of "
                       f"{num_points} points ({expected} bytes)")
    return num_points, float(start_frame), float(sample_rate), num_samples


def read_pc2(path: str | os.PathLike) -> tuple[np.ndarray, float, float]:
    """(points (num_samples, num_points, 3) float32, start_frame, sample_rate) of a PC2 file."""
    num_points, start_frame, sample_rate, num_samples = read_header(path)
    points = np.fromfile(path, dtype="<f4", offset=HEADER_SIZE, count=num_samples * num_points * 3)
    return points.reshape(num_samples, num_points, 3).astype(np.float32), start_frame, sample_rate


class PC2Writer:
    """Streams samples into a PC2 file without holding the whole animation in memory.

    Samples go to a temporary file next to `path`; `commit()` patches the sample count into the
    header and renames the file over `path` in one step, so readers never see a half-written cache and
    an existing file is only replaced by a complete one. `abort()` (or leaving a `with` block through
    an exception) deletes the temporary file and leaves `path` untouched.
    """

    def __init__(self, path: str | os.PathLike, num_points: int, start_frame: float = 1.0,
                 sample_rate: float = 1.0) -> None:
        if num_points < 0:
            raise PC2Error(f"negative point count {num_points}")
        self.path = Path(path)
        self.num_points = int(num_points)
        self.num_samples = 0
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent)
        self._tmp = Path(tmp)
        self._file = os.fdopen(fd, "wb")
        try:
            # mkstemp makes the file private (0600); a cache read by render-farm accounts must get the
            # permissions an ordinary new file would get.
            os.chmod(self._tmp, 0o666 & ~_umask())
            self._file.write(pack_header(self.num_points, start_frame, sample_rate, 0))
        except BaseException:
            self.abort()
            raise

    def add(self, points: np.ndarray) -> None:
        """Append one sample: points (num_points, 3), written as little-endian float32."""
        if self._file is None:
            raise PC2Error("the cache was already committed or aborted")
        points = np.asarray(points)
        if points.shape != (self.num_points, 3):
            raise PC2Error(f"sample of shape {points.shape}, expected ({self.num_points}, 3)")
        if not np.all(np.isfinite(points)):
            raise PC2Error(f"sample {self.num_samples} has non-finite coordinates")
        self._file.write(np.ascontiguousarray(points, dtype="<f4").tobytes())
        self.num_samples += 1

    def commit(self) -> Path:
        """Finish the file and move it to `path` (replacing any previous file); returns `path`."""
        if self._file is None:
            raise PC2Error("the cache was already committed or aborted")
        try:
            self._file.seek(_SAMPLES_OFFSET)
            self._file.write(struct.pack("<i", self.num_samples))
            self._file.close()
            self._file = None
            os.replace(self._tmp, self.path)
        except BaseException:
            self.abort()
            raise
        return self.path

    def abort(self) -> None:
        """Drop the temporary file; `path` keeps whatever it held before. Safe to call twice."""
        if self._file is not None:
            self._file.close()
            self._file = None
        self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> PC2Writer:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, _exc: BaseException | None,
                 _tb: TracebackType | None) -> None:
        if exc_type is not None:
            self.abort()
        elif self._file is not None:
            self.commit()


def write_pc2(path: str | os.PathLike, points: np.ndarray, start_frame: float = 1.0,
              sample_rate: float = 1.0) -> Path:
    """Write points (num_samples, num_points, 3) as a PC2 file at `path` (atomically)."""
    points = np.asarray(points)
    if points.ndim != 3 or points.shape[2] != 3:
        raise PC2Error(f"points of shape {points.shape}, expected (samples, points, 3)")
    with PC2Writer(path, points.shape[1], start_frame, sample_rate) as writer:
        for sample in points:
            writer.add(sample)
    return writer.path
