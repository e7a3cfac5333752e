"""`jaxstereo batch`: a rendered campaign against ground truth, failures, resume after a kill, workers, Dask."""

import csv
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from jaxstereo._app.batch import run_batch
from jaxstereo._app.cli import main
from jaxstereo._app.images import write_image
from jaxstereo._stereo.table_cache import use_table_cache
from jaxstereo._surface.damage_report import stretch_damage
from jaxstereo._surface.grid import grid_median, load_dem
from jaxstereo._synthetic.campaign import SWL, write_synthetic_campaign
from jaxstereo._synthetic.scenes import build_scene


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    root = tmp_path_factory.mktemp("campaign")
    manifest, specs = write_synthetic_campaign(root, image_size=(864, 576), tests=1, stages=3)
    return root, manifest, specs


def _rows(path):
    with open(path) as f:
        return {(r["test"], r["stage"]): r for r in csv.DictReader(f)}


def _truth_damage(specs, reference_dem):
    """Damage of each later stage against the first, from the exact heightfields on the reference stage's grid."""
    dems = []
    for spec in specs:
        hf = build_scene(spec).heightfield
        X, Y = np.meshgrid(hf.x, hf.y)
        nodes = np.stack([X.ravel(), Y.ravel(), np.asarray(hf.z).ravel()], axis=-1)
        dems.append(grid_median(nodes, 0.005, reference_dem.x, reference_dem.y))
    spec = specs[0]
    return [stretch_damage(dems[0], d, spec.dn50_m, spec.slope, SWL, (spec.toe_x_m, 0.0)) for d in dems[1:]]


