"""cjax.sweep: chunked jit(vmap(fn)) sharded over devices, progress bar, resumable
checkpoints (killed and resumed in a real process), refusal of foreign checkpoints,
recomputation of corrupted chunks, bounded device memory, input errors."""

import json
import os
import pathlib
import signal
import subprocess
import sys
import textwrap
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax

from .helpers import run_python


ROOT = pathlib.Path(__file__).parents[1]
# One CPU device, named explicitly: the same device in this process and in the
# subprocesses below, whatever accelerator the test machine has.
CPU = jax.devices("cpu")[:1]


def _fn(p):
    """A pytree in, a pytree out."""
    x, y = p["x"], p["y"]
    return {
        "s": jnp.sin(x) * y[0] + jnp.exp(-y[1]),
        "t": (jnp.outer(y, y), jnp.sum(y * x)),
    }


def _numpy_fn(p):
    """`_fn` on all rows at once, written independently with numpy."""
    x, y = p["x"], p["y"]
    return {
        "s": np.sin(x) * y[:, 0] + np.exp(-y[:, 1]),
        "t": (y[:, :, None] * y[:, None, :], np.sum(y * x[:, None], axis=1)),
    }


def _inputs(n, seed=0):
    rng = np.random.default_rng(seed)
    return {"x": rng.normal(size=n), "y": rng.normal(size=(n, 3))}


def _assert_tree_equal(a, b):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for u, v in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        assert isinstance(u, np.ndarray) and isinstance(v, np.ndarray)
        assert u.dtype == v.dtype and u.shape == v.shape
        np.testing.assert_array_equal(u, v)


