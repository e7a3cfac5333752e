"""All the pipeline's numbers in one table: per-stage times, compile time, peak memory, batch throughput.

Run: python benchmarks/run_all.py [--size 2496x1664] [--batch-size 1728x1152] [--batch-pairs 50]
                                   [--workers 2] [--workdir DIR] [--json]

1. Renders a synthetic campaign (breakwater stages under 0.158 m of water) at `--size` and another of
   `--batch-pairs` pairs at `--batch-size` (kept in `--workdir` and reused when it is given again).
2. A fresh process times one pair at `--size` through the whole batch job (load, rectify and match,
   triangulate, write, preview, grid, damage): the first (compiling) run, then warm runs stage by stage,
   beside bare OpenCV SGBM on the same rectified pair (the baseline ratio), and its peak memory.
3. A fresh process times warm single runs at `--batch-size` (the per-pair baseline), then the whole
   campaign runs as `jaxstereo batch` in a fresh process (wall time from outside: start-up, imports and
   compilation included) and, with `--workers N`, again on N local processes. Ratios compare the batch's
   time per pair with the warm single run's.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _size(text):
    w, h = (int(v) for v in text.lower().split("x"))
    return w, h


def _peak_mb() -> float:
    """This process's peak resident memory, MB. VmHWM (Linux) starts afresh at exec, whereas ru_maxrss
    keeps the high-water mark of the process that spawned us."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _campaign(folder: Path, size, tests: int, stages: int) -> Path:
    manifest = folder / "campaign.toml"
    if manifest.is_file():
        return manifest
    from jaxstereo import write_synthetic_campaign

    print(f"rendering {min(stages, 3)} stage pairs at {size[0]}x{size[1]} into {folder}", file=sys.stderr)
    return write_synthetic_campaign(folder, size, tests=tests, stages=stages)[0]


def _child_single(manifest: str, repeat: int) -> dict:
    """In a fresh process: cold run, warm runs per stage, bare SGBM, peak memory."""
    started = time.perf_counter()
    import jax

    from jaxstereo._app.batch_job import plan_jobs, run_pair
    from jaxstereo._app.manifest import load_manifest

    imported = time.perf_counter() - started
    m = load_manifest(manifest)
    scratch = Path(tempfile.mkdtemp(prefix="jaxstereo-bench-"))
    jobs = [j for j in plan_jobs(m, scratch) if j.pair.test == m.pairs[0].test]
    start = time.perf_counter()
    first = run_pair(jobs[0])
    first_s = time.perf_counter() - start
    if first["status"] != "ok":
        raise SystemExit(f"benchmark pair failed: {first['error']}")
    warm, every_run = {}, []
    for job in jobs:
        runs = [run_pair(job) for _ in range(repeat)]
        every_run += [r["seconds"] for r in runs]
        warm[job.pair.stage] = min(runs, key=lambda r: r["seconds"])  # the stage table: fastest run
    sgbm_s = _bare_sgbm(m, repeat)
    damaged = [r for r in warm.values() if "S" in r] or list(warm.values())
    shutil.rmtree(scratch, ignore_errors=True)
    return {"import_s": imported, "first_run_s": first_s, "warm_reference_s": warm[jobs[0].pair.stage]["seconds"],
            "warm_mean_s": sum(every_run) / len(every_run),  # the batch baseline: every warm run, as a batch has
            "stages_s": damaged[0]["stage_seconds"], "warm_damaged_s": damaged[0]["seconds"],
            "points": damaged[0]["points"], "sgbm_s": sgbm_s, "peak_mb": _peak_mb(), "jax": jax.__version__}


def _bare_sgbm(m, repeat: int) -> float:
    import jax

    from jaxstereo._app.images import read_image
    from jaxstereo._calibration.rig import load_rig
    from jaxstereo._geometry.interface import Interface
    from jaxstereo._stereo.epipolar import disparity_bounds
    from jaxstereo._stereo.match_ahead import remap
    from jaxstereo._stereo.matching import MatchOptions, disparity_search_range, sgbm_disparity
    from jaxstereo._stereo.rectify import rectification_maps, rectify

    rig = load_rig(m.rig)
    pair = m.pairs[0]
    with jax.enable_x64(True):
        rect = rectify(rig.left, rig.right, Interface(pair.water_level), "air")
        maps = [rectification_maps(rect, cam, s) for s, cam in enumerate((rig.left, rig.right))]
        a, b = (remap(read_image(path, grayscale=True), side_maps)
                for path, side_maps in ((pair.left, maps[0]), (pair.right, maps[1])))
        bounds = disparity_bounds(rect, rig.left, rig.right, Interface(pair.water_level), *(m.z_range or (-0.05, 0.45)))
        lo, num = disparity_search_range(*bounds, MatchOptions().margin_px)
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        sgbm_disparity(a, b, lo, num, MatchOptions())
        times.append(time.perf_counter() - start)
    return min(times)


def _child_batch(manifest: str, output: str, workers: int) -> dict:
    from jaxstereo._app.batch import run_batch

    result = run_batch(manifest, output, workers=workers, log=lambda _: None, progress_stream=open("/dev/null", "w"))
    workers_peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    return {"pairs": len(result.rows), "failed": result.failed, "batch_s": result.seconds, "peak_mb": _peak_mb(),
            "peak_worker_mb": workers_peak}


