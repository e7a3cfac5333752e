"""Surveys: reconstructed point clouds, their `.npz` file, `.ply` export and preview figure."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import zipfile
from pathlib import Path

import numpy as np

from .._app.io import atomic_path, temporary_path
from .._geometry.errors import JaxStereoError
from .._geometry.types import PathLike


@dataclasses.dataclass(frozen=True)
class Survey:
    """A reconstructed point cloud in the world frame.

    **Fields:** `points` (N, 3) world metres; `colors` (N, 3) uint8 RGB; `pixels` (N, 2) left-image
    pixels; `submerged` (N,) bool; `rig_json` the rig used (JSON text); `model` "exact",
    "first-order" or "none"; `water_level` metres (NaN for a dry survey); `cov` (N, 6) each point's
    covariance [xx, yy, zz, xy, xz, yz] m^2 (world axes; matching and shared errors together, see
    `jaxstereo._stereo.uncertainty`), None when not known (surveys written before it existed);
    `sigma_z_match` (N,) the vertical std (metres) from matching alone, independent between points beyond
    the matching window, `sigma_z_level` (N,) from the water level alone, and `dz_subpixel` (N,) the signed
    vertical offset between the two sub-pixel estimators (SGBM's own minus the refined, averaged over the
    window: a systematic error of unknown sign, see `refine_disparity`), or None; the rest of `sigma_z`
    (`sigma_z_calibration`) comes from the calibration. The level's and the calibration's parts are shared by
    every point of the survey.
    """

    points: np.ndarray
    colors: np.ndarray
    pixels: np.ndarray
    submerged: np.ndarray
    rig_json: str
    model: str
    water_level: float
    cov: np.ndarray | None = None
    sigma_z_match: np.ndarray | None = None
    sigma_z_level: np.ndarray | None = None
    dz_subpixel: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def sigma_z(self) -> np.ndarray | None:
        """Each point's vertical standard deviation (N,) metres, or None when the survey has no covariance."""
        return None if self.cov is None else np.sqrt(np.maximum(self.cov[:, 2].astype(np.float64), 0.0))

    @property
    def sigma_z_shared(self) -> np.ndarray | None:
        """The part of `sigma_z` (N,) metres that does not average out between points (calibration, water level,
        the sub-pixel estimators' disagreement), or None."""
        if self.cov is None or self.sigma_z_match is None:
            return None
        return np.sqrt(np.maximum(self.cov[:, 2].astype(np.float64) - self.sigma_z_match.astype(np.float64) ** 2, 0.0))

    @property
    def sigma_z_calibration(self) -> np.ndarray | None:
        """The part of `sigma_z` (N,) metres that the calibration gives (shared, the level's part left out)."""
        shared = self.sigma_z_shared
        if shared is None or self.sigma_z_level is None:
            return None
        method = 0.0 if self.dz_subpixel is None else self.dz_subpixel.astype(np.float64) ** 2
        return np.sqrt(np.maximum(shared**2 - self.sigma_z_level.astype(np.float64) ** 2 - method, 0.0))


def save_survey(survey: Survey, path: PathLike) -> None:
    """Write the survey `.npz` atomically."""
    writer = SurveyWriter(path)
    try:
        writer.write_points(survey)
        writer.finish(survey)
    except BaseException:
        writer.discard()
        raise


