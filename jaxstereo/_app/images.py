"""Reading images from disk with clear errors (unreadable files, empty globs, size mismatches)."""

from __future__ import annotations

import glob as _glob
import os
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from .._geometry.errors import JaxStereoError

# `_geometry.types.PathLike`, not imported from there: that module imports JAX (through jaxtyping), and the
# command line reads its images while JAX is imported.
PathLike = str | os.PathLike


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


def read_image(path: PathLike, grayscale: bool = False) -> np.ndarray:
    """Read an image file as uint8 (h, w, 3) RGB, or (h, w) grey; `JaxStereoError` if it cannot be read.

    Decoded by Pillow, which raises on broken files instead of printing to the process's stderr.
    Colour pixels equal OpenCV's `imread`; JPEG grey comes straight from the decoder's luma, as
    `IMREAD_GRAYSCALE` does (identical), other formats through OpenCV's RGB-to-grey weights (within one
    grey level of `imread`); 16-bit images keep their high byte.
    """
    path = Path(path)
    if not path.is_file():
        raise JaxStereoError(f"image {str(path)!r} does not exist")
    if path.stat().st_size == 0:
        raise JaxStereoError(f"image {str(path)!r} is empty (0 bytes)")
    try:
        with Image.open(path) as image:
            if grayscale and image.format == "JPEG":
                image.draft("L", image.size)  # the decoder's own luma, no colour conversion
            pixels = _to_uint8(image, grayscale)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise JaxStereoError(f"image {str(path)!r} cannot be read (corrupt, truncated or not an image)") from exc
    if pixels.size == 0:
        raise JaxStereoError(f"image {str(path)!r} has no pixels")
    return np.ascontiguousarray(pixels)


def _to_uint8(image: Image.Image, grayscale: bool) -> np.ndarray:
    """A Pillow image as uint8 grey (h, w) or RGB (h, w, 3); decoding happens here."""
    if image.mode.startswith("I;16") or image.mode == "I":
        high = (np.asarray(image).astype(np.uint32) >> 8).clip(0, 255).astype(np.uint8)
        return high if grayscale else np.repeat(high[..., None], 3, axis=-1)
    if grayscale and image.mode == "L":
        return np.asarray(image)
    rgb = np.asarray(image.convert("RGB"))
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if grayscale else rgb


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


def write_image(path: PathLike, image: np.ndarray) -> None:
    """Write an RGB (h, w, 3) or grey (h, w) uint8 image atomically (format from the suffix)."""
    from .io import atomic_path

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
