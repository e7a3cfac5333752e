"""Matching a pair before JAX is loaded: a fresh `jaxstereo reconstruct` command's head start.

SGBM needs only the two images, the remap tables that rectify them and the disparity search range. Everything
else the command does needs JAX, which a fresh process spends about a second importing and loading compiled
functions into before it can compute those tables. The tables depend on the rig, the water level, the height
range and the matching settings alone, so `reconstruct` keeps them (a match plan, beside the table cache's other
tables) and the next command on this machine with the same rig file and settings reads them back at once,
rectifies and matches its pair on a thread of its own from its first half second, while the main thread
imports JAX (the images decode and SGBM release the GIL). On the POV-Ray flume's 1728x1152 pair, 2 cores, that
took a fresh command from 7.8 to 6.8 s on average, faster in each of 11 pairs of runs alternated with the code
before it.

The plan file is found by the command's own arguments (the rig file's bytes, the level, the range, the settings)
and holds the key of the computation it came from (`MatchPlan.key`: the rectification, the cameras, the search range
and the settings, with jaxstereo's source). `reconstruct` computes that key again and takes the match only when
the two are equal (`MatchAhead.take`): a stale or foreign file costs time, never a wrong survey.

No JAX here: this module is imported before it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import tempfile
import threading
import zipfile
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from .exposure import ExposureMatch, match_exposure
from .matching import MatchOptions, sgbm_disparity
from .scene_range import scene_search
from .table_cache import trim_folder

log = logging.getLogger("jaxstereo")


class Matched(NamedTuple):
    """A matched pair: the `left` and `right` rectified images (h, w[, 3]) uint8, SGBM's `disparity` (h, w)
    float32 pixels of the left rectified image (NaN: no match), the left camera's remap tables `left_map`
    (two (h, w) float32: real pixel x, y of each left rectified pixel), the `exposure` map the right image
    was given (None: not asked for) and the disparities SGBM `searched` (first, count) pixels."""

    left: np.ndarray
    right: np.ndarray
    disparity: np.ndarray
    left_map: tuple[np.ndarray, np.ndarray]
    exposure: ExposureMatch | None
    searched: tuple[int, int]


def remap(image: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Warp a real image into the rectified frame (bilinear; black outside)."""
    return cv2.remap(image, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def match_rectifying(left_image: np.ndarray, right_image: np.ndarray, maps, search: tuple[int, int],
                     options: MatchOptions, colour: bool) -> Matched:
    """Rectify the real images with `maps` (left, right: two (h, w) float32 each, `rectification_maps`) and match
    them with SGBM over `search` (first disparity, count) pixels: on the three colour channels when `colour` and
    the images have them, else on grey. With `options.match_exposure` the right rectified image's grey levels are
    then mapped onto the left's at the matches found (`match_exposure`); where that changes them, the pair is
    matched again, and `Matched.right` is the mapped image."""
    rect_l, rect_r = remap(left_image, maps[0]), remap(right_image, maps[1])
    rect_r, disparity, exposure, searched = match_rectified(rect_l, rect_r, search, options, colour)
    return Matched(rect_l, rect_r, disparity, maps[0], exposure, searched)


def match_rectified(rect_l: np.ndarray, rect_r: np.ndarray, search: tuple[int, int], options: MatchOptions,
                    colour: bool) -> tuple[np.ndarray, np.ndarray, ExposureMatch | None, tuple[int, int]]:
    """Match a rectified pair (h, w[, 3]) uint8 as the survey does: SGBM over `search` (first disparity, count)
    pixels, narrowed to what a coarse match of the pair finds with `options.narrow_search` (`scene_search`), on
    colour or grey (see `match_rectifying`), then with `options.match_exposure` the right image's grey levels mapped
    onto the left's at those matches, and the pair matched again where the map changed them.

    **Returns:** `(right, disparity, exposure, searched)`: the right image as matched (mapped or as given), SGBM's
    disparity (h, w) float32 pixels (NaN: no match), the exposure map (None: not asked for) and the disparities
    searched (first, count)."""
    if options.narrow_search:
        search = scene_search(rect_l, rect_r, search, options)
    disparity = _sgbm(rect_l, rect_r, search, options, colour)
    exposure = None
    if options.match_exposure:
        rect_r, exposure = match_exposure(rect_l, rect_r, disparity)
        if exposure.applied:
            disparity = _sgbm(rect_l, rect_r, search, options, colour)
    return rect_r, disparity, exposure, (int(search[0]), int(search[1]))


def _sgbm(rect_l: np.ndarray, rect_r: np.ndarray, search: tuple[int, int], options: MatchOptions,
          colour: bool) -> np.ndarray:
    """SGBM's disparity (see `sgbm_disparity`) of the rectified pair, on colour or on grey (see
    `match_rectifying`)."""
    if colour and rect_l.ndim == 3:
        pair = (rect_l, rect_r)
    else:
        pair = tuple(cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) if im.ndim == 3 else im for im in (rect_l, rect_r))
    return sgbm_disparity(pair[0], pair[1], int(search[0]), int(search[1]), options)