class SurveyWriter:
    """A survey `.npz` written in steps, under a temporary name beside `path` until the last: the points as soon
    as they are known (`write_points`), the covariances row by row as they are propagated (`error_rows`, optional),
    then the rest of the error fields (`finish`), which renames the file to `path`; `discard` removes it instead.
    The command line writes the points and the covariances (four fifths of a survey's 100 MB) while the errors are
    propagated. The file is the one `np.savez` writes (stored, not compressed). One step at a time: the steps
    share one open archive."""

    def __init__(self, path: PathLike):
        self.path = Path(path)
        if self.path.suffix != ".npz":
            raise JaxStereoError(f"survey file {str(self.path)!r} must end in .npz")
        self._temporary = temporary_path(self.path)
        try:
            self._archive = zipfile.ZipFile(self._temporary, "w", zipfile.ZIP_STORED, allowZip64=True)
        except BaseException:
            os.remove(self._temporary)
            raise
        self._cov_member = None  # the covariances' member while its rows come in
        self._cov_rows = 0
        self._cov = None  # the covariances, once all their rows are written

    def error_rows(self, fields: dict, start: int, stop: int) -> None:
        """Rows `start:stop` of the error fields (`reconstruct`'s `on_error_rows`: in order, from the first): the
        covariances (`fields["cov"]`, (n, 6) float32) go into the file now, the other fields with `finish`."""
        cov = fields["cov"]
        if cov.dtype != np.float32:
            raise JaxStereoError(f"the covariances must be float32, got {cov.dtype}")
        if start != self._cov_rows:
            raise JaxStereoError(f"covariance rows {start}:{stop} came after {self._cov_rows} rows written")
        if start == 0:
            self._cov_member = self._archive.open("cov.npy", "w", force_zip64=True)
            np.lib.format.write_array_header_1_0(self._cov_member, np.lib.format.header_data_from_array_1_0(cov))
        self._cov_member.write(np.ascontiguousarray(cov[start:stop]).data)
        self._cov_rows = stop
        if stop == cov.shape[0]:
            self._cov_member.close()
            self._cov = cov

    def write_points(self, survey: Survey) -> None:
        """The survey's points, colours, pixels, flags, rig, model and water level."""
        # np.asarray: no copy of an array already of its type
        self._write(points=np.asarray(survey.points, dtype=np.float64), colors=np.asarray(survey.colors, np.uint8),
                    pixels=np.asarray(survey.pixels, np.float32), submerged=np.asarray(survey.submerged, bool),
                    rig=np.array(survey.rig_json), model=np.array(survey.model),
                    water_level=np.array(survey.water_level, dtype=np.float64))

    def finish(self, survey: Survey) -> None:
        """The survey's error fields (those it has, less the covariances `error_rows` wrote: they must be the
        survey's), then the file under its own name."""
        fields = {key: np.asarray(getattr(survey, key), dtype=np.float32)
                  for key in ("cov", "sigma_z_match", "sigma_z_level", "dz_subpixel")
                  if getattr(survey, key) is not None}
        if self._cov_member is not None:
            cov = fields.get("cov")
            if self._cov is None or not (cov is self._cov or np.array_equal(cov, self._cov)):
                raise JaxStereoError("the covariances written row by row are not the survey's")
            del fields["cov"]
        self._write(**fields)
        self._archive.close()
        os.replace(self._temporary, self.path)

    def discard(self) -> None:
        """Remove the temporary file (nothing is left at `path`); after `finish`, nothing to do."""
        with contextlib.suppress(OSError):  # a full disk fails the archive's last write: removed all the same
            self._archive.close()
        with contextlib.suppress(FileNotFoundError):
            os.remove(self._temporary)

    def _write(self, **arrays: np.ndarray) -> None:
        for name, value in arrays.items():
            with self._archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                if value.ndim and value.flags.c_contiguous and value.dtype.kind in "biuf":
                    np.lib.format.write_array_header_1_0(member, np.lib.format.header_data_from_array_1_0(value))
                    member.write(value.data)  # the same bytes, without the copy `write_array` makes of each chunk
                else:
                    np.lib.format.write_array(member, value, allow_pickle=False)


def load_survey(path: PathLike) -> Survey:
    """Read a survey `.npz`; `JaxStereoError` names the file and what is wrong with it."""
    from .._app.io import read_npz

    return survey_from_fields(read_npz(path, "survey"), path)