@pytest.mark.parametrize("n, batch_size", [(23, 5), (7, 100), (8, 8)])
def test_matches_vmap_with_one_compilation(n, batch_size):
    """N not a multiple of the batch size, batch size > N, and exactly one chunk:
    the same as vmap over everything (and as numpy), host numpy arrays back, and fn
    traced once for all chunks."""
    traces = []

    def fn(p):
        traces.append(None)
        return _fn(p)

    inputs = _inputs(n)
    out = cjax.sweep(fn, inputs, batch_size=batch_size, devices=CPU, progress=False)
    assert len(traces) == 1
    assert jax.tree.structure(out) == jax.tree.structure(_numpy_fn(inputs))
    assert all(isinstance(leaf, np.ndarray) for leaf in jax.tree.leaves(out))
    for got, vmapped, reference in zip(
        jax.tree.leaves(out),
        jax.tree.leaves(jax.vmap(_fn)(inputs)),
        jax.tree.leaves(_numpy_fn(inputs)),
        strict=True,
    ):
        assert got.shape == vmapped.shape and got.shape[0] == n
        np.testing.assert_allclose(got, vmapped, rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(got, reference, rtol=1e-13, atol=1e-14)


def test_only_chunks_reach_the_device():
    """Every evaluation sees a `(chunk, ...)` batch, one per chunk, and while the
    program runs every array the sweep has put on a device is chunk-sized (the
    inputs stay in host memory and only the current chunk is sent)."""
    n, batch_size = 1009, 64  # 16 chunks, the last one padded
    seen = []
    before = jax.live_arrays("cpu")  # held, so that their ids stay theirs
    old = {id(a) for a in before}

    def record(x):
        live = [a.shape for a in jax.live_arrays("cpu") if id(a) not in old]
        seen.append((x.shape, live))
        return x

    def fn(p):
        x = jax.pure_callback(
            record,
            jax.ShapeDtypeStruct(p["y"].shape, p["y"].dtype),
            p["y"],
            vmap_method="broadcast_all",
        )
        return {"s": jnp.sum(x), "big": jnp.tile(x, 4)}

    inputs = _inputs(n)
    out = cjax.sweep(fn, inputs, batch_size=batch_size, devices=CPU, progress=False)
    assert len(seen) == 16
    for shape, live in seen:
        assert shape == (batch_size, 3)
        assert live and all(s and s[0] <= batch_size for s in live), live
    np.testing.assert_allclose(out["s"], inputs["y"].sum(axis=1), rtol=1e-14)
    np.testing.assert_array_equal(out["big"], np.tile(inputs["y"], 4))


def test_progress_bar(capsys, monkeypatch):
    inputs = _inputs(10)
    cjax.sweep(_fn, inputs, batch_size=3, devices=CPU)
    err = capsys.readouterr().err
    assert "cjax.sweep" in err and "4/4" in err and "chunk/s" in err
    cjax.sweep(_fn, inputs, batch_size=3, devices=CPU, progress=False)
    assert capsys.readouterr().err == ""
    monkeypatch.setenv("TQDM_DISABLE", "1")
    cjax.sweep(_fn, inputs, batch_size=3, devices=CPU)
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize(
    "inputs, kwargs, match",
    [
        ({"x": np.zeros(3), "y": np.zeros((4, 2))}, {}, "share their leading axis"),
        ({"x": np.zeros(0)}, {}, "length 0"),
        ({"x": np.zeros(3)}, {"batch_size": 0}, "batch_size"),
        ({"x": np.zeros(3)}, {"batch_size": 2.5}, "batch_size"),
        ({"x": np.zeros(3)}, {"batch_size": True}, "batch_size"),
        ({"x": np.zeros(3), "c": 2.0}, {}, r"inputs\['c'\] is a float"),
        ([1.0, 2.0], {}, "not an array"),
        ({"x": np.float64(1.0)}, {}, "not an array"),
        ({"x": jnp.asarray(1.0)}, {}, "scalar"),
        ({}, {}, "without any array leaf"),
        ({"x": np.zeros(3)}, {"devices": []}, "devices"),
    ],
)
def test_bad_inputs(inputs, kwargs, match):
    with pytest.raises(ValueError, match=match):
        cjax.sweep(lambda p: p, inputs, **kwargs)


def test_typed_key_outputs_are_refused():
    with pytest.raises(ValueError, match="key_data"):
        cjax.sweep(jax.random.key, np.arange(3), progress=False)


def _run(script: str, *, env_extra=None, timeout=240) -> subprocess.CompletedProcess:
    environ = dict(JAX_PLATFORMS="cpu", TQDM_DISABLE="1", **(env_extra or {}))
    return run_python(script, timeout=timeout, **environ)


_PRELUDE = """
import json, os, sys, time
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
import constrained_jax as cjax
"""


def test_sharded_over_four_devices():
    """With 4 (forced) CPU devices: the batch axis of every chunk is split into 4
    shards, the batch size is rounded up to a multiple of 4, and the results are
    those of a single-device sweep and of numpy."""
    script = _PRELUDE + textwrap.dedent(
        """
        from jax.sharding import PartitionSpec
        assert len(jax.devices()) == 4, jax.devices()
        seen = []

        def fn(p):
            jax.debug.inspect_array_sharding(p["x"], callback=seen.append)
            x, y = p["x"], p["y"]
            return {"s": jnp.sin(x) * y[0] + jnp.exp(-y[1]),
                    "t": (jnp.outer(y, y), jnp.sum(y * x))}

        rng = np.random.default_rng(0)
        inputs = {"x": rng.normal(size=21), "y": rng.normal(size=(21, 3))}
        out = cjax.sweep(fn, inputs, batch_size=6)  # rounded up to 8: 3 chunks
        (sharding,) = seen  # one compilation
        one = cjax.sweep(fn, inputs, batch_size=6, devices=jax.devices()[:1])
        report = {
            "devices": len(jax.devices()),
            "mesh_devices": len(sharding.device_set),
            "spec_is_batch": sharding.spec == PartitionSpec("batch"),
            "shard_shape": list(sharding.shard_shape((8,))),
            "max_diff": max(float(np.max(np.abs(a - b))) for a, b in
                            zip(jax.tree.leaves(out), jax.tree.leaves(one))),
        }
        print("REPORT" + json.dumps(report))
        print("RESULT" + json.dumps(jax.tree.map(lambda a: a.tolist(), out)))
        """
    )
    proc = _run(
        script, env_extra={"XLA_FLAGS": "--xla_force_host_platform_device_count=4"}
    )
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    report = json.loads(next(x for x in lines if x.startswith("REPORT"))[6:])
    result = json.loads(next(x for x in lines if x.startswith("RESULT"))[6:])
    assert report["devices"] == 4
    assert report["mesh_devices"] == 4 and report["spec_is_batch"]
    assert report["shard_shape"] == [2]  # 8 rows of a chunk over 4 devices
    assert report["max_diff"] <= 1e-14
    reference = _numpy_fn(_inputs(21))
    np.testing.assert_allclose(result["s"], reference["s"], rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(
        result["t"][0], reference["t"][0], rtol=1e-13, atol=1e-14
    )
    np.testing.assert_allclose(
        result["t"][1], reference["t"][1], rtol=1e-13, atol=1e-14
    )


# The same source is run in a subprocess (slowly) and here (fast): each chunk goes
# through a Python callback that sleeps PAUSE seconds and counts the chunk. The
# jaxpr, hence the checkpoint's fingerprint of fn, does not depend on PAUSE.
_SLOW_FN = """
import time
import jax, jax.numpy as jnp

def _pause(x):
    time.sleep(PAUSE)
    CALLS.append(x.shape)
    return x

def slow_fn(p):
    x = jax.pure_callback(
        _pause,
        jax.ShapeDtypeStruct(p["x"].shape, p["x"].dtype),
        p["x"],
        vmap_method="broadcast_all",
    )
    y = p["y"]
    return {"s": jnp.sin(x) * y[0] + jnp.exp(-y[1]), "t": jnp.cumsum(y) * jnp.cos(x)}
"""
N_SLOW, BATCH_SLOW = 40, 4  # 10 chunks


def _slow_namespace():
    namespace = {"PAUSE": 0.0, "CALLS": []}
    exec(_SLOW_FN, namespace)
    return namespace


@pytest.fixture(scope="module")
def uninterrupted():
    """The reference: the whole sweep in one go, without a checkpoint."""
    ns = _slow_namespace()
    out = cjax.sweep(
        ns["slow_fn"],
        _inputs(N_SLOW),
        batch_size=BATCH_SLOW,
        devices=CPU,
        progress=False,
    )
    assert len(ns["CALLS"]) == 10
    return out


def _chunk_files(folder):
    return {
        p.name: (p.stat().st_ino, p.stat().st_mtime_ns)
        for p in sorted(folder.glob("chunk_*.npz"))
    }


def test_killed_sweep_resumes(tmp_path, uninterrupted):
    """A sweep in another process is killed (SIGKILL) part-way; resumed here, it
    computes only the missing chunks, leaves the finished chunk files untouched, and
    returns exactly the uninterrupted result."""
    folder = tmp_path / "ckpt"
    script = (
        _PRELUDE
        + "PAUSE, CALLS = 0.4, []\n"
        + _SLOW_FN
        + textwrap.dedent(
            f"""
            rng = np.random.default_rng(0)
            n = {N_SLOW}
            inputs = {{"x": rng.normal(size=n), "y": rng.normal(size=(n, 3))}}
            cjax.sweep(slow_fn, inputs, batch_size={BATCH_SLOW},
                       devices=jax.devices("cpu")[:1], checkpoint={str(folder)!r})
            """
        )
    )
    env = dict(os.environ, JAX_PLATFORMS="cpu", TQDM_DISABLE="1")
    proc = subprocess.Popen(
        [sys.executable, "-c", script],
        cwd=ROOT,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 180
        while len(_chunk_files(folder)) < 3:
            assert proc.poll() is None, proc.stderr.read().decode()
            assert time.monotonic() < deadline, "the subprocess never wrote 3 chunks"
            time.sleep(0.02)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    before = _chunk_files(folder)
    assert 3 <= len(before) < 10, before  # killed part-way

    ns = _slow_namespace()
    out = cjax.sweep(
        ns["slow_fn"],
        _inputs(N_SLOW),
        batch_size=BATCH_SLOW,
        devices=CPU,
        checkpoint=folder,
        progress=False,
    )
    assert len(ns["CALLS"]) == 10 - len(before)  # nothing recomputed
    after = _chunk_files(folder)
    assert len(after) == 10
    assert {k: after[k] for k in before} == before  # finished files not rewritten
    assert not list(folder.glob(".*.tmp"))
    _assert_tree_equal(out, uninterrupted)

    # Complete now: a third call reads everything back and computes nothing.
    ns = _slow_namespace()
    again = cjax.sweep(
        ns["slow_fn"],
        _inputs(N_SLOW),
        batch_size=BATCH_SLOW,
        devices=CPU,
        checkpoint=folder,
        progress=False,
    )
    assert ns["CALLS"] == []
    _assert_tree_equal(again, uninterrupted)


@pytest.fixture
def full_checkpoint(tmp_path):
    folder = tmp_path / "full"
    ns = _slow_namespace()
    cjax.sweep(
        ns["slow_fn"],
        _inputs(N_SLOW),
        batch_size=BATCH_SLOW,
        devices=CPU,
        checkpoint=folder,
        progress=False,
    )
    return folder


def test_corrupted_chunks_are_recomputed(full_checkpoint, uninterrupted):
    """A truncated file, a flipped byte, and a well-formed file whose numbers were
    changed: each is detected, reported, recomputed and rewritten."""
    folder = full_checkpoint
    truncated = folder / "chunk_000002.npz"
    truncated.write_bytes(truncated.read_bytes()[: truncated.stat().st_size // 2])
    flipped = folder / "chunk_000005.npz"
    data = bytearray(flipped.read_bytes())
    data[len(data) // 2] ^= 0xFF
    flipped.write_bytes(bytes(data))
    edited = folder / "chunk_000007.npz"
    with np.load(edited) as f:
        arrays = {k: f[k] for k in f.files}
    arrays["leaf_0"] = arrays["leaf_0"] + 1e-12  # still a valid .npz
    np.savez(edited, **arrays)

    ns = _slow_namespace()
    with pytest.warns(UserWarning, match="recomputed") as record:
        out = cjax.sweep(
            ns["slow_fn"],
            _inputs(N_SLOW),
            batch_size=BATCH_SLOW,
            devices=CPU,
            checkpoint=folder,
            progress=False,
        )
    messages = " ".join(str(w.message) for w in record)
    for path in (truncated, flipped, edited):
        assert path.name in messages
    assert "checksum" in messages
    assert len(ns["CALLS"]) == 3
    _assert_tree_equal(out, uninterrupted)

    ns = _slow_namespace()
    again = cjax.sweep(
        ns["slow_fn"],
        _inputs(N_SLOW),
        batch_size=BATCH_SLOW,
        devices=CPU,
        checkpoint=folder,
        progress=False,
    )
    assert ns["CALLS"] == []
    _assert_tree_equal(again, uninterrupted)


def test_foreign_checkpoint_is_refused(full_checkpoint, tmp_path):
    """Other input values, another batch size, another fn, another input dtype: each
    refused with a message naming the difference; the folder is left as it was."""
    folder = full_checkpoint
    before = _chunk_files(folder)
    ns = _slow_namespace()
    fn = ns["slow_fn"]
    inputs = _inputs(N_SLOW)

    def sweep(fn, inputs, batch_size=BATCH_SLOW, checkpoint=folder):
        return cjax.sweep(
            fn,
            inputs,
            batch_size=batch_size,
            devices=CPU,
            checkpoint=checkpoint,
            progress=False,
        )

    other = {"x": inputs["x"].copy(), "y": inputs["y"]}
    other["x"][17] += 1e-9
    with pytest.raises(ValueError, match=r"values of inputs\['x'\] differ.*new folder"):
        sweep(fn, other)
    with pytest.raises(ValueError, match="chunking.*batch_size=5"):
        sweep(fn, inputs, batch_size=5)
    with pytest.raises(ValueError, match="`fn`"):
        sweep(lambda p: jax.tree.map(lambda a: 2 * a, fn(p)), inputs)
    with pytest.raises(ValueError, match="dtypes"):
        sweep(fn, {"x": inputs["x"].astype(np.float32), "y": inputs["y"]})
    assert ns["CALLS"] == []
    assert _chunk_files(folder) == before

    # A chunk file from another sweep dropped into this folder: refused as well.
    elsewhere = tmp_path / "elsewhere"
    sweep(fn, other, checkpoint=elsewhere)
    (folder / "chunk_000003.npz").write_bytes(
        (elsewhere / "chunk_000003.npz").read_bytes()
    )
    with pytest.raises(ValueError, match="chunk_000003.npz carries the fingerprint"):
        sweep(fn, inputs)


def test_a_second_sweep_of_the_same_fn_does_not_retrace():
    """The chunk program is kept per `fn`: sweeping it again (new values, same
    shapes) neither traces nor compiles again, and the answer follows the inputs."""
    traces = []

    def fn(x):
        traces.append(None)
        return jnp.sin(x) * 2.0

    first = cjax.sweep(fn, np.linspace(0.0, 1.0, 10), batch_size=4, progress=False)
    second = cjax.sweep(fn, np.linspace(1.0, 2.0, 10), batch_size=4, progress=False)
    assert len(traces) == 1
    np.testing.assert_allclose(first, 2 * np.sin(np.linspace(0.0, 1.0, 10)), rtol=1e-15)
    np.testing.assert_allclose(
        second, 2 * np.sin(np.linspace(1.0, 2.0, 10)), rtol=1e-15
    )
