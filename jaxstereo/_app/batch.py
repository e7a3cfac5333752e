"""`jaxstereo batch`: every pair of a campaign through reconstruct, grid and damage, unattended.

Pairs run as jobs (`run_pair`, see `_batch_job`) in this process (compiled functions reused across
pairs), in local worker processes (`workers > 1`, each traces once and shares this process's caches of
compiled functions and rig tables, if it keeps any: the command line does), or on a Dask distributed cluster
(`scheduler`; its workers share those caches too); reference stages first, then the others. Finished pairs
are skipped (resumable); a failing pair is logged (`batch.log`, `summary.csv`) and skipped. Every file is
written atomically.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import time
from collections.abc import Callable
from pathlib import Path
from typing import TextIO

from .._geometry.errors import JaxStereoError
from .._geometry.types import PathLike
from .batch_job import finished_row, plan_jobs, run_pair
from .io import write_text_atomic
from .manifest import Manifest, load_manifest
from .progress import Progress, format_seconds

CSV_COLUMNS = ("test", "stage", "reference", "status", "seconds", "points", "submerged_fraction", "water_level_m",
               "A_e_m2", "L_e_m", "d_e_m", "S", "S_sigma", "S_low", "S_high", "S_max", "E2D", "E2D_low", "E2D_high",
               "E3D", "E3D_low", "E3D_high", "eroded_volume_m3", "accreted_volume_m3", "damage_level", "stretch_y_m",
               "active_zone_z_m", "error", "survey", "dem")


@dataclasses.dataclass(frozen=True)
class BatchResult:
    """What a batch did: one row per pair (manifest order), counts, the output folder and files written."""

    rows: list[dict]
    processed: int
    skipped: int
    failed: int
    seconds: float
    output: Path
    summary_csv: Path
    figures: list[Path]


def _result_or_failure(future, job) -> dict:
    """A job's row; a worker that died (killed, out of memory) becomes a failed row, not a crash."""
    try:
        return future.result()
    except Exception as err:
        return {"status": "failed", "error": f"the worker running it died ({err.__class__.__name__}: {err})",
                "test": job.pair.test, "stage": job.pair.stage, "reference": job.pair.reference, "seconds": 0.0}


class _Inline:
    """Jobs one after another in this process."""

    def run(self, jobs):
        for job in jobs:
            yield job, run_pair(job)

    def close(self):
        pass


class _Processes:
    """Jobs on `workers` local processes (spawned: JAX is not fork-safe), which keep their compiled functions
    and rig tables where this process does (`_CACHE_SETTINGS`; nowhere if it keeps none)."""

    def __init__(self, workers: int):
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        self.pool = ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                                        initializer=_use_caches, initargs=_cache_settings())

    def run(self, jobs):
        from concurrent.futures import as_completed

        futures = {self.pool.submit(run_pair, job): job for job in jobs}
        for future in as_completed(futures):
            yield futures[future], _result_or_failure(future, futures[future])

    def close(self):
        self.pool.shutdown(cancel_futures=True)


_CACHE_SETTINGS = ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs",
                   "jax_persistent_cache_min_entry_size_bytes")


def _cache_settings() -> tuple[dict, Path | None]:
    """This process's JAX persistent-cache settings (`_CACHE_SETTINGS`) and rig tables' folder, for its workers."""
    import jax

    from .._stereo.table_cache import table_cache_folder

    return {name: getattr(jax.config, name) for name in _CACHE_SETTINGS}, table_cache_folder()


def _use_caches(jax_settings: dict, table_folder) -> None:
    """A worker process's start: JAX's persistent-cache settings and the rig tables' folder of its parent."""
    import jax

    from .._stereo.table_cache import use_table_cache

    if jax_settings.get("jax_compilation_cache_dir"):
        for name, value in jax_settings.items():
            jax.config.update(name, value)
    use_table_cache(table_folder)