def _run_child(*args) -> tuple[dict, float]:
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, __file__, "--child", *args], capture_output=True, text=True)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"benchmark step {args[0]} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1]), wall


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=_size, default=(2496, 1664), help="image size of the per-stage table")
    parser.add_argument("--batch-size", type=_size, default=(1728, 1152), help="image size of the batch")
    parser.add_argument("--batch-pairs", type=int, default=50)
    parser.add_argument("--workers", type=int, default=1, help="also run the batch on N local processes (N > 1)")
    parser.add_argument("--repeat", type=int, default=2, help="warm runs per stage (the fastest is kept)")
    parser.add_argument("--workdir", help="keep renders here and reuse them (default: a temporary folder)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of the table")
    parser.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        kind, *rest = args.child
        out = _child_single(rest[0], int(rest[1])) if kind == "single" else _child_batch(rest[0], rest[1], int(rest[2]))
        print(json.dumps(out))
        return

    work = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="jaxstereo-bench-"))
    w, h = args.size
    bw, bh = args.batch_size
    stage_manifest = _campaign(work / f"stages-{w}x{h}", args.size, tests=1, stages=2)
    stages_per_test = 5
    batch_manifest = _campaign(work / f"batch-{bw}x{bh}-{args.batch_pairs}", args.batch_size,
                               tests=math.ceil(args.batch_pairs / stages_per_test), stages=stages_per_test)
    if args.batch_pairs % stages_per_test:
        print(f"note: {args.batch_pairs} rounded up to whole tests of {stages_per_test} stages", file=sys.stderr)

    print("timing one pair at full size (fresh process)", file=sys.stderr)
    single, _ = _run_child("single", str(stage_manifest), str(args.repeat))
    print("timing warm single runs at the batch size (fresh process)", file=sys.stderr)
    single_b, _ = _run_child("single", str(batch_manifest), str(args.repeat))
    batches = []
    for workers in sorted({1, args.workers}):
        out = work / f"batch-out-{workers}"
        shutil.rmtree(out, ignore_errors=True)
        print(f"batch of the campaign on {workers} process(es)", file=sys.stderr)
        info, wall = _run_child("batch", str(batch_manifest), str(out), str(workers))
        batches.append({"workers": workers, "wall_s": wall, **info})
        shutil.rmtree(out, ignore_errors=True)

    result = {"size": f"{w}x{h}", "batch_size": f"{bw}x{bh}", "single": single, "single_batch_size": single_b,
              "batches": batches}
    for b in batches:
        b["per_pair_s"] = b["wall_s"] / b["pairs"]
        b["pairs_per_min"] = 60.0 / b["per_pair_s"]
        b["ratio_to_warm_single"] = b["per_pair_s"] / single_b["warm_mean_s"]
    if args.json:
        print(json.dumps(result, indent=2))
        return
    sgbm = single["sgbm_s"]
    rows = [(f"bare SGBM on the rectified pair, {w}x{h} (baseline)", f"{sgbm:.2f} s", "1.00x")]
    total = single["warm_damaged_s"]
    rows.append((f"one pair, warm, whole job ({single['points']} points)", f"{total:.2f} s", f"{total / sgbm:.2f}x"))
    for stage, seconds in single["stages_s"].items():
        rows.append((f"  {stage.replace(' (s)', '')}", f"{seconds:.2f} s", f"{seconds / sgbm:.2f}x"))
    rows += [
        ("first run (compiling) minus warm run", f"{single['first_run_s'] - single['warm_reference_s']:.1f} s", ""),
        ("import jax + jaxstereo", f"{single['import_s']:.1f} s", ""),
        (f"peak memory, one pair at {w}x{h} (process)", f"{single['peak_mb']:.0f} MB", ""),
        (f"warm single runs, mean per pair at {bw}x{bh} (baseline)", f"{single_b['warm_mean_s']:.2f} s", "1.00x"),
    ]
    for b in batches:
        rows += [
            (f"batch, {b['pairs']} pairs, {b['workers']} process(es): wall (start-up and compile included)",
             f"{b['wall_s']:.1f} s", ""),
            ("  per pair", f"{b['per_pair_s']:.2f} s", f"{b['ratio_to_warm_single']:.2f}x"),
            ("  throughput", f"{b['pairs_per_min']:.1f} pairs/min", ""),
            ("  peak memory (batch process; largest worker)",
             f"{b['peak_mb']:.0f} MB" + (f"; {b['peak_worker_mb']:.0f} MB" if b["workers"] > 1 else ""), ""),
        ]
        if b["failed"]:
            rows.append(("  FAILED pairs", str(b["failed"]), ""))
    width = max(len(r[0]) for r in rows)
    print(f"jaxstereo benchmarks (jax {single['jax']}, {_cores()} cores)")
    print(f"| {'quantity':<{width}} | value | ratio |")
    print(f"|{'-' * (width + 2)}|---:|---:|")
    for name, value, ratio in rows:
        print(f"| {name:<{width}} | {value} | {ratio} |")


def _cores() -> int:
    import os

    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()


if __name__ == "__main__":
    main()