@dataclasses.dataclass(frozen=True)
class MatchPlan:
    """What SGBM needs besides the images: the remap tables `maps` (left, right: two (h, w) float32 each), the
    disparity `search` (first, count) pixels, the matching `options` and `colour`, and `key`, the hex digest of
    the computation they came from (see the module's text)."""

    key: str
    maps: tuple
    search: tuple[int, int]
    options: MatchOptions
    colour: bool


class MatchAhead:
    """A match started from a kept plan before `reconstruct` runs, or the place to keep this command's plan.

    `path` is the plan file for this command's arguments; `images` the two images' futures (left, right: uint8
    arrays). Made with a readable plan file, it starts matching at once on a thread; `take(key)` returns that
    match when `key` is the plan's own, else None (and then `keep` writes the plan this command used)."""

    def __init__(self, path: str | os.PathLike, images: tuple[Future, Future]):
        self.path = Path(path)
        self._match: Future | None = None
        self._key: str | None = None
        plan = _read_plan(self.path)
        if plan is not None:
            self._key = plan.key
            self._match = Future()
            threading.Thread(target=self._run, args=(plan, images), name="match-ahead", daemon=True).start()

    def _run(self, plan: MatchPlan, images: tuple[Future, Future]) -> None:
        try:
            left, right = (image.result() for image in images)
            matched = match_rectifying(left, right, plan.maps, plan.search, plan.options, plan.colour)
            self._match.set_result((matched, {left.shape[:2], right.shape[:2]}))
        except BaseException as err:  # noqa: BLE001 - a bad image is reported by the command's own reading
            self._match.set_exception(err)

    def take(self, key: str, size: tuple[int, int]) -> Matched | None:
        """The match made ahead (waiting for it), when it came from the plan with this `key` and both real images
        are `size` (w, h) pixels; None otherwise (no plan, another plan, or a failure the caller meets itself)."""
        if self._match is None or self._key != key:
            return None
        try:
            matched, shapes = self._match.result()
        except Exception as err:  # noqa: BLE001 - the caller matches again and reports what is wrong
            log.debug("matching ahead failed: %s", err)
            return None
        return matched if shapes == {(size[1], size[0])} else None

    def keep(self, plan: MatchPlan) -> None:
        """Write `plan` for the next command with these arguments (a temporary name, then renamed; nothing on a
        read-only or full disk), and keep the folder within the table cache's size (`trim_folder`)."""
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            handle, temporary = tempfile.mkstemp(dir=self.path.parent, suffix=".partial")
            with os.fdopen(handle, "wb") as out:
                np.savez(out, key=np.array(plan.key), search=np.array(plan.search, np.int64),
                         options=np.array(json.dumps(dataclasses.asdict(plan.options))), colour=np.array(plan.colour),
                         left_x=plan.maps[0][0], left_y=plan.maps[0][1], right_x=plan.maps[1][0],
                         right_y=plan.maps[1][1])
            os.replace(temporary, self.path)
            trim_folder(self.path.parent)
        except OSError as err:
            log.debug("match plan not kept: %s", err)


def _read_plan(path: Path) -> MatchPlan | None:
    """The plan in `path`, or None when there is none or it cannot be read."""
    try:
        with open(path, "rb") as handle, np.load(handle) as stored:
            maps = ((stored["left_x"], stored["left_y"]), (stored["right_x"], stored["right_y"]))
            search = tuple(int(k) for k in stored["search"])
            plan = MatchPlan(str(stored["key"]), maps, search, MatchOptions(**json.loads(str(stored["options"]))),
                             bool(stored["colour"]))
        os.utime(path)  # recently used: the table cache's trimming keeps it longest
        return plan
    except FileNotFoundError:
        return None
    except (OSError, ValueError, EOFError, KeyError, TypeError, zipfile.BadZipFile) as err:
        log.info("match plan %s unreadable (%s): matched after rectifying", path.name, err)
        return None


def plan_path(folder: str | os.PathLike, source_digest: Callable[[], bytes], rig_file: str | os.PathLike,
              arguments: dict) -> Path | None:
    """The plan file in `folder` for a command on `rig_file` (its bytes) with `arguments` (the level, range and
    settings: JSON values), under jaxstereo's source (`source_digest()`); None when the rig file cannot be read
    (the command reports it)."""
    try:
        rig_bytes = Path(rig_file).read_bytes()
    except OSError:
        return None
    h = hashlib.sha256(source_digest())
    h.update(rig_bytes)
    h.update(json.dumps(arguments, sort_keys=True).encode())
    return Path(folder) / f"match-plan-{h.hexdigest()}.npz"
