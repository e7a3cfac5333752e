"""Reading images from disk with clear errors (unreadable files, empty globs, size mismatches)."""

from __future__ import annotations

import contextlib
import glob as _glob
import os
import sys
import threading
from pathlib import Path

import cv2
import numpy as np

from ._errors import JaxStereoError


def expand_images(pattern_or_paths, what: str = "images") -> list[Path]:
    """Expand a glob pattern (or a list of paths/patterns) into a sorted list of existing files.

    Raises `JaxStereoError` when nothing matches.
    """
    items = [pattern_or_paths] if isinstance(pattern_or_paths, (str, Path)) else list(pattern_or_paths)
    paths: list[Path] = []
    for item in items:
        item = str(item)
        matches = sorted(_glob.glob(item)) if any(ch in item for ch in "*?[") else ([item] if Path(item).exists() else [])
        if not matches:
            raise JaxStereoError(f"no {what} match {item!r}")
        paths.extend(Path(m) for m in matches)
    return paths


_STDERR_LOCK = threading.Lock()


@contextlib.contextmanager
def _quiet_native_stderr():
    """Silence file descriptor 2 (C libraries' messages) for the duration; our own error says what is wrong.

    File descriptors are per process: the lock keeps threads (a threaded Dask worker) from interleaving
    the swap and leaving stderr pointed at /dev/null."""
    with _STDERR_LOCK:
        sys.stderr.flush()
        try:
            saved = os.dup(2)
        except OSError:
            yield
            return
        try:
            with open(os.devnull, "wb") as null:
                os.dup2(null.fileno(), 2)
                yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def read_image(path, grayscale: bool = False) -> np.ndarray:
    """Read an image file as uint8 (h, w, 3) RGB, or (h, w) grey; `JaxStereoError` if it cannot be read."""
    path = Path(path)
    if not path.is_file():
        raise JaxStereoError(f"image {str(path)!r} does not exist")
    if path.stat().st_size == 0:
        raise JaxStereoError(f"image {str(path)!r} is empty (0 bytes)")
    data = np.fromfile(str(path), dtype=np.uint8)
    with _quiet_native_stderr():  # libpng/libjpeg print their own complaints about broken files
        image = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE if grayscale else cv2.IMREAD_COLOR)
    if image is None or image.size == 0:
        raise JaxStereoError(f"image {str(path)!r} cannot be read (corrupt, truncated or not an image)")
    if not grayscale:
        image = image[..., ::-1].copy()
    return image


def read_images_same_size(paths, grayscale: bool = True) -> tuple[list[np.ndarray], tuple[int, int]]:
    """Read several images and check they share one size; returns `(images, (width, height))`."""
    images = [read_image(p, grayscale) for p in paths]
    h, w = images[0].shape[:2]
    for p, im in zip(paths, images):
        if im.shape[:2] != (h, w):
            raise JaxStereoError(
                f"image {str(p)!r} is {im.shape[1]}x{im.shape[0]} but {str(paths[0])!r} is {w}x{h}: "
                "all images of a camera must have the same size"
            )
    return images, (w, h)


def write_image(path, image: np.ndarray) -> None:
    """Write an RGB (h, w, 3) or grey (h, w) uint8 image atomically (format from the suffix)."""
    from ._io import atomic_path

    path = Path(path)
    bgr = image[..., ::-1] if image.ndim == 3 else image
    ok, data = cv2.imencode(path.suffix or ".png", np.ascontiguousarray(bgr))
    if not ok:
        raise JaxStereoError(f"cannot encode image for {str(path)!r}")
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(data.tobytes())


def check_texture(image: np.ndarray, what: str) -> None:
    """`JaxStereoError` if `image` is uniform (all black, all white...): nothing in it can be matched."""
    if image.size == 0 or int(image.max()) == int(image.min()):
        value = int(image.flat[0]) if image.size else 0
        raise JaxStereoError(f"{what} is uniform (every pixel {value}): no texture to match")


def check_pair(left: np.ndarray, right: np.ndarray, image_size: tuple[int, int], left_name: str = "left image",
               right_name: str = "right image") -> None:
    """`JaxStereoError` unless both images are `image_size` (w, h) pixels, the rig's, and carry texture."""
    w, h = image_size
    for name, image in ((left_name, left), (right_name, right)):
        if image.shape[:2] != (h, w):
            raise JaxStereoError(f"{name} is {image.shape[1]}x{image.shape[0]} but the rig's cameras are {w}x{h}")
    check_texture(left, left_name)
    check_texture(right, right_name)
