import subprocess
import sys

import numpy as np
import pytest

import jaxstereo as js
from jaxstereo._calibration.rig import Rig, load_rig, save_rig
from jaxstereo._stereo import table_cache
from jaxstereo._stereo.rectify import rectify
from jaxstereo._stereo.table_cache import cached_tables, table_key, use_table_cache
from jaxstereo._synthetic.flume_rig import RigSpec, flume_rig


@pytest.fixture
def folder(tmp_path):
    use_table_cache(tmp_path)
    yield tmp_path
    use_table_cache(None)


def _counting(value):
    calls = []

    def compute():
        calls.append(1)
        return {"a": np.asarray(value, np.float64), "b": np.arange(3)}

    return compute, calls


def test_a_table_is_computed_once_and_read_back_equal(folder):
    compute, calls = _counting([1.0, 2.0])
    first = cached_tables("t", (np.ones(2), 0.5, "water", None), compute)
    again = cached_tables("t", (np.ones(2), 0.5, "water", None), compute)
    assert len(calls) == 1 and np.array_equal(again["a"], first["a"]) and np.array_equal(again["b"], np.arange(3))
    # Any difference in the inputs' values (past the last few bits: `_quantised`), dtypes or structure is another
    # table.
    for inputs in ((np.ones(2) + 1e-8, 0.5, "water", None), (np.ones(2, np.float32), 0.5, "water", None),
                   (np.ones(2), 0.5, "air", None), (np.ones(2), 0.5, "water", 0.0), (np.ones(2), 0.5)):
        cached_tables("t", inputs, compute)
    assert len(calls) == 6 and len(list(folder.glob("*.npz"))) == 6


def test_an_unreadable_file_is_computed_again_and_no_folder_means_no_file(folder):
    compute, calls = _counting([3.0])
    cached_tables("t", (1,), compute)
    (path,) = folder.glob("*.npz")
    path.write_bytes(b"PK\x03\x04 half a zip")
    assert cached_tables("t", (1,), compute)["a"][0] == 3.0 and len(calls) == 2
    assert cached_tables("t", (1,), compute)["a"][0] == 3.0 and len(calls) == 2  # rewritten whole
    use_table_cache(None)
    cached_tables("t", (1,), compute)
    assert len(calls) == 3


def test_the_least_recently_used_files_go_first_when_the_folder_is_full(folder, monkeypatch):
    monkeypatch.setattr(table_cache, "MAX_FOLDER_BYTES", 3000)
    for k in range(6):  # about 700 bytes each
        cached_tables("t", (k,), _counting(np.zeros(40))[0])
        path = max(folder.glob("*.npz"), key=lambda p: p.stat().st_mtime_ns)
        path.touch()
    cached_tables("t", (0,), _counting(np.zeros(40))[0])  # computed again: it was the oldest
    names = list(folder.glob("*.npz"))
    assert 0 < sum(p.stat().st_size for p in names) <= 3000 and len(names) < 6


def test_the_key_of_a_rectification_is_the_same_in_another_process(tmp_path, x64):
    spec = RigSpec(image_size=(432, 288), dist=(-0.12, 0.09, 0.0, 0.0, 0.0),
                   misalignment_deg=((0.3, -0.5, 0.2), (-0.4, 0.6, -0.3)))
    save_rig(Rig(*flume_rig(spec)), tmp_path / "rig.json")
    rig = load_rig(tmp_path / "rig.json")
    rect = rectify(rig.left, rig.right, js.Interface(0.18), "water")
    here = table_key("k", (rect, rig.left, 0.16))
    code = ("import jax; jax.config.update('jax_enable_x64', True)\n"
            "import jaxstereo as js\n"
            "from jaxstereo._calibration.rig import load_rig\n"
            "from jaxstereo._stereo.rectify import rectify\n"
            "from jaxstereo._stereo.table_cache import table_key\n"
            f"rig = load_rig({str(tmp_path / 'rig.json')!r})\n"
            "rect = rectify(rig.left, rig.right, js.Interface(0.18), 'water')\n"
            "print(table_key('k', (rect, rig.left, 0.16)))")
    there = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert there == here
    assert table_key("k", (rect, rig.right, 0.16)) != here
    assert table_key("k", (rectify(rig.left, rig.right, js.Interface(0.18 + 1e-9), "water"), rig.left, 0.16)) != here


def test_the_key_ignores_last_bit_differences_and_keeps_real_ones(x64):
    """On an H100 under load (the suite on 12 workers) a rectification of the same rig got another key in another
    process (run alone, three processes agreed to the last bit; XLA picks its GPU kernels per process by timing
    them): its key (and so the command line's match plan) must not change with its last bits, and must with a real
    change."""
    import jax

    spec = RigSpec(image_size=(432, 288), dist=(-0.12, 0.09, 0.0, 0.0, 0.0),
                   misalignment_deg=((0.3, -0.5, 0.2), (-0.4, 0.6, -0.3)))
    rig = Rig(*flume_rig(spec))
    rect = rectify(rig.left, rig.right, js.Interface(0.18), "water")
    here = table_key("k", (rect, rig.left))
    rng = np.random.default_rng(3)

    def moved(leaf, ulps):  # every entry moved by up to `ulps` units in its last place (about 1e-16 relative)
        value = np.asarray(leaf)
        if not np.issubdtype(value.dtype, np.floating):
            return leaf
        return value + ulps * np.spacing(value) * rng.integers(-1, 2, value.shape)

    for _ in range(20):
        assert table_key("k", (jax.tree_util.tree_map(lambda x: moved(x, 4), rect), rig.left)) == here
    leaves, structure = jax.tree_util.tree_flatten(rect)
    for index, leaf in enumerate(leaves):  # a change of 1e-8 of an array's largest value is a different table
        value = np.asarray(leaf)
        if np.issubdtype(value.dtype, np.floating) and value.size:
            changed = value.copy()
            changed.flat[0] += 1e-8 * np.max(np.abs(value))
            altered = jax.tree_util.tree_unflatten(structure, leaves[:index] + [changed] + leaves[index + 1:])
            assert table_key("k", (altered, rig.left)) != here, index
    nan = np.array([1.0, np.nan, 2.0])
    assert len({table_key("k", (a,)) for a in (nan, np.array([1.0, 0.0, 2.0]), np.array([1.0, np.inf, 2.0]))}) == 3
