"""Training-time access to a capture: lazy decoding behind a cache bounded in bytes.

Nothing is decoded until a view is asked for, and decoded views are kept in an LRU cache whose
total size never exceeds ``cache_bytes``, so a capture larger than memory still trains (at the
price of decoding again on a miss). The bound is per process: each DataLoader worker holds its own
cache, so give workers ``cache_bytes / num_workers``.

Conventions of the served tensors:
- ``image`` (H, W, 3) float32, values as stored in the file scaled to 0..1 (PNG/JPEG therefore
  stay sRGB-encoded; EXR stays linear). Grey images are repeated to 3 channels.
- ``mask`` (H, W, 1) float32 in 0..1: the fraction of the pixel covered by the foreground (alpha),
  from masks/ or else from the image's alpha channel; None when neither exists. Where it is
  fractional the image holds *straight* (unpremultiplied) colour, the colour of the foreground
  part alone, as PNG alpha does, so that ``image * mask + bg * (1 - mask)`` is the pixel in front
  of background ``bg`` (what the trainer and `dgs eval` compare with). A binary mask over an image
  that shows the real background fits the convention as well. Seeding, the foreground of the
  metrics and the masked losses count a pixel as foreground when its mask is > 0.5.
- ``normal`` (H, W, 3) float32 world-space normals (PNG decoded as 2 v - 1; camera-space priors
  rotated to world); None when the view has no prior.
When the camera has distortion and ``undistort`` is on, all three are resampled to the ideal pinhole
with the same K and cropped to the largest rectangle every pixel of which samples the source
image (as COLMAP's undistorter crops): the rim that samples outside it, or blends with the
outside, holds no picture, and trained or scored as if it did it costs several dB (the fox: a
one-pixel rim of black-blended pixels at 1/8 held most of the held-out error). The served camera
has ``distortion=None`` and the crop's size and principal point. Downscaling (area averaging)
happens after that. Both keep the convention: the mask is resampled as coverage and the image
weighted by it (premultiplied, resampled, divided again), so the foreground colour of an edge
pixel does not take in the background that the mask removes.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from core.data.capture import Camera, Capture
from core.data.images import ImageReadError, read_image

__all__ = ["ByteLRUCache", "CaptureDataset", "Sample"]


@dataclass
class Sample:
    """One view served for training."""

    index: int
    frame: str
    camera_id: str
    camera: Camera
    """The camera matching the served tensors (scaled, undistorted)."""
    image: torch.Tensor
    """(H, W, 3) float32 in 0..1, values as stored (see module doc)."""
    mask: torch.Tensor | None
    """(H, W, 1) float32 in 0..1 or None."""
    normal: torch.Tensor | None
    """(H, W, 3) float32 world-space normal prior or None."""


class ByteLRUCache:
    """Least-recently-used cache of numpy arrays whose total ``nbytes`` stays <= ``max_bytes``."""

    def __init__(self, max_bytes: int):
        if max_bytes < 0:
            raise ValueError(f"max_bytes: expected >= 0, got {max_bytes}")
        self.max_bytes = int(max_bytes)
        self.nbytes = 0
        self.hits = 0
        self.misses = 0
        self._items: OrderedDict[Hashable, tuple[Any, int]] = OrderedDict()

    def __len__(self) -> int:
        return len(self._items)

    def get(self, key: Hashable) -> Any | None:
        item = self._items.get(key)
        if item is None:
            self.misses += 1
            return None
        self.hits += 1
        self._items.move_to_end(key)
        return item[0]

    def put(self, key: Hashable, value: Any, nbytes: int) -> None:
        """Insert; an item larger than the whole budget is simply not kept."""
        if key in self._items:
            self.nbytes -= self._items.pop(key)[1]
        if nbytes > self.max_bytes:
            return
        while self.nbytes + nbytes > self.max_bytes and self._items:
            self.nbytes -= self._items.popitem(last=False)[1][1]
        self._items[key] = (value, nbytes)
        self.nbytes += nbytes


def _nbytes(value: Any) -> int:
    if isinstance(value, np.ndarray):
        return value.nbytes
    if isinstance(value, tuple):
        return sum(_nbytes(v) for v in value)
    return 0 if value is None else 64


class CaptureDataset(torch.utils.data.Dataset):
    """Views of a capture, frame-major: index = frame_index * n_cameras + camera_index."""

    def __init__(
        self,
        capture: Capture,
        *,
        frames: Sequence[str] | None = None,
        cameras: Sequence[str] | None = None,
        downscale: float = 1.0,
        undistort: bool = True,
        cache_bytes: int = 1 << 30,
        matte: bool = True,
    ):
        if not downscale >= 1.0:
            raise ValueError(f"downscale: expected a factor >= 1, got {downscale}")
        self.capture = capture
        self.frames = list(frames) if frames is not None else list(capture.frames)
        missing = [f for f in self.frames if f not in capture.frames]
        if missing:
            raise ValueError(f"frames: not in the capture: {missing}")
        ids = list(cameras) if cameras is not None else [c.id for c in capture.cameras]
        self.cameras = [capture.camera(i) for i in ids]
        self.downscale = float(downscale)
        self.undistort = undistort
        self.matte = matte
        """The masks are mattes: a downscaled image keeps the straight colour of the masked
        part at its edges. Off (masks that only mark a subject inside the picture): the
        picture is resampled as it is."""
        self.cache = ByteLRUCache(cache_bytes)

    def __len__(self) -> int:
        return len(self.frames) * len(self.cameras)

    def index_of(self, frame: str, camera_id: str) -> int:
        cam_ids = [c.id for c in self.cameras]
        return self.frames.index(frame) * len(self.cameras) + cam_ids.index(camera_id)

    def served_camera(self, camera: Camera) -> Camera:
        """The camera matching served tensors: undistorted and cropped (if enabled) and
        downscaled."""
        if self.undistort and camera.distortion is not None:
            x0, y0, cw, ch = self._crop(camera)
            K = camera.K.copy()
            K[0, 2] -= x0
            K[1, 2] -= y0
            camera = Camera(camera.id, cw, ch, K, camera.world_to_camera, None)
        w = max(1, round(camera.width / self.downscale))
        h = max(1, round(camera.height / self.downscale))
        return camera.scaled(w, h)

    def _crop(self, cam: Camera) -> tuple[int, int, int, int]:
        """(x0, y0, width, height) of the undistorted image that samples only the source."""
        key = ("crop", cam.id)
        crop = self.cache.get(key)
        if crop is None:
            map_x, map_y = self._undistort_maps(cam)
            # Bilinear taps stay inside: a sample within half a pixel of the edge blends with
            # the constant border.
            valid = (map_x >= 0) & (map_y >= 0) & (map_x <= cam.width - 1) & \
                (map_y <= cam.height - 1)
            crop = _inner_rectangle(valid)
            self.cache.put(key, crop, 64)
        return crop

    def __getitem__(self, index: int) -> Sample:
        if not -len(self) <= index < len(self):
            raise IndexError(f"index: {index} out of range for {len(self)} views")
        index %= len(self)
        frame = self.frames[index // len(self.cameras)]
        cam = self.cameras[index % len(self.cameras)]
        image, mask, normal = self._load(frame, cam)
        return Sample(
            index=index,
            frame=frame,
            camera_id=cam.id,
            camera=self.served_camera(cam),
            image=torch.from_numpy(image.copy()),
            mask=None if mask is None else torch.from_numpy(mask.copy()),
            normal=None if normal is None else torch.from_numpy(normal.copy()),
        )

    def _load(
        self, frame: str, cam: Camera
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        key = ("view", frame, cam.id)
        hit = self.cache.get(key)
        if hit is not None:
            return hit
        value = self._decode(frame, cam)
        self.cache.put(key, value, _nbytes(value))
        return value

    def _decode(
        self, frame: str, cam: Camera
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        view = self.capture.view(frame, cam.id)
        if view.image is None:
            raise ImageReadError(
                f"images/{frame}/{cam.id}.png", "missing image (run dgs capture validate)"
            )
        raw = self._read(view.image)
        image = _to_rgb(raw)
        mask = None
        if view.mask is not None:
            mask = self._read(view.mask)[:, :, :1]
        elif raw.shape[2] in (2, 4):
            mask = raw[:, :, -1:].copy()
        normal = self._read_normal(view.normal, cam) if view.normal is not None else None
        image = self._resample(image, cam, weight=mask if self.matte else None)
        mask = self._resample(mask, cam)
        normal = self._resample(normal, cam)
        if normal is not None:
            norm = np.linalg.norm(normal, axis=2, keepdims=True)
            # Near-zero vectors mark "no prior" (8-bit PNG stores 0 as 128/255, norm ~0.007).
            normal = np.where(norm > 0.1, normal / np.maximum(norm, 1e-6), 0.0).astype(np.float32)
        return image, mask, normal

    def _name(self, path: Path) -> str:
        """How the capture's author knows a file of it: relative to the capture folder."""
        root = Path(self.capture.root)
        return path.relative_to(root).as_posix() if path.is_relative_to(root) else str(path)

    def _read(self, path: Path) -> np.ndarray:
        try:
            return read_image(path)
        except ImageReadError as exc:
            raise exc.named(self._name(path)) from None

    def _read_normal(self, path: Any, cam: Camera) -> np.ndarray:
        raw = self._read(path)
        if raw.shape[2] < 3:
            raise ImageReadError(
                self._name(path), f"normal map needs 3 channels, got {raw.shape[2]}"
            )
        n = raw[:, :, :3]
        if path.suffix.lower() != ".exr":
            n = n * 2.0 - 1.0
        if self.capture.normals_space == "camera":
            # Camera-space (OpenCV axes) to world: n_w = R^T n_c.
            n = n @ cam.R.astype(np.float32)
        return np.ascontiguousarray(n, dtype=np.float32)

    def _resample(self, arr: np.ndarray | None, cam: Camera,
                  weight: np.ndarray | None = None) -> np.ndarray | None:
        """Undistort (bilinear) and downscale (area) `arr`; with `weight` (the mask) the straight
        colour of the weighted part: resample(arr * weight) / resample(weight), and the plain
        resampled value where no weight is left."""
        if arr is None:
            return None
        served = self.served_camera(cam)
        moves = (self.undistort and cam.distortion is not None) or (
            (served.width, served.height) != (arr.shape[1], arr.shape[0]))
        if weight is not None and moves:
            num, den = self._resample(arr * weight, cam), self._resample(weight, cam)
            plain = self._resample(arr, cam)
            # 1/1024 of a pixel: below that the division only amplifies rounding.
            return np.ascontiguousarray(
                np.where(den > 1 / 1024, num / np.maximum(den, 1 / 1024), plain), dtype=np.float32)

        if self.undistort and cam.distortion is not None:
            map_x, map_y = self._undistort_maps(cam)
            arr = cv2.remap(arr, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            x0, y0, cw, ch = self._crop(cam)
            arr = arr[y0:y0 + ch, x0:x0 + cw]
        if (served.width, served.height) != (arr.shape[1], arr.shape[0]):
            arr = cv2.resize(arr, (served.width, served.height), interpolation=cv2.INTER_AREA)
        if arr.ndim == 2:
            arr = arr[:, :, None]
        return np.ascontiguousarray(arr, dtype=np.float32)

    def _undistort_maps(self, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
        key = ("undistort", cam.id)
        maps = self.cache.get(key)
        if maps is None:
            # OpenCV puts pixel centres at integer coordinates; ours are at +0.5 (DESIGN 3.1).
            K = cam.K.copy()
            K[0, 2] -= 0.5
            K[1, 2] -= 0.5
            dist = np.array(cam.distortion, dtype=np.float64)
            maps = cv2.initUndistortRectifyMap(
                K, dist, None, K, (cam.width, cam.height), cv2.CV_32FC1
            )
            self.cache.put(key, maps, _nbytes(maps))
        return maps


def _inner_rectangle(valid: np.ndarray) -> tuple[int, int, int, int]:
    """(x0, y0, width, height) of a large axis-aligned rectangle of True pixels in `valid`
    (H, W): the full image shrunk, one row or column at a time, on the side with the most
    invalid pixels along its edge (undistortion leaves a convex-ish valid region)."""
    x0, y0, x1, y1 = 0, 0, valid.shape[1], valid.shape[0]
    while x1 - x0 > 1 and y1 - y0 > 1:
        bad = {"top": int((~valid[y0, x0:x1]).sum()), "bottom": int((~valid[y1 - 1, x0:x1]).sum()),
               "left": int((~valid[y0:y1, x0]).sum()), "right": int((~valid[y0:y1, x1 - 1]).sum())}
        side = max(bad, key=bad.get)
        if bad[side] == 0:
            break
        x0, y0 = x0 + (side == "left"), y0 + (side == "top")
        x1, y1 = x1 - (side == "right"), y1 - (side == "bottom")
    return x0, y0, x1 - x0, y1 - y0


def _to_rgb(raw: np.ndarray) -> np.ndarray:
    channels = raw.shape[2]
    if channels in (1, 2):
        return np.ascontiguousarray(np.repeat(raw[:, :, :1], 3, axis=2))
    return np.ascontiguousarray(raw[:, :, :3])