def survey_from_fields(fields: dict, path) -> Survey:
    """A `Survey` from the arrays of a survey `.npz` (already read); `path` names it in errors."""
    for key in ("points", "colors", "pixels", "submerged"):
        if key not in fields:
            raise JaxStereoError(f"survey {str(path)!r} has no {key!r} array")
    points = np.asarray(fields["points"], dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise JaxStereoError(f"survey {str(path)!r}: points must have shape (N, 3), got {points.shape}")
    bad = int(np.count_nonzero(~np.all(np.isfinite(points), axis=1)))
    if bad:
        raise JaxStereoError(f"survey {str(path)!r} holds {bad} point(s) with NaN or infinite coordinates")
    cov = _optional(fields, "cov", (points.shape[0], 6), path)
    sigma_z_match, sigma_z_level, dz_subpixel = (_optional(fields, key, (points.shape[0],), path)
                                                 for key in ("sigma_z_match", "sigma_z_level", "dz_subpixel"))
    return Survey(points, np.asarray(fields["colors"]), np.asarray(fields["pixels"]),
                  np.asarray(fields["submerged"], dtype=bool), str(fields.get("rig", "")),
                  str(fields.get("model", "")), float(fields.get("water_level", np.nan)), cov, sigma_z_match,
                  sigma_z_level, dz_subpixel)


def _optional(fields: dict, key: str, shape: tuple, path) -> np.ndarray | None:
    """An optional per-point array of the survey file: None when absent; checked for shape and finiteness."""
    if key not in fields:
        return None
    value = np.asarray(fields[key], dtype=np.float32)
    if value.shape != shape:
        raise JaxStereoError(f"survey {str(path)!r}: {key} must have shape {shape}, got {value.shape}")
    if not np.all(np.isfinite(value)):
        raise JaxStereoError(f"survey {str(path)!r}: {key} holds NaN or infinite values")
    return value


def save_ply(survey: Survey, path: PathLike) -> None:
    """Write the points and colours as a binary little-endian PLY, atomically; with the survey's covariance,
    also the vertical std `sigma_z` and its matching part `sigma_z_match` (float, metres), which CloudCompare
    shows as scalar fields."""
    n = len(survey)
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("r", "u1"), ("g", "u1"), ("b", "u1")]
    scalars = {}
    if survey.cov is not None:
        scalars["sigma_z"] = survey.sigma_z
        if survey.sigma_z_match is not None:
            scalars["sigma_z_match"] = survey.sigma_z_match
    fields += [(name, "<f4") for name in scalars]
    header = (f"ply\nformat binary_little_endian 1.0\ncomment jaxstereo survey, model {survey.model}, world metres\n"
              f"element vertex {n}\nproperty double x\nproperty double y\nproperty double z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\n"
              + "".join(f"property float {name}\n" for name in scalars) + "end_header\n").encode()
    record = np.zeros(n, dtype=fields)
    record["x"], record["y"], record["z"] = survey.points.T
    record["r"], record["g"], record["b"] = survey.colors.T
    for name, values in scalars.items():
        record[name] = values
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(header)
        fh.write(record.tobytes())


# (left, bottom, width, height) in figure fractions: the image panel, the top view, the colour bar
PREVIEW_PANELS = ((0.06, 0.1, 0.39, 0.78), (0.52, 0.1, 0.38, 0.78), (0.92, 0.15, 0.012, 0.68))
PREVIEW_SIZE_PX = (1560, 576)  # width, height
SUBMERGED_COLOUR = (31, 119, 180)  # the legend's square: matplotlib's first colour


def plot_survey_preview(survey: Survey, image_size: tuple[int, int], path, title: str = "") -> None:
    """`survey_preview_png` written to `path` (atomically)."""
    from .._app.io import write_bytes_atomic

    write_bytes_atomic(path, survey_preview_png(survey, image_size, title))


