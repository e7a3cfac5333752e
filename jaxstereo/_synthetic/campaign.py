"""A synthetic test campaign on disk (rendered breakwater stages, the rig, a manifest) for batch runs.

Used by the batch tests and benchmarks: the stage images are rendered once and copied to every test,
so a campaign of many pairs costs three renders.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

from .._app.images import write_image
from .._app.io import write_text_atomic
from .._calibration.rig import Rig, save_rig
from .._geometry.interface import Interface
from .._geometry.precision import float64
from .._geometry.types import PathLike
from .flume_rig import RigSpec, flume_rig
from .render import render_view
from .scenes import Breakwater, Damage, build_scene

SWL = 0.158
DAMAGES = (None, Damage(half_length_dn50=2.0, half_width_dn50=3.0, swl_m=SWL),
           Damage(half_length_dn50=3.0, half_width_dn50=3.5, deep_fraction=0.6, swl_m=SWL))
ROMAN = ("I", "II", "III", "IV", "V", "VI", "VII", "VIII", "IX", "X")


@float64
def write_synthetic_campaign(folder: PathLike, image_size: tuple[int, int] = (864, 576), tests: int = 1, stages: int = 3,
                             log: Callable[[str], object] | None = None) -> tuple[Path, list]:
    """Write `tests` tests of `stages` stages each into `folder`: images under `pairs/`, `rig.json`
    and `campaign.toml`. Stage k shows damage state k mod 3 (none, moderate, heavy) of one breakwater.

    **Returns:** `(manifest_path, specs)`, `specs[k]` the `Breakwater` spec of damage state k.
    """
    folder = Path(folder)
    left, right = flume_rig(RigSpec(image_size=image_size, water_level_m=SWL))
    save_rig(Rig(left, right), folder / "rig.json")
    water = Interface(SWL)
    specs, rendered = [], []
    for k, damage in enumerate(DAMAGES[: min(stages, 3)]):
        if log:
            log(f"rendering damage state {k} at {image_size[0]}x{image_size[1]}")
        spec = Breakwater(seed=7, damage=damage)
        scene = build_scene(spec)
        files = []
        for side, cam in (("L", left), ("R", right)):
            path = folder / "renders" / f"state{k}_{side}.png"
            write_image(path, render_view(cam, scene.heightfield, water).image)
            files.append(path)
        specs.append(spec)
        rendered.append(files)
    pairs = []
    for t in range(tests):
        for s in range(stages):
            names = []
            for side, source in zip("LR", rendered[s % len(rendered)]):
                name = f"pairs/T{t + 1:02d}_{ROMAN[s] if s < len(ROMAN) else s + 1}_{side}.png"
                (folder / name).parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(source, folder / name)
                names.append(name)
            pairs.append((f"T{t + 1:02d}", ROMAN[s] if s < len(ROMAN) else str(s + 1), *names))
    spec = specs[0]
    lines = ['rig = "rig.json"', f"water_level = {SWL}", "z_range = [-0.05, 0.45]", "spacing = 0.005",
             "max_gap = 0.01", "", "[damage]", f"dn50 = {spec.dn50_m}", f'slope = "1:{spec.slope:g}"',
             f"swl = {SWL}", f"slope_origin = [{spec.toe_x_m}, 0.0]", ""]
    for test, stage, left_name, right_name in pairs:
        lines += ["[[pair]]", f'test = "{test}"', f'stage = "{stage}"', f'left = "{left_name}"',
                  f'right = "{right_name}"', ""]
    manifest = folder / "campaign.toml"
    write_text_atomic(manifest, "\n".join(lines))
    return manifest, specs
