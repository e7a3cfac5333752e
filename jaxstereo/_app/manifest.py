"""Campaign manifests for `jaxstereo batch`: which stereo pairs, which rig, which damage settings.

A manifest is a TOML file. Paths in it are relative to the manifest's folder. Example::

    rig = "rig.json"              # required
    water_level = 0.158           # metres, world Z; default: the rig's interface (dry if none)
    model = "exact"               # exact | first-order | none
    z_range = [-0.05, 0.45]       # optional, metres: bounds the disparity search
    spacing = 0.005               # DEM cell size, metres
    max_gap = 0.01                # fill DEM holes up to this size, metres

    [damage]                      # optional: without it pairs are surveyed and gridded only
    dn50 = 0.036                  # metres
    slope = "1:2"
    swl = 0.158                   # metres
    slope_origin = [1.2, 0.0]     # (x, z) of a point of the design slope (its toe), metres; or fit_slope = true
    stretch = [-0.2, 0.2]         # optional: the tested stretch, y from, y to (metres); default the whole width
    active_zone = [6, 4]          # optional: erosion counted from 6 Dn50 below to 4 Dn50 above the SWL

    [[pair]]                      # one table per stereo pair
    test = "T01"
    stage = "I"
    left = "T01/I_L.png"
    right = "T01/I_R.png"
    reference = true              # optional: the stage the others are compared with (default: the first)
    water_level = 0.160           # optional, overrides the top-level value

Instead of `[[pair]]` tables, `pairs = "FOLDER"` takes every `TEST_STAGE_L.ext` / `TEST_STAGE_R.ext`
in that folder (png, jpg, jpeg, tif, tiff, bmp); stages are ordered naturally (numbers by value) unless
`stages = ["I", "II", ...]` gives the order.
"""

from __future__ import annotations

import dataclasses
import math
import re
import tomllib
from pathlib import Path

from .._geometry.errors import JaxStereoError
from .._geometry.types import PathLike

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
_TOP_KEYS = {"rig", "water_level", "model", "z_range", "spacing", "max_gap", "damage", "pair", "pairs", "stages",
             "output"}
_PAIR_KEYS = {"test", "stage", "left", "right", "reference", "water_level"}
_DAMAGE_KEYS = {"dn50", "slope", "swl", "slope_origin", "fit_slope", "profile_spacing", "stretch", "active_zone"}


@dataclasses.dataclass(frozen=True)
class PairEntry:
    """One stereo pair of a campaign: `test` and `stage` names, absolute image paths, its `water_level`
    (metres, or None for the rig's), whether it is its test's `reference` stage, and `index` (manifest order)."""

    test: str
    stage: str
    left: Path
    right: Path
    water_level: float | None
    reference: bool
    index: int

    @property
    def key(self) -> str:
        return f"{self.test}/{self.stage}"


@dataclasses.dataclass(frozen=True)
class DamageSettings:
    """Damage settings: `dn50` metres, `slope` (as given, e.g. "1:2"), `swl` metres, the design slope's
    `slope_origin` (x, z) metres or `fit_slope` (fitted to each test's reference DEM), and optional
    `profile_spacing` metres, `stretch` (y0, y1) metres and `active_zone` (below, above) in Dn50."""

    dn50: float
    slope: str
    swl: float
    slope_origin: tuple[float, float] | None = None
    profile_spacing: float | None = None
    fit_slope: bool = False
    stretch: tuple[float, float] | None = None
    active_zone: tuple[float, float] | None = None


@dataclasses.dataclass(frozen=True)
class Manifest:
    """A parsed campaign: the manifest `path`, the `rig` file, reconstruction settings (`model`,
    `z_range` metres or None, DEM `spacing` and `max_gap` metres), optional `damage` settings, the
    `pairs` in processing order (each test's reference first) and the default `output` folder."""

    path: Path
    rig: Path
    model: str
    z_range: tuple[float, float] | None
    spacing: float
    max_gap: float
    damage: DamageSettings | None
    pairs: tuple[PairEntry, ...]
    output: Path

    def tests(self) -> list[str]:
        seen: dict[str, None] = {}
        for p in self.pairs:
            seen.setdefault(p.test, None)
        return list(seen)

    def reference_of(self, test: str) -> PairEntry:
        return next(p for p in self.pairs if p.test == test and p.reference)


def _pair_of_numbers(path, table: dict, key: str):
    value = table.get(key)
    if value is None:
        return None
    if not isinstance(value, list) or len(value) != 2 or not all(isinstance(v, (int, float)) for v in value):
        _fail(path, f"[damage] {key} must be a list of two numbers, got {value!r}")
    return float(value[0]), float(value[1])


def _fail(path: Path, message: str):
    raise JaxStereoError(f"{'folder' if path.is_dir() else 'manifest'} {str(path)!r}: {message}")