class _Dask:
    """Jobs on a Dask distributed cluster (the optional `dask` extra); workers must see the files. Each worker
    keeps its compiled functions and rig tables where this process does (`dask_caches.CachesOnWorkers`)."""

    def __init__(self, address: str):
        try:
            from distributed import Client
        except ImportError:
            raise JaxStereoError("--scheduler needs the optional Dask extra: pip install 'jaxstereo[dask]'") from None
        try:
            self.client = Client(address, timeout="20s")
        except (OSError, TimeoutError, ValueError) as err:
            raise JaxStereoError(f"cannot reach the Dask scheduler at {address!r}: {err}") from None
        from .dask_caches import CachesOnWorkers

        self.client.register_plugin(CachesOnWorkers(*_cache_settings()))

    def run(self, jobs):
        from distributed import as_completed

        futures = {}
        for job in jobs:
            futures[self.client.submit(run_pair, job, pure=False, key=f"jaxstereo-{job.pair.key}-{job.fingerprint}")] = job
        for future in as_completed(list(futures)):
            yield futures[future], _result_or_failure(future, futures[future])

    def close(self):
        self.client.close()


def _check_inputs_exist(manifest: Manifest):
    missing = [str(p) for pair in manifest.pairs for p in (pair.left, pair.right) if not p.is_file()]
    if missing:
        more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
        raise JaxStereoError(f"manifest {str(manifest.path)!r} points to {len(missing)} missing image file(s): "
                             f"{', '.join(missing[:3])}{more}")


def _check_water_levels(manifest: Manifest, rig) -> None:
    """Every pair's water level below both cameras (else a manifest error, before any output)."""
    from .._geometry.interface import Interface, check_camera_above

    for pair in manifest.pairs:
        if pair.water_level is None:
            interface = rig.interface
        else:
            base = rig.interface
            interface = Interface(pair.water_level) if base is None else Interface(
                pair.water_level, base.normal, float(base.n_air), float(base.n_water))
        if interface is None:
            continue
        try:
            for name, cam in (("left", rig.left), ("right", rig.right)):
                check_camera_above(cam.center, interface, f"{name} camera")
        except JaxStereoError as err:
            raise JaxStereoError(f"manifest {str(manifest.path)!r}, pair {pair.key}: {err}") from None


def run_batch(manifest_path: PathLike | Manifest, output: PathLike | None = None, workers: int = 1, scheduler: str | None = None,
              log: Callable[[str], object] | None = print, progress_stream: TextIO | None = None) -> BatchResult:
    """Run a campaign manifest (a TOML path, see `load_manifest`, or a `Manifest`); returns a `BatchResult`.

    Checks the manifest, the rig and that every image exists before writing anything; then runs the
    pairs not yet finished, logs each to `OUTPUT/batch.log`, and writes `OUTPUT/summary.csv` and one
    `OUTPUT/damage_vs_stage_TEST.png` per test (tests with damage settings).
    """
    from .._calibration.rig import load_rig

    manifest = manifest_path if isinstance(manifest_path, Manifest) else load_manifest(manifest_path)
    rig = load_rig(manifest.rig)  # a broken rig is the manifest's error, before any output
    _check_inputs_exist(manifest)
    _check_water_levels(manifest, rig)
    if not isinstance(workers, int) or workers < 1:
        raise JaxStereoError(f"--workers must be a positive integer, got {workers!r}")
    out = Path(output).resolve() if output is not None else manifest.output
    jobs = plan_jobs(manifest, out)
    out.mkdir(parents=True, exist_ok=True)
    log_path = out / "batch.log"
    started = time.perf_counter()

    def record(message):
        stamp = time.strftime("%Y-%m-%d %H:%M:%S")
        with open(log_path, "a") as f:
            f.write(f"{stamp} {message}\n")

    rows: dict[str, dict] = {}
    todo = []
    for job in jobs:
        row = finished_row(job)
        if row is None:
            todo.append(job)
        else:
            rows[job.pair.key] = {**row, "status": row.get("status", "ok")}
    skipped = len(jobs) - len(todo)
    where = f"{workers} local processes" if workers > 1 and not scheduler else (
        f"Dask scheduler {scheduler}" if scheduler else "this process")
    log(f"batch: {len(jobs)} pairs in {len(manifest.tests())} test(s); {skipped} already done, {len(todo)} to run "
        f"on {where}; output {out}")
    record(f"start: {len(todo)} to run, {skipped} already done ({where})")
    failed = _run_jobs(todo, rows, workers, scheduler, record, Progress(len(todo), "pairs", progress_stream))
    ordered = [rows[j.pair.key] for j in jobs if j.pair.key in rows]
    summary_csv = out / "summary.csv"
    write_text_atomic(summary_csv, _rows_to_csv(ordered))
    figures = _plot_tests(ordered, manifest, out) if manifest.damage is not None else []
    seconds = time.perf_counter() - started
    record(f"end: {len(todo) - failed} done, {failed} failed, {skipped} skipped, {seconds:.1f} s")
    if todo:
        log(f"batch: {len(todo) - failed} done, {failed} failed, {skipped} skipped in {format_seconds(seconds)} "
            f"({60 * len(todo) / seconds:.1f} pairs/min)")
    else:
        log(f"batch: nothing to do, all {skipped} pairs already done")
    for row in ordered:
        if row["status"] == "failed":
            log(f"  FAILED {row['test']}/{row['stage']}: {row['error']}")
        for warning in row.get("warnings", []):
            log(f"  WARNING {row['test']}/{row['stage']}: {warning}")
    log(f"summary: {summary_csv}" + "".join(f"\nfigure: {f}" for f in figures) + f"\nlog: {log_path}")
    return BatchResult(ordered, len(todo), skipped, failed, seconds, out, summary_csv, figures)