def _manifest_with_broken_test(root):
    """The campaign plus test T02: a good reference, a truncated stage II, an all-black stage III."""
    pairs = root / "pairs"
    for side in "LR":
        shutil.copyfile(pairs / f"T01_I_{side}.png", pairs / f"T02_I_{side}.png")
        data = (pairs / f"T01_II_{side}.png").read_bytes()
        (pairs / f"T02_II_{side}.png").write_bytes(data[: len(data) // 3])
        write_image(pairs / f"T02_III_{side}.png", np.zeros((576, 864, 3), np.uint8))
    text = (root / "campaign.toml").read_text()
    for stage in ("I", "II", "III"):
        text += (f'\n[[pair]]\ntest = "T02"\nstage = "{stage}"\nleft = "pairs/T02_{stage}_L.png"\n'
                 f'right = "pairs/T02_{stage}_R.png"\n')
    path = root / "broken.toml"
    path.write_text(text)
    return path


def test_batch_matches_ground_truth_logs_failures_and_skips_finished_pairs(campaign, tmp_path, capsys):
    root, _, specs = campaign
    manifest = _manifest_with_broken_test(root)
    out = tmp_path / "out"
    assert main(["batch", str(manifest), "-o", str(out)]) == 1  # two pairs failed: exit status 1
    captured = capsys.readouterr()
    assert "4 done, 2 failed, 0 skipped" in captured.out
    assert "6/6 pairs" in captured.err and "left" in captured.err  # the progress bar with the time left
    rows = _rows(out / "summary.csv")
    assert [rows[("T01", s)]["status"] for s in ("I", "II", "III")] == ["ok", "ok", "ok"]
    assert rows[("T02", "I")]["status"] == "ok"
    assert rows[("T02", "II")]["status"] == "failed" and "cannot be read" in rows[("T02", "II")]["error"]
    assert rows[("T02", "III")]["status"] == "failed" and "uniform" in rows[("T02", "III")]["error"]
    log = (out / "batch.log").read_text()
    assert "FAILED T02/II" in log and "FAILED T02/III" in log
    # Damage against the exact heightfields (whole 0.9 m wide model, 864x576 px).
    truth = _truth_damage(specs, load_dem(out / "T01" / "I" / "dem.npz"))
    for stage, t in zip(("II", "III"), truth):
        row = rows[("T01", stage)]
        assert abs(float(row["S"]) - t.averaged.S) <= 0.10 * t.averaged.S, (stage, row["S"], t.averaged.S)
        # E3D (a Dn50 disc's mean depth at the deepest place) within 20 %: at 864 px a 31 px sub-pixel patch spans
        # 8 cm, 2 Dn50, and deepens the small stage-II hole's edges a little (1.45 against 1.25).
        assert abs(float(row["E3D"]) - t.volumes.E3D) <= 0.20 * t.volumes.E3D, (stage, row["E3D"], t.volumes.E3D)
        # The 95 % intervals (the figure's error bars) hold the measured value and the truth (both stages: S 0.54-0.76
        # and 1.30-1.73 for 0.63 and 1.54; E3D 1.01-1.53 and 2.05-2.85 for 1.25 and 2.43).
        for key, true in (("S", t.averaged.S), ("E2D", t.averaged.E2D), ("E3D", t.volumes.E3D)):
            low, high = float(row[f"{key}_low"]), float(row[f"{key}_high"])
            assert 0 <= low < float(row[key]) < high and low <= true <= high, (stage, key, low, high, true)
    assert float(rows[("T01", "III")]["S"]) > float(rows[("T01", "II")]["S"]) > 0
    for test in ("T01", "T02"):
        assert (out / f"damage_vs_stage_{test}.png").read_bytes()[:4] == b"\x89PNG"
    for stage in ("I", "II", "III"):
        assert (out / "T01" / stage / "survey.npz").is_file() and (out / "T01" / stage / "dem.npz").is_file()
    assert (out / "T01" / "III" / "damage" / "damage.json").is_file()
    assert not (out / "T02" / "II" / "result.json").exists()
    # A second run skips the four finished pairs (their files untouched) and retries the two failed ones.
    stamps = {p: p.stat().st_mtime_ns for p in out.glob("T01/*/*.npz")}
    result = run_batch(manifest, out, log=lambda _: None)
    assert (result.skipped, result.processed, result.failed) == (4, 2, 2)
    assert stamps == {p: p.stat().st_mtime_ns for p in out.glob("T01/*/*.npz")}
    assert "start: 2 to run, 4 already done" in (out / "batch.log").read_text()
    assert [r["status"] for r in result.rows] == ["ok", "ok", "ok", "ok", "failed", "failed"]


def test_interrupted_batch_resumes_without_redoing_finished_pairs(campaign, tmp_path):
    root, manifest, _ = campaign
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "jaxstereo", "batch", str(manifest), "-o", str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    done = out / "T01" / "I" / "result.json"
    deadline = time.time() + 240
    while not done.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)  # as a power cut would: no chance to clean up
    proc.wait()
    assert done.exists()
    finished = {p for p in out.glob("T01/*/result.json")}
    assert len(finished) < 3, "the batch finished before it could be interrupted"
    stamps = {p: p.stat().st_mtime_ns for p in finished}
    lines = []
    result = run_batch(manifest, out, log=lines.append)
    assert result.skipped == len(finished) and result.processed == 3 - len(finished) and result.failed == 0
    assert stamps == {p: p.stat().st_mtime_ns for p in finished}  # finished pairs were not redone
    assert f"{len(finished)} already done" in lines[0]
    assert not [p for p in out.rglob(".*") if p.is_file()]  # no temporary (partial) file is left
    assert [r["status"] for r in result.rows] == ["ok", "ok", "ok"]
    # Changing an input redoes that pair and the ones that depend on it (damage against stage I).
    os.utime(root / "pairs" / "T01_I_L.png")
    again = run_batch(manifest, out, log=lambda _: None)
    assert again.processed == 3 and again.skipped == 0


def _first_two_stages(root):
    """The campaign without stage III: each parallel worker gets one pair, and stage II still has damage."""
    text = (root / "campaign.toml").read_text()
    head, _, _ = text.rpartition("[[pair]]")
    path = root / "two_stages.toml"
    path.write_text(head)
    return path


def test_workers_and_dask_cluster_give_the_same_results(campaign, tmp_path, monkeypatch):
    manifest = _first_two_stages(campaign[0])
    serial = run_batch(manifest, tmp_path / "serial", log=lambda _: None)
    use_table_cache(tmp_path / "tables")  # as the command line does: the workers keep their parent's folder
    try:
        parallel = run_batch(manifest, tmp_path / "workers", workers=2, log=lambda _: None)
    finally:
        use_table_cache(None)
    assert len(list((tmp_path / "tables").glob("rectification-*.npz"))) >= 2
    distributed = pytest.importorskip("distributed")
    monkeypatch.setenv("JAXSTEREO_CACHE_DIR", str(tmp_path / "cli-caches"))  # the command's cache folder
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        assert main(["batch", str(manifest), "-o", str(tmp_path / "dask"), "--scheduler", cluster.scheduler_address]) == 0
    # The Dask worker kept the rig tables it computed in the command's folder (this process computes none)
    assert len(list((tmp_path / "cli-caches" / "tables").glob("rectification-*.npz"))) >= 2
    on_dask = _rows(tmp_path / "dask" / "summary.csv")
    for a, b in zip(serial.rows, parallel.rows):
        assert (a["test"], a["stage"], a["status"], a["points"]) == (b["test"], b["stage"], "ok", b["points"])
        if "S" in a:
            assert abs(a["S"] - b["S"]) <= 1e-9 * max(1.0, a["S"])
            assert abs(a["S"] - float(on_dask[(a["test"], a["stage"])]["S"])) <= 1e-5 * max(1.0, a["S"])
    assert all(r["status"] == "ok" for r in on_dask.values())


def test_folder_of_pairs_named_by_convention(campaign, tmp_path, capsys):
    root, _, specs = campaign
    folder = tmp_path / "pairs"
    folder.mkdir()
    for path in (root / "pairs").glob("T01_*.png"):  # stages I and III: the damage against the truth
        if "_II_" not in path.name:
            shutil.copyfile(path, folder / path.name)
    out = tmp_path / "out"
    damage = ["--dn50", "0.036", "--slope", "1:2", "--swl", str(SWL), "--slope-origin", str(specs[0].toe_x_m), "0"]
    assert main(["batch", str(folder), "--rig", str(root / "rig.json"), "--water-level", str(SWL), *damage,
                 "-o", str(out)]) == 0
    rows = _rows(out / "summary.csv")
    assert list(rows) == [("T01", "I"), ("T01", "III")]
    (truth,) = _truth_damage([specs[0], specs[2]], load_dem(out / "T01" / "I" / "dem.npz"))
    # the design slope fitted near the SWL here, not given
    assert abs(float(rows[("T01", "III")]["S"]) - truth.averaged.S) <= 0.10 * truth.averaged.S
    capsys.readouterr()
    assert main(["batch", str(folder), "-o", str(tmp_path / "o2")]) == 2
    assert "give --rig" in capsys.readouterr().err
    assert main(["batch", str(folder), "--rig", str(root / "rig.json"), "--dn50", "0.036", "-o", str(tmp_path / "o3")]) == 2
    assert "missing --slope, --swl" in capsys.readouterr().err
    assert main(["batch", str(root / "campaign.toml"), "--rig", str(root / "rig.json"), "-o", str(tmp_path / "o4")]) == 2
    assert "only for a folder of pairs" in capsys.readouterr().err
    assert not any((tmp_path / name).exists() for name in ("o2", "o3", "o4"))


def test_a_pair_whose_scene_rises_past_the_height_range_is_warned_about(campaign, tmp_path, capsys):
    root, _, _ = campaign
    text = (root / "campaign.toml").read_text().replace("z_range = [-0.05, 0.45]", "z_range = [-0.05, 0.2]")
    head, _, _ = text.partition("[damage]")  # stage I alone, no damage
    manifest = root / "low_range.toml"
    manifest.write_text(head + '[[pair]]\ntest = "T01"\nstage = "I"\nleft = "pairs/T01_I_L.png"\n'
                        'right = "pairs/T01_I_R.png"\n')
    out = tmp_path / "out"
    assert main(["batch", str(manifest), "-o", str(out)]) == 0  # the crest at 0.31 m: the survey goes on, truncated
    printed = capsys.readouterr().out
    assert "WARNING T01/I: " in printed and "above the height range's top, z = 0.200 m" in printed
    assert "WARNING T01/I: " in (out / "batch.log").read_text()
