"""cjax.sweep under `jax.distributed`: two processes on this machine (CPU, two forced
host devices each) share the chunks through the checkpoint folder and both return
the one-process result bit for bit; one of them killed after its first chunk, a
restart of both with the same folder computes only the missing chunks."""

import json
import os
import pathlib
import signal
import socket
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest


ROOT = pathlib.Path(__file__).parents[1]
CHUNKS = 6  # of WORKER's 22 inputs, 4 rows each (2 per device), the last padded
TIMEOUT = 120  # seconds, for any subprocess: the test can never hang

# One process of the sweep: `python -c WORKER process_id port folder out exit_at`
# (`port` 0: no `jax.distributed`, one process). `fn` goes through a callback that
# counts the rows it sees (hence the chunks evaluated) and, with `exit_at` > 0,
# ends the process abruptly (`os._exit`) when its chunk number `exit_at` starts:
# the chunks before it are on disk, nothing of the others; `exit_at` -1: `fn` is
# another function; -2: `fn` raises (`eqx.error_if`) on input row 5.
WORKER = textwrap.dedent(
    """
    import json, os, sys
    process_id, port, folder, out, exit_at = sys.argv[1:]
    import equinox as eqx, jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    if int(port):
        jax.distributed.initialize(
            coordinator_address=f"127.0.0.1:{port}",
            num_processes=2,
            process_id=int(process_id),
        )
    import constrained_jax as cjax
    assert len(jax.local_devices()) == int(os.environ["DEVICES"])
    rng = np.random.default_rng(0)
    inputs = {"x": rng.normal(size=22), "y": rng.normal(size=(22, 3))}
    rows = []

    def count(x):
        if int(exit_at) > 0 and sum(rows) >= (int(exit_at) - 1) * 4:
            os._exit(17)
        rows.append(x.shape[0])
        return x

    def fn(p):
        x = jax.pure_callback(
            count,
            jax.ShapeDtypeStruct(p["x"].shape, p["x"].dtype),
            p["x"],
            vmap_method="broadcast_all",
        )
        if int(exit_at) == -1:  # another fn
            x = 2 * x
        if int(exit_at) == -2:  # fails on row 5 (chunk 1: process 1's)
            x = eqx.error_if(x, x == inputs["x"][5], "no answer for this input")
        y = p["y"]
        return {"s": jnp.sin(x) * y[0] + jnp.exp(-y[1]), "t": jnp.cumsum(y) * x}

    result = cjax.sweep(
        fn, inputs, batch_size=4, checkpoint=None if folder == "-" else folder
    )
    np.savez(out, s=result["s"], t=result["t"])
    with open(out + ".json", "w") as f:
        json.dump({"chunks": sum(rows) / 4, "process": jax.process_index(),
                   "processes": jax.process_count()}, f)
    """
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start(process_id, port, folder, out, exit_at=0, devices=2) -> subprocess.Popen:
    env = dict(
        os.environ,
        JAX_PLATFORMS="cpu",
        XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}",
        DEVICES=str(devices),
        TQDM_DISABLE="1",
        PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
    )
    args = [str(process_id), str(port), str(folder), str(out), str(exit_at)]
    return subprocess.Popen(
        [sys.executable, "-c", WORKER, *args],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def _finish(procs, timeout=TIMEOUT) -> list[tuple[int, str]]:
    """Wait for every process (killing all at the deadline): (returncode, output)."""
    deadline = time.monotonic() + timeout
    results = []
    try:
        for proc in procs:
            left = max(deadline - time.monotonic(), 1)
            output, _ = proc.communicate(timeout=left)
            results.append((proc.returncode, output))
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    return results


def _sweep_in_two(folder, out_dir, exit_at=(0, 0), devices=2):
    port = _free_port()
    return [
        _start(k, port, folder, out_dir / f"out_{k}.npz", exit_at[k], devices)
        for k in (0, 1)
    ]


def _result(path):
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    info = json.loads(pathlib.Path(str(path) + ".json").read_text())
    return arrays, info


def _assert_equal(a, b):
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape
        np.testing.assert_array_equal(a[k], b[k])


def _chunk_files(folder):
    return {
        p.name: (p.stat().st_ino, p.stat().st_mtime_ns)
        for p in sorted(folder.glob("chunk_*.npz"))
    }


def _both_return(procs, out_dir, reference) -> list[dict]:
    """Both processes succeed and return `reference` bit for bit: their infos."""
    for code, output in _finish(procs):
        assert code == 0, output
    infos = []
    for k in (0, 1):
        arrays, info = _result(out_dir / f"out_{k}.npz")
        _assert_equal(arrays, reference)
        infos.append(info)
    return infos


def _names(*chunks) -> set[str]:
    return {f"chunk_{c:06d}.npz" for c in chunks}


@pytest.fixture(scope="module")
def one_process(tmp_path_factory):
    """The reference: one process, the same two devices, no checkpoint."""
    out = tmp_path_factory.mktemp("one") / "out.npz"
    ((code, output),) = _finish([_start(0, 0, "-", out)])
    assert code == 0, output
    arrays, info = _result(out)
    assert info == {"chunks": CHUNKS, "process": 0, "processes": 1}
    return arrays


def test_two_processes_share_the_chunks(tmp_path, one_process):
    folder = tmp_path / "ckpt"
    infos = _both_return(_sweep_in_two(folder, tmp_path), tmp_path, one_process)
    # Chunk c is process c % 2's: three each, none twice.
    assert [i["chunks"] for i in infos] == [3, 3]
    assert [(i["process"], i["processes"]) for i in infos] == [(0, 2), (1, 2)]
    assert len(_chunk_files(folder)) == CHUNKS
    assert not list(folder.glob(".*.tmp"))


def test_killed_process_resumes(tmp_path, one_process):
    """Process 1 dies (`os._exit`) as its second chunk starts; process 0 finishes its
    own chunks and waits for the others, killed then. Both restarted with the same
    folder: only the two lost chunks are computed, the finished files are left as
    they were, and both return the one-process result bit for bit."""
    folder = tmp_path / "ckpt"
    first, second = _sweep_in_two(folder, tmp_path, exit_at=(0, 2))
    try:
        ((code, output),) = _finish([second])
        assert code == 17, output
        deadline = time.monotonic() + TIMEOUT
        while set(_chunk_files(folder)) != _names(0, 1, 2, 4):
            assert first.poll() is None, first.communicate()[0]
            assert time.monotonic() < deadline, _chunk_files(folder)
            time.sleep(0.05)
        time.sleep(0.5)
        assert first.poll() is None  # waiting for chunks 3 and 5, not returning
        first.send_signal(signal.SIGKILL)
    finally:
        _finish([first])
    assert first.returncode == -signal.SIGKILL
    before = _chunk_files(folder)

    infos = _both_return(_sweep_in_two(folder, tmp_path), tmp_path, one_process)
    # Chunks 3 and 5, by process 1; nothing recomputed.
    assert [i["chunks"] for i in infos] == [0, 2]
    after = _chunk_files(folder)
    assert len(after) == CHUNKS
    assert {k: after[k] for k in before} == before
    assert not list(folder.glob(".*.tmp"))


def test_a_failing_process_stops_the_others(tmp_path):
    """One process raises (here: it sweeps another `fn`, so the folder's manifest,
    written by the other, refuses it): the other process, its own chunks done,
    raises too (told through JAX's coordination service) instead of waiting for
    chunks that will not come."""
    folder = tmp_path / "ckpt"
    results = _finish(_sweep_in_two(folder, tmp_path, exit_at=(0, -1)), timeout=60)
    (code0, output0), (code1, output1) = results
    refused = "was written for a different sweep: `fn`"
    assert code0 != 0 and code1 != 0, results
    # Whichever process wrote the manifest first, the other is refused.
    told = [o for o in (output0, output1) if "so its chunks will not come" in o]
    assert len(told) == 1, results
    (told,) = told
    other = output1 if told is output0 else output0
    assert refused in other
    assert refused in told and "same folder" in told


def test_a_run_time_error_stops_the_others(tmp_path):
    """`fn` raises on input row 5 (process 1's chunk): process 1 names the row, and
    process 0 raises with its message once its own chunks are on disk. One device
    per process: with several, a failing callback leaves the other devices of its
    process waiting in XLA's collectives on CPU (as in one process)."""
    folder = tmp_path / "ckpt"
    results = _finish(
        _sweep_in_two(folder, tmp_path, exit_at=(-2, -2), devices=1), timeout=60
    )
    (code0, output0), (code1, output1) = results
    assert code1 != 0 and "`fn` raised on input row 5 " in output1, results
    assert "no answer for this input" in output1
    assert code0 != 0 and "process 1 failed" in output0, results
    assert "`fn` raised on input row 5 " in output0
    assert set(_chunk_files(folder)) == _names(0, 2, 4)


def test_several_processes_need_a_checkpoint(monkeypatch):
    import jax

    import constrained_jax as cjax

    monkeypatch.setattr(jax, "process_count", lambda: 2)
    with pytest.raises(ValueError, match="checkpoint=folder"):
        cjax.sweep(lambda x: 2 * x, np.arange(4.0), progress=False)