def _run_jobs(todo: list, rows: dict, workers: int, scheduler: str | None, record, progress: Progress) -> int:
    """Run the jobs (every test's reference stage first), storing each row in `rows` by pair key, logging
    each with `record` and advancing `progress`; returns how many failed."""
    if not todo:
        return 0
    failed = 0
    runner = _Dask(scheduler) if scheduler else (_Processes(workers) if workers > 1 else _Inline())
    try:
        phases = [[j for j in todo if j.pair.reference], [j for j in todo if not j.pair.reference]]
        for phase in phases:
            for job, row in runner.run(phase):
                rows[job.pair.key] = row
                if row["status"] == "failed":
                    failed += 1
                    record(f"FAILED {job.pair.key} ({row['seconds']:.1f} s): {row['error']}")
                else:
                    record(f"ok {job.pair.key}: {row['points']} points, {row['seconds']:.1f} s"
                           + (f", S {row['S']:.2f}" if "S" in row else ""))
                    for warning in row.get("warnings", []):
                        record(f"WARNING {job.pair.key}: {warning}")
                progress.advance(f"{job.pair.key} {row['status']}")
    finally:
        runner.close()
    return failed


def _rows_to_csv(rows: list[dict]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=CSV_COLUMNS, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    return buffer.getvalue()


def _plot_tests(rows: list[dict], manifest: Manifest, out: Path) -> list[Path]:
    """One figure per test: S, E2D and E3D versus stage (the reference stage at zero)."""
    from .plots import plot_damage_versus_stage
    paths = []
    for test in manifest.tests():
        stages = [r for r in rows if r["test"] == test]
        if not any(r["status"] == "ok" for r in stages):
            continue
        names = [r["stage"] for r in stages]
        figures = {}
        for key, label in (("S", "S (averaged profile)"), ("E2D", "E2D"), ("E3D", "E3D")):
            values = [0.0 if r["reference"] else r.get(key) for r in stages]
            intervals = [None if r["reference"] else (r.get(f"{key}_low"), r.get(f"{key}_high")) for r in stages]
            figures[label] = (values, intervals)
        failed = [r["stage"] for r in stages if r["status"] == "failed"]
        title = f"Test {test}: damage versus stage" + (f" (failed: {', '.join(failed)})" if failed else "")
        path = out / f"damage_vs_stage_{test}.png"
        plot_damage_versus_stage(path, names, figures, title)
        paths.append(path)
    return paths