def survey_preview_png(survey: Survey, image_size: tuple[int, int], title: str = "") -> bytes:
    """The survey's preview, a PNG in memory (`PREVIEW_SIZE_PX`): height in the left image's pixels (`image_size`
    (w, h) pixels) and a top view (x, y metres) coloured by height (viridis, the heights' 1st to 99th percentile),
    with a colour bar, and in the top view the submerged share.

    Drawn with Pillow (`_app/raster_figure.py`), not matplotlib, whose import and axes cost a fresh `reconstruct`
    about a sixth of its time (docs/speed.md, round 70). At most about 1000 pixels of the image are drawn per side.
    """
    from .._app.raster_figure import RasterFigure, colour_mapped

    w, h = image_size
    z = survey.points[:, 2]
    if len(survey):
        vmin, vmax = (float(v) for v in np.percentile(z, [1, 99]))
    else:
        vmin, vmax = 0.0, 1.0
    step = max(1, int(np.ceil(max(w, h) / 1000)))  # at most ~1000 px drawn: a panel is ~600 px wide anyway
    gw, gh = -(-w // step), -(-h // step)
    grid = np.full((gh, gw), np.nan)
    pu, pv = (np.floor((survey.pixels[:, k] + 0.5) / step).astype(np.intp) for k in (0, 1))
    ok = (pu >= 0) & (pu < gw) & (pv >= 0) & (pv < gh)
    grid[pv[ok], pu[ok]] = z[ok]
    fig = RasterFigure(*PREVIEW_SIZE_PX)
    fig.image_panel(fig.box(PREVIEW_PANELS[0]), colour_mapped(grid, vmin, vmax),
                    (-0.5, gw * step - 0.5, gh * step - 0.5, -0.5), "height (m) in the left image", "u (px)", "v (px)")
    top, extent = _top_view(survey.points)
    panel = fig.image_panel(fig.box(PREVIEW_PANELS[1]), colour_mapped(top[::-1], vmin, vmax), extent, "top view",
                            "x (m)", "y (m)", anchor="W")  # a narrow top view sits beside the image panel
    if np.isfinite(survey.water_level) and survey.submerged.any():
        fig.legend(panel, SUBMERGED_COLOUR, f"{100 * survey.submerged.mean():.0f}% submerged")
    fig.colour_bar(fig.box(PREVIEW_PANELS[2]), vmin, vmax, "z (m)")
    fig.text((PREVIEW_SIZE_PX[0] / 2, 12), title or f"survey: {len(survey)} points, model {survey.model}",
             round(1.2 * fig.text_px), "mt")
    return fig.png()


def _top_view(points: np.ndarray, cells: int = 500):
    """Mean height on a regular (x, y) grid of about `cells` cells along the longer side (NaN where empty);
    returns `(image, extent)`: row 0 at the lowest y, the extent `(left, right, bottom, top)` metres. Drawing an
    image, not a scatter of every point, keeps the preview fast for millions of points."""
    if points.shape[0] == 0:
        return np.full((1, 1), np.nan), (0.0, 1.0, 0.0, 1.0)
    x, y = points[:, 0], points[:, 1]  # column by column: numpy reduces an (n, 2) array's axis 0 4x slower
    lo, hi = np.array([x.min(), y.min()]), np.array([x.max(), y.max()])
    size = max(float(np.max(hi - lo)) / cells, 1e-6)
    shape = np.maximum(np.ceil((hi - lo) / size).astype(int), 1)
    i = np.minimum(((x - lo[0]) / size).astype(np.intp), shape[0] - 1)
    j = np.minimum(((y - lo[1]) / size).astype(np.intp), shape[1] - 1)
    flat = j * shape[0] + i
    count = np.bincount(flat, minlength=shape[0] * shape[1])
    total = np.bincount(flat, weights=points[:, 2], minlength=shape[0] * shape[1])
    with np.errstate(invalid="ignore", divide="ignore"):
        image = np.where(count > 0, total / count, np.nan).reshape(shape[1], shape[0])
    return image, (lo[0], lo[0] + shape[0] * size, lo[1], lo[1] + shape[1] * size)


def survey_summary_json(summary: dict) -> str:
    return json.dumps(summary, indent=2, default=float)