def _number(path, table: dict, key: str, where: str, default=None, positive=False):
    if key not in table:
        if default is None:
            return None
        return default
    value = table[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        _fail(path, f"{where}{key} must be a finite number, got {value!r}")
    if positive and value <= 0:
        _fail(path, f"{where}{key} must be positive, got {value!r}")
    return float(value)


def _name(path, table: dict, key: str, where: str) -> str:
    value = table.get(key)
    if not isinstance(value, (str, int)) or isinstance(value, bool) or str(value).strip() == "":
        _fail(path, f"{where}needs a {key!r} (a name), got {value!r}")
    text = str(value).strip()
    if not re.fullmatch(r"[A-Za-z0-9._+-]+", text) or text in (".", ".."):
        _fail(path, f"{where}{key} {text!r} may hold only letters, digits and . _ + - (it names output folders)")
    return text


_ROMAN = re.compile(r"M{0,3}(CM|CD|D?C{0,3})(XC|XL|L?X{0,3})(IX|IV|V?I{0,3})")


def _roman_value(text: str) -> int:
    values = {"I": 1, "V": 5, "X": 10, "L": 50, "C": 100, "D": 500, "M": 1000}
    total = 0
    for a, b in zip(text, text[1:] + " "):
        total += -values[a] if values.get(b, 0) > values[a] else values[a]
    return total


def _natural_key(text: str):
    """Sort key: Roman numerals by value (stage IX after VIII), then numbers inside names by value."""
    if text and _ROMAN.fullmatch(text):
        return (0, _roman_value(text), [])
    return (1, 0, [(0, int(part), "") if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", text)])


def _pairs_from_folder(path: Path, folder: Path, stage_order) -> list[dict]:
    if not folder.is_dir():
        _fail(path, f"pairs folder {str(folder)!r} does not exist")
    found: dict[tuple[str, str], dict[str, Path]] = {}
    pattern = re.compile(r"(?P<test>.+?)_(?P<stage>[^_]+)_(?P<side>[LR])$")
    for file in sorted(folder.iterdir()):
        if file.suffix.lower() not in IMAGE_SUFFIXES:
            continue
        m = pattern.match(file.stem)
        if m:
            found.setdefault((m["test"], m["stage"]), {})[m["side"]] = file
    if not found:
        _fail(path, f"no images named TEST_STAGE_L / TEST_STAGE_R in {str(folder)!r}")
    for (test, stage), sides in found.items():
        if set(sides) != {"L", "R"}:
            missing = "R" if "L" in sides else "L"
            _fail(path, f"{test}_{stage}_{missing} is missing in {str(folder)!r}")
    order = {s: i for i, s in enumerate(stage_order or [])}

    def sort_key(item):
        (test, stage), _ = item
        return (_natural_key(test), order.get(stage, len(order)), _natural_key(stage))

    return [{"test": t, "stage": s, "left": str(v["L"]), "right": str(v["R"])} for (t, s), v in sorted(found.items(), key=sort_key)]


def load_manifest(path: PathLike) -> Manifest:
    """Read and check a campaign manifest (TOML); every error names the manifest and the entry."""
    path = Path(path)
    if not path.is_file():
        raise JaxStereoError(f"manifest {str(path)!r} does not exist")
    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        _fail(path, f"not valid TOML ({err})")
    return manifest_from_dict(data, path, path.parent)


def manifest_from_dict(data: dict, path: Path, base: Path) -> Manifest:
    """Check a campaign given as the manifest's key-value pairs (`data`); `path` names it in errors,
    `base` is the folder that relative paths start from."""
    path, base = Path(path), Path(base)
    unknown = set(data) - _TOP_KEYS
    if unknown:
        _fail(path, f"unknown key(s) {', '.join(sorted(unknown))}; known: {', '.join(sorted(_TOP_KEYS))}")
    if not isinstance(data.get("rig"), str):
        _fail(path, "needs rig = \"RIG.json\" (the rig file, relative to the manifest)")
    rig = (base / data["rig"]).resolve()
    if not rig.is_file():
        _fail(path, f"rig file {str(rig)!r} does not exist")
    model = data.get("model", "exact")
    if model not in ("exact", "first-order", "none"):
        _fail(path, f"model must be exact, first-order or none, got {model!r}")
    z_range = _z_range(path, data.get("z_range"))
    spacing = _number(path, data, "spacing", "", 0.005, positive=True)
    max_gap = _number(path, data, "max_gap", "", 0.01)
    if max_gap < 0:
        _fail(path, f"max_gap must not be negative, got {max_gap}")
    default_level = _number(path, data, "water_level", "")
    damage = _damage_settings(path, data["damage"]) if "damage" in data else None
    pairs = [_pair_entry(path, base, entry, i, default_level) for i, entry in enumerate(_raw_pairs(path, base, data))]
    output = data.get("output", path.stem + "-out")
    if not isinstance(output, str):
        _fail(path, "output must be a folder name")
    return Manifest(path.resolve(), rig, model, z_range, spacing, max_gap, damage, _references_first(path, pairs),
                    (base / output).resolve())


def _z_range(path: Path, z_range) -> tuple[float, float] | None:
    """The manifest's `z_range = [ZMIN, ZMAX]` (metres) checked, or None."""
    if z_range is None:
        return None
    if (not isinstance(z_range, list) or len(z_range) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in z_range)
            or not z_range[0] < z_range[1]):
        _fail(path, f"z_range must be [ZMIN, ZMAX] in metres with ZMIN < ZMAX, got {z_range!r}")
    return float(z_range[0]), float(z_range[1])


def _damage_settings(path: Path, table) -> DamageSettings:
    """The `[damage]` table checked."""
    if not isinstance(table, dict):
        _fail(path, "[damage] must be a table")
    unknown = set(table) - _DAMAGE_KEYS
    if unknown:
        _fail(path, f"[damage] has unknown key(s) {', '.join(sorted(unknown))}")
    for key in ("dn50", "slope", "swl"):
        if key not in table:
            _fail(path, f"[damage] needs {key}")
    origin, stretch, zone = (_pair_of_numbers(path, table, key) for key in ("slope_origin", "stretch", "active_zone"))
    fit = table.get("fit_slope", False)
    if not isinstance(fit, bool):
        _fail(path, f"[damage] fit_slope must be true or false, got {fit!r}")
    from .._surface.damage import parse_slope

    try:
        parse_slope(str(table["slope"]))
    except JaxStereoError as err:
        _fail(path, f"[damage] {err}")
    if (origin is None) == (not fit):
        _fail(path, "[damage] place the design slope with exactly one of slope_origin = [X, Z] (its toe, say) "
                    "or fit_slope = true")
    return DamageSettings(
        dn50=_number(path, table, "dn50", "[damage] ", positive=True), slope=str(table["slope"]),
        swl=_number(path, table, "swl", "[damage] "), slope_origin=origin,
        profile_spacing=_number(path, table, "profile_spacing", "[damage] ", positive=True), fit_slope=fit,
        stretch=stretch, active_zone=zone)


def _raw_pairs(path: Path, base: Path, data: dict) -> list:
    """The pairs as listed: `[[pair]]` tables, or those found in the `pairs = "FOLDER"` folder."""
    if "pair" in data and "pairs" in data:
        _fail(path, "give either [[pair]] tables or pairs = \"FOLDER\", not both")
    if "pairs" in data:
        if not isinstance(data["pairs"], str):
            _fail(path, "pairs must be a folder name")
        stages = data.get("stages")
        if stages is not None and not (isinstance(stages, list) and all(isinstance(s, str) for s in stages)):
            _fail(path, "stages must be a list of stage names")
        return _pairs_from_folder(path, (base / data["pairs"]).resolve(), stages)
    raw = data.get("pair")
    if not isinstance(raw, list) or not raw:
        _fail(path, "lists no pairs: add [[pair]] tables (test, stage, left, right) or pairs = \"FOLDER\"")
    return raw


def _pair_entry(path: Path, base: Path, entry, i: int, default_level: float | None) -> PairEntry:
    """Pair `i` (0-based) checked."""
    where = f"pair {i + 1}: "
    if not isinstance(entry, dict):
        _fail(path, f"{where}must be a table")
    unknown = set(entry) - _PAIR_KEYS
    if unknown:
        _fail(path, f"{where}unknown key(s) {', '.join(sorted(unknown))}")
    test, stage = _name(path, entry, "test", where), _name(path, entry, "stage", where)
    files = []
    for side in ("left", "right"):
        if not isinstance(entry.get(side), str):
            _fail(path, f"{where}needs {side} = \"IMAGE\"")
        files.append((base / entry[side]).resolve())
    reference = entry.get("reference", False)
    if not isinstance(reference, bool):
        _fail(path, f"{where}reference must be true or false")
    level = _number(path, entry, "water_level", where)
    return PairEntry(test, stage, files[0], files[1], level if level is not None else default_level, reference, i)


def _references_first(path: Path, pairs: list[PairEntry]) -> tuple[PairEntry, ...]:
    """Each test's pairs, its reference stage first (the marked one, else its first listed); no pair twice."""
    seen = set()
    for pair in pairs:
        if (pair.test, pair.stage) in seen:
            _fail(path, f"pair {pair.index + 1}: test {pair.test} stage {pair.stage} is listed twice")
        seen.add((pair.test, pair.stage))
    ordered = []
    for test in dict.fromkeys(p.test for p in pairs):
        group = [p for p in pairs if p.test == test]
        refs = [p for p in group if p.reference]
        if len(refs) > 1:
            _fail(path, f"test {test} marks {len(refs)} stages as reference ({', '.join(p.stage for p in refs)}); "
                  "mark one")
        ref = refs[0] if refs else group[0]
        ordered.append(dataclasses.replace(ref, reference=True))
        ordered.extend(p for p in group if p is not ref)
    return tuple(ordered)
