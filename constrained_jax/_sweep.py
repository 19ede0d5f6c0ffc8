"""`sweep()`: one function over many inputs, in chunks of `jit(vmap(fn))`, sharded over
the local devices, with a progress bar and an optional resumable checkpoint.

The chunk layout: the inputs (leading axis `N`) are cut into `ceil(N / chunk_size)`
chunks of `chunk_size` rows; the last one is padded by repeating its last row, so every
chunk has the same shape and one compiled program serves them all; the padding rows'
outputs are dropped. Each chunk is moved to the devices, evaluated, and its outputs
brought back to host memory before the next one is sent: device memory is bounded by
one chunk, whatever `N`.

The checkpoint folder holds `manifest.json` (what was swept: the fingerprint) and one
file `chunk_XXXXXX.npz` per finished chunk, each written atomically (a temporary file
in the same folder, `fsync`, `os.replace`) with the fingerprint's digest and a SHA-256
checksum of its own arrays.

Under `jax.distributed`, chunk `c` is process `c % process_count`'s; the processes
exchange chunks through the folder only (each polls it for the others' files), and
a failing process leaves a note in the key-value store of JAX's coordination
service so that the others stop waiting (`_Peers`).
"""

import collections
import functools
import hashlib
import itertools
import json
import math
import operator
import os
import pathlib
import re
import socket
import tempfile
import time
import types
import warnings
import zlib
from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ._compat import distributed_client, quiet_callback_errors
from ._misc import check_signature, progress_bar


_FORMAT = "constrained_jax.sweep/1"
_MANIFEST = "manifest.json"
_ADDRESS = re.compile(r"0x[0-9a-fA-F]+")
# The fingerprint's fields that the jaxpr of vmap(fn) depends on besides fn itself.
_TRACED_WITH = ("inputs", "chunking", "devices", "format")


def sweep(
    fn: Callable[[Any], Any],
    inputs: Any,
    *,
    batch_size: int = 1024,
    devices: Sequence[jax.Device] | None = None,
    checkpoint: str | os.PathLike | None = None,
    progress: bool = True,
) -> Any:
    """Evaluate `fn` on every input of a batch, in chunks, over all local devices.

    Equivalent to `jax.vmap(fn)(inputs)`, but for any number of inputs: the batch is
    cut into chunks of `batch_size` rows evaluated with one compiled
    `jax.jit(jax.vmap(fn))`, each chunk sharded over the devices along its batch axis
    (a 1-D `jax.sharding.Mesh`, `NamedSharding(mesh, PartitionSpec("batch"))`). Only
    one chunk is on the devices at a time, so device memory is bounded by the chunk
    size whatever the number of inputs.

    **Arguments:**

    - `fn`: maps ONE input (a pytree of arrays, one row of `inputs`) to outputs (a
        pytree of arrays), written as for `jax.vmap`. It is traced and compiled
        once for all chunks; sweeping the same `fn` object again with the same
        chunk shapes and devices reuses both (pass the same function, not a new
        lambda, to repeated sweeps). Unlike a `jax.jit` function, a kept program is
        not reused when a Python value `fn` reads has changed since (a global or a
        closed-over variable reassigned, a numpy array or list written in place,
        an attribute of an object it reads): `fn` is traced again and, if the
        computation differs, compiled again, so a sweep never returns values of
        the old state (the trace caches of `jax.jit` / `eqx.filter_jit` functions
        met on the way, `fn` itself or helpers it calls, are then cleared, since
        they would hand back the old trace). Checking costs well under a
        millisecond (plus hashing any numpy arrays `fn` closes over). What is
        watched (see `_python_state` in `_sweep.py`):
        closure cells, defaults, the globals `fn`'s code names and the attributes
        `module.name` it reads, followed into the functions, containers and
        objects found there (not into the code of JAX and the other numerical
        libraries). State hidden beyond that (behind properties, in C
        extensions, more than 8 levels deep) is not seen: pass changing values
        as `inputs`, or a new `fn`.
    - `inputs`: a pytree whose leaves are arrays (numpy or JAX) with a common leading
        axis of length `N >= 1`: row `i` of every leaf together is input `i`. Keep
        large inputs as numpy arrays: chunks are sliced on the host and only the
        chunk is sent to the devices.
    - `batch_size`: rows per chunk, rounded up to a multiple of the number of devices
        (each device gets `chunk_size / n_devices` rows); if that exceeds `N` (rounded
        up likewise), a single chunk holds everything. The last chunk is padded by
        repeating the last input, so that it has the same shape (no recompilation);
        the padding's outputs are discarded. Choose it so that one chunk fits in
        device memory.
    - `devices`: the devices to shard over; default `jax.local_devices()`. All must
        belong to this process and share one platform.
    - `checkpoint`: a folder (created if missing) to make the sweep resumable; see
        below. `None` (default): nothing is written.
    - `progress`: show a tqdm bar (chunks done, rate, time left; compilation, shown
        as such, is left out of the rate). `False`, or the environment variable
        `TQDM_DISABLE` set to any non-empty value (as tqdm reads it: `0` and `off`
        disable it too), turns it off. A long single
        simulation has diffrax's progress meter instead:
        `cjax.simulate(..., progress_meter=diffrax.TqdmProgressMeter())`.

    **Returns:** the outputs pytree with a leading axis `N` on every leaf, as host
    **numpy** arrays (the same whether a chunk was computed now or read back from a
    checkpoint); `jnp.asarray` moves them to a device if wanted.

    **Checkpoints.** With `checkpoint=folder`, every finished chunk is written to
    `folder/chunk_XXXXXX.npz` atomically (temporary file, `fsync`, `os.replace`: a
    killed process leaves either the whole chunk or nothing). The folder's
    `manifest.json` records the fingerprint of the sweep: a SHA-256 of the input
    leaves' bytes, shapes, dtypes and tree structure; `N`, the chunk size and number
    of chunks; the devices (count, platform, kind); and `fn`, as a SHA-256 of the
    jaxpr of `vmap(fn)` on one chunk (its text, with memory addresses removed, and
    the values of its closed-over constants). Calling `sweep` again with the same
    folder resumes: finished chunks are read back (each checked against its
    checksum) and never recomputed, and the result is bit-identical to an
    uninterrupted run. A folder written for a different sweep (other inputs, batch
    size, devices, or `fn`) raises a `ValueError` naming what differs: use a new
    folder, or delete the old one to start again. A chunk file that is truncated or
    corrupted is reported with a warning and recomputed, never used.

    !!! note

        What the `fn` fingerprint sees is the computation JAX traces: changing the
        code, the shapes or a closed-over array changes it, so does upgrading JAX or
        a library `fn` calls into (then the checkpoint is refused). It does not see
        inside Python callbacks (`jax.pure_callback`, `jax.debug.callback`): changing
        a callback's Python code needs a new folder.

    One sweep per folder at a time (one process, or the processes of one
    `jax.distributed` job): a sweep holds the folder's lock file
    `sweep.p<process index>.lock` (its process id and host) while it runs, and a
    second sweep on the same folder is refused with a `ValueError`, before it
    reads or writes anything there. A lock left by a process that has ended (on this
    host) is taken over; one left on another host must be deleted by hand. A sweep
    refused for any reason writes nothing: a folder whose manifest was lost is
    refused, without a new manifest, if its chunk files carry another sweep's
    fingerprint.

    **Several processes or hosts.** Under `jax.distributed.initialize()` (SLURM,
    Kubernetes, or several processes on one machine), call `sweep` the same way in
    every process, with the same `fn`, the same `inputs` and the same `checkpoint`
    folder, one that every process can read and write (a shared file system): chunk
    `c` is evaluated by process `c % jax.process_count()`, on that process's local
    devices, and written to the folder; every process then reads the others'
    chunks from the folder as they appear and returns the whole result (the same
    bits in every process, and as with one process with as many devices of that
    kind). No communication between the processes is needed besides the folder,
    and no process waits for another before its own chunks are done. The chunking
    must be the same in all processes (the same number and kind of local devices,
    the same `batch_size`): a process whose sweep differs is refused by the
    folder's manifest, like any other sweep.

    - If a process raises, it tells the others through JAX's coordination service,
        and they raise too (rather than wait for chunks that will not come), once
        their own chunks are done.
    - If a process dies, its finished chunks are on disk and its unfinished ones are
        lost; JAX's runtime ends the other processes (after
        `heartbeat_timeout_seconds` of `jax.distributed.initialize`), their own
        chunks done. Start the job again with the same folder:
        chunks already there are read back, whoever wrote them, and only the missing
        ones are computed (with any number of processes).
    - Without a checkpoint folder, `sweep` raises a `ValueError` under several
        processes: the folder is how they exchange their chunks.

    Tested with two processes on one machine, each with two CPU devices (forced by
    `XLA_FLAGS=--xla_force_host_platform_device_count=2`), including one killed
    mid-sweep and resumed.

    **Errors inside `fn`.** A run-time error of `fn` (an `eqx.error_if`, e.g. a solve
    called with `throw=True` that fails) stops the sweep: the chunk where it
    happened is evaluated again on subsets of its rows (by bisection, with the same
    compiled program; only after a failure, so the sweep costs nothing more when
    nothing fails) and the error raised names the failing rows' indices in
    `inputs` (`jax.errors.JaxRuntimeError`, the original message included). The
    chunks finished before it are in the checkpoint, if one is kept. To get every
    row's answer instead, call the solves with `throw=False` and return their
    `result` from `fn`: the failing rows are
    `np.flatnonzero(out.result != cjax.RESULTS.successful)`, and values that are
    NaN or inf are returned as they are, never dropped. On CPU with several devices
    per process (`--xla_force_host_platform_device_count`), JAX 0.10.2 does not
    return from a chunk whose `fn` raised (the other devices wait for the failing
    one in a collective; seen with one process and with several): there, use
    `throw=False`, or one device per process.

    **Raises:** `ValueError` for leaves that are not arrays or have no leading axis,
    leading axes of different lengths (the message lists each leaf's length), `N =
    0` (nothing to evaluate: filter empty batches out before calling `sweep`),
    text or object arrays, `batch_size < 1`, bad `devices`, a `fn` that does not take
    one argument, a checkpoint folder from a different sweep, or one in use by
    another sweep.
    """
    if jax.process_count() == 1:
        return _sweep(fn, inputs, batch_size, devices, checkpoint, progress, None)
    peers = _Peers()
    try:
        return _sweep(fn, inputs, batch_size, devices, checkpoint, progress, peers)
    except BaseException as error:
        peers.report(error)
        raise


def _sweep(fn, inputs, batch_size, devices, checkpoint, progress, peers):
    """`sweep`; `peers`: the other processes under `jax.distributed`, or `None`."""
    check_signature(fn, "`fn` of `cjax.sweep`", "fn(inputs)")
    leaves, paths, treedef, n = _check_inputs(inputs)
    batch_size = _check_batch_size(batch_size)
    devices = _check_devices(devices)
    me, processes = jax.process_index(), jax.process_count()
    if processes > 1 and checkpoint is None:
        raise ValueError(
            f"`sweep` runs in one of {processes} processes (`jax.distributed`): each "
            "process evaluates its share of the chunks and the processes exchange "
            "them through the checkpoint folder. Pass `checkpoint=folder`, a folder "
            "that every process can read and write (the same path in all of them)."
        )
    n_devices = len(devices)
    chunk = min(_round_up(batch_size, n_devices), _round_up(n, n_devices))
    n_chunks = math.ceil(n / chunk)

    mesh = Mesh(np.asarray(devices, dtype=object), ("batch",))
    sharding = NamedSharding(mesh, PartitionSpec("batch"))
    dtypes = [jax.dtypes.canonicalize_dtype(leaf.dtype) for leaf in leaves]
    specs = jax.tree.unflatten(
        treedef,
        [
            jax.ShapeDtypeStruct((chunk,) + leaf.shape[1:], dtype, sharding=sharding)
            for leaf, dtype in zip(leaves, dtypes, strict=True)
        ],
    )
    # At most one trace and one compilation per sweep; none when the same `fn` is
    # swept again with the same chunk shapes and devices and the Python values it
    # reads unchanged (JAX's caches, through one jitted function kept per `fn`).
    traced, fn_fingerprint = _chunk_traced(fn, sharding, specs)
    out_info, out_treedef = jax.tree.flatten(traced.out_info)
    if any(jax.dtypes.issubdtype(o.dtype, jax.dtypes.extended) for o in out_info):
        raise ValueError(
            "`fn` returns arrays of an extended dtype (typed PRNG keys?), which "
            "cannot be brought to the host: return `jax.random.key_data(keys)`."
        )
    outputs = [np.empty((n,) + o.shape[1:], o.dtype) for o in out_info]

    store = None
    done = [False] * n_chunks
    if checkpoint is not None:
        key = {
            "format": _FORMAT,
            "inputs": _inputs_fingerprint(leaves, paths, treedef),
            "length": n,
            "chunking": {"chunk_size": chunk, "chunks": n_chunks},
            "devices": _devices_fingerprint(devices),
            "fn": fn_fingerprint,
            "outputs": {
                "structure": _strip_addresses(str(out_treedef)),
                "shapes": [list(o.shape[1:]) for o in out_info],
                "dtypes": [np.dtype(o.dtype).str for o in out_info],
            },
        }
        info = {"batch_size": batch_size, "jax": jax.__version__}
        store = _Checkpoint(pathlib.Path(checkpoint), key, info)
        try:
            for index in range(n_chunks):
                start, stop = _bounds(index, chunk, n)
                loaded = store.load(index, start, stop, outputs)
                if loaded is not None:
                    for out, part in zip(outputs, loaded, strict=True):
                        out[start:stop] = part
                    done[index] = True
        except BaseException:
            store.close()
            raise

    desc = "cjax.sweep" if processes == 1 else f"cjax.sweep [{me}/{processes}]"
    bar = progress_bar(
        progress, total=n_chunks, initial=sum(done), unit="chunk", desc=desc
    )
    compiled = None

    def evaluate(index: int) -> None:
        nonlocal compiled
        if compiled is None:
            bar.set_postfix_str("compiling", refresh=True)
            compiled = traced.lower().compile()
            bar.set_postfix_str("", refresh=False)
            bar.unpause()  # the rate and time left leave compilation out
        start, stop = _bounds(index, chunk, n)
        host_in = [
            _padded_rows(leaf, start, stop, chunk, dtype)
            for leaf, dtype in zip(leaves, dtypes, strict=True)
        ]
        try:
            host_out = _run_chunk(compiled, host_in, treedef, sharding)
        except jax.errors.JaxRuntimeError as error:
            # Only on failure: find the rows that raise (by bisection with the same
            # compiled program) and say which they are.
            _raise_with_rows(error, compiled, host_in, treedef, sharding, start, n)
        host_out = [x[: stop - start] for x in host_out]
        for out, part in zip(outputs, host_out, strict=True):
            out[start:stop] = part
        if store is not None:
            store.save(index, start, stop, host_out)
        done[index] = True
        bar.update(1)

    try:
        # Chunk `index` is this process's if `index % processes == me`.
        for index in range(me, n_chunks, processes):
            if not done[index]:
                evaluate(index)
        if peers is not None:
            peers.collect(store, done, outputs, chunk, n, evaluate, bar)
    finally:
        bar.close()
        if store is not None:
            store.close()
    return jax.tree.unflatten(out_treedef, outputs)


# The last few chunk programs, one per `(fn, sharding, chunk shapes)`, each with the
# snapshot of the Python values `fn` read when it was traced. A strong, bounded
# cache: the jitted function holds `fn`, so a weak-keyed one would never let go of it.
_PROGRAMS: "collections.OrderedDict[tuple, _Program]" = collections.OrderedDict()
_PROGRAMS_KEPT = 16


class _Program:
    __slots__ = ("jitted", "fingerprint", "state", "kept")

    def __init__(self, jitted, fingerprint, state, kept):
        self.jitted = jitted
        # `_fn_fingerprint` of its trace, taken when traced: a numpy constant of the
        # jaxpr may be the user's array itself, written in place since.
        self.fingerprint = fingerprint
        self.state = state  # what `_python_state(fn)` gave after tracing
        self.kept = kept  # the objects `state` names by id (so ids stay unique)


def _chunk_traced(fn, sharding, specs):
    """`jit(vmap(fn))` for `sharding`, traced for `specs`, and the `_fn_fingerprint`
    of that trace.

    The jitted function is kept per `(fn, sharding, specs)`, so that sweeping `fn`
    again reuses JAX's trace and compilation caches, as a second call of one
    `jax.jit` function would. Unlike `jax.jit`, a `fn` whose Python state changed
    (a global or closed-over value it reads was reassigned or mutated: see
    `_python_state`) is traced again; if the new jaxpr (text and constants) differs
    from the kept one, a new program replaces it, so the sweep never returns values
    computed with the old state. Checking the state costs microseconds; a new trace
    (tens to hundreds of milliseconds) is paid only when it changed, and the
    fingerprint (a few percent of a compilation) only with a new trace."""
    make = lambda: jax.jit(jax.vmap(fn), in_shardings=sharding, out_shardings=sharding)
    leaves, structure = jax.tree.flatten(specs)
    key = (fn, sharding, structure, tuple((s.shape, s.dtype) for s in leaves))
    try:
        kept = _PROGRAMS.pop(key, None)
    except TypeError:  # unhashable fn: no reuse
        traced = make().trace(specs)
        return traced, _fn_fingerprint(traced.jaxpr)
    if kept is not None:
        state, objects = _python_state(fn)
    if kept is not None and state == kept.state:
        program, traced = kept, kept.jitted.trace(specs)
    else:
        if kept is not None:
            # `jax.jit` functions that fn calls (its own, or an `eqx.filter_jit`'s)
            # keep traces of the old state: a new trace of fn would reuse them.
            for obj in objects:
                if _is_jitted(obj):
                    obj.clear_cache()
        jitted = make()
        traced = jitted.trace(specs)
        fingerprint = _fn_fingerprint(traced.jaxpr)
        if kept is not None and fingerprint == kept.fingerprint:
            # The state changed but not the computation (fn does not read what
            # changed): keep the old program and its compilation.
            jitted, traced = kept.jitted, kept.jitted.trace(specs)
        # The snapshot after tracing: a trace that mutates what it reads (a list
        # counting traces) is not a change.
        program = _Program(jitted, fingerprint, *_python_state(fn))
    _PROGRAMS[key] = program
    while len(_PROGRAMS) > _PROGRAMS_KEPT:
        _PROGRAMS.popitem(last=False)
    return traced, program.fingerprint


# Python state of `fn` (see `_python_state`): packages whose functions are not
# looked into (their module state is the library's, not the user's), and bounds.
_LIBRARIES = frozenset(
    {
        "builtins",
        "collections",
        "constrained_jax",
        "diffrax",
        "equinox",
        "functools",
        "jax",
        "jaxlib",
        "jaxtyping",
        "lineax",
        "math",
        "numpy",
        "optax",
        "optimistix",
        "scipy",
        "typing",
    }
)
_STATE_DEPTH = 8
_STATE_OBJECTS = 2000
_STATE_ITEMS = 256  # items of one container looked at


def _python_state(fn) -> tuple[tuple, list]:
    """A snapshot of the Python values `fn` may read when traced, to tell whether a
    kept trace of `fn` is stale: returns `(tokens, objects)`, `tokens` comparable
    with `==`, `objects` the objects named in it by `id` (keep them alive).

    Walks from `fn`: its closure cells, defaults, and the globals its code names
    (`co_names`, nested code included); for a global module `m`, the attributes
    `m.name` its code may read; into functions, bound methods, `functools.partial`,
    `__wrapped__`, tuples, lists, dicts and objects' `__dict__` (eqx.Modules: their
    fields, e.g. a user's Lagrangian), to depth 8 and 2,000 objects. Scalars and
    strings enter by value, numpy arrays by a CRC-32 of their bytes (in-place
    writes are seen; about a millisecond per megabyte), anything else (JAX arrays,
    which are immutable) by identity.
    Functions of the libraries in `_LIBRARIES` are not looked into. Not seen: state
    beyond those bounds, behind properties or `__getattr__`, or in C extensions. If
    looking raises, the snapshot equals nothing (`fn` is traced at every sweep)."""
    tokens: list = []
    objects: list = []
    seen: set = set()

    def library(obj) -> bool:
        module = getattr(obj, "__module__", None)
        return isinstance(module, str) and module.split(".")[0] in _LIBRARIES

    def visit(obj, depth: int) -> None:
        if obj is None or isinstance(obj, (bool, int, str, bytes)):
            tokens.append((type(obj).__name__, obj))
            return
        if isinstance(obj, (float, complex)):
            tokens.append((type(obj).__name__, repr(obj)))  # nan == nan by repr
            return
        if id(obj) in seen:
            tokens.append(("again", id(obj)))
            return
        if depth > _STATE_DEPTH or len(seen) >= _STATE_OBJECTS:
            tokens.append(("deep", id(obj)))
            objects.append(obj)
            return
        seen.add(id(obj))
        objects.append(obj)
        tokens.append((type(obj).__qualname__, id(obj)))
        if isinstance(obj, (np.ndarray, np.generic)):
            a = np.asarray(obj)
            if not a.dtype.hasobject:
                a = np.ascontiguousarray(a)
                # CRC-32: cheaper than a cryptographic hash, and a change is all
                # it has to see.
                crc = zlib.crc32(memoryview(a.reshape(-1).view(np.uint8)))
                tokens.append((a.shape, a.dtype.str, crc))
            return
        if isinstance(obj, (type, types.ModuleType, jax.Array)):
            return
        if isinstance(obj, types.FunctionType):
            if depth > 0 and library(obj):
                return
            for cell in obj.__closure__ or ():
                try:
                    visit(cell.cell_contents, depth + 1)
                except ValueError:  # an empty cell
                    tokens.append("empty cell")
            visit(obj.__defaults__, depth + 1)
            visit(obj.__kwdefaults__, depth + 1)
            names = _code_names(obj.__code__)
            namespace = obj.__globals__
            for name in names:
                if name not in namespace:
                    continue
                value = namespace[name]
                tokens.append(name)
                if isinstance(value, types.ModuleType):
                    attributes = vars(value)
                    for attribute in names:
                        if attribute in attributes:
                            tokens.append(attribute)
                            visit(attributes[attribute], depth + 1)
                else:
                    visit(value, depth + 1)
            return
        if isinstance(obj, types.MethodType):
            visit(obj.__func__, depth + 1)
            visit(obj.__self__, depth + 1)
            return
        if isinstance(obj, functools.partial):
            visit(obj.func, depth + 1)
            visit(obj.args, depth + 1)
            visit(obj.keywords, depth + 1)
            return
        if isinstance(obj, (tuple, list)):
            tokens.append(len(obj))
            for item in obj[:_STATE_ITEMS]:
                visit(item, depth + 1)
            return
        if isinstance(obj, dict):
            items(obj, depth)
            return
        wrapped = getattr(obj, "__wrapped__", None)
        if wrapped is not None and (not library(obj) or _is_jitted(obj)):
            visit(wrapped, depth + 1)
        try:
            attributes = vars(obj)
        except TypeError:
            return
        items(attributes, depth)

    def items(mapping, depth: int) -> None:
        tokens.append(len(mapping))
        for k, v in list(mapping.items())[:_STATE_ITEMS]:
            visit(k, depth + 1)
            visit(v, depth + 1)

    try:
        visit(fn, 0)
    except Exception:  # an object that cannot be looked into: trace every time
        return (("unreadable", object()),), []
    return tuple(tokens), objects


def _is_jitted(obj) -> bool:
    """A `jax.jit` function (with a trace cache of its own)."""
    return type(obj).__name__ == "PjitFunction" and callable(
        getattr(obj, "clear_cache", None)
    )


def _code_names(code: types.CodeType) -> tuple[str, ...]:
    names = list(code.co_names)
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            names.extend(_code_names(const))
    return tuple(dict.fromkeys(names))


_BISECTION_RUNS = 256  # runs of a failed chunk to find its failing rows, at most


def _run_chunk(compiled, host_in, treedef, sharding) -> list:
    """One chunk (host numpy rows in) through `compiled`: host numpy leaves out."""
    device_in = jax.device_put(jax.tree.unflatten(treedef, host_in), sharding)
    device_out = compiled(device_in)
    host_out = [np.asarray(x) for x in jax.device_get(jax.tree.leaves(device_out))]
    del device_in, device_out  # nothing of this chunk stays on the devices
    return host_out


def _raise_with_rows(error, compiled, host_in, treedef, sharding, start, n):
    """`fn` raised at run time (an `eqx.error_if`, e.g. a solve with `throw=True`)
    somewhere in a chunk: find the rows that raise by bisection, each test a run of
    the same compiled program on a chunk made of some rows only (repeated to fill
    it), and raise naming them (global indices) with the first message."""
    chunk = host_in[0].shape[0]
    real = min(chunk, n - start)
    runs = [0]

    def raises(rows) -> bool:
        runs[0] += 1
        take = np.resize(np.asarray(rows), chunk)  # the rows, repeated to fill
        try:
            _run_chunk(compiled, [leaf[take] for leaf in host_in], treedef, sharding)
        except jax.errors.JaxRuntimeError:
            return True
        return False

    def failing(rows) -> list:
        if runs[0] >= _BISECTION_RUNS or not raises(rows):
            return []
        if len(rows) == 1:
            return list(rows)
        half = len(rows) // 2
        return failing(rows[:half]) + failing(rows[half:])

    # The bisection's own failures are expected: keep JAX from logging each one.
    with quiet_callback_errors():
        rows = failing(list(range(real))) if real > 1 else list(range(real))
    if not rows:  # no subset raises on its own: report the error as it was
        raise error
    named = [start + r for r in rows]
    listed = ", ".join(map(str, named[:20])) + (
        f", ... ({len(named)} rows)" if len(named) > 20 else ""
    )
    if runs[0] >= _BISECTION_RUNS:
        listed += f" and maybe others (the search stopped after {runs[0]} runs)"
    if len(named) == real > 1:
        listed += " (every row of the chunk: the error may not depend on the row)"
    try:
        kind = type(error)
        kind("")
    except Exception:
        kind = RuntimeError
    raise kind(
        f"cjax.sweep: `fn` raised on input row{'s' if len(named) > 1 else ''} "
        f"{listed} (indices into the leading axis of `inputs`, N = {n}; of rows "
        f"{start} to {start + real - 1}, the chunk being evaluated: later rows were "
        "not evaluated). To get "
        "every row's answer instead, have `fn` call its solves with `throw=False` "
        "and return their `result`: the failing rows are then "
        "`np.flatnonzero(out.result != cjax.RESULTS.successful)`. The error raised:\n"
        f"{error}"
    ) from error


def _round_up(x: int, multiple: int) -> int:
    return -(-x // multiple) * multiple


def _bounds(index: int, chunk: int, n: int) -> tuple[int, int]:
    return index * chunk, min((index + 1) * chunk, n)


def _padded_rows(leaf, start, stop, chunk, dtype):
    """Rows `start:stop` of `leaf` (on the host), padded to `chunk` rows by repeating
    the last one."""
    rows = np.asarray(leaf[start:stop], dtype=dtype)
    missing = chunk - (stop - start)
    if missing:
        rows = np.concatenate([rows, np.repeat(rows[-1:], missing, axis=0)])
    return rows


def _check_inputs(inputs):
    with_paths, treedef = jax.tree_util.tree_flatten_with_path(inputs)
    if not with_paths:
        raise ValueError(
            "`sweep` got inputs without any array leaf: pass a pytree of arrays with "
            "a common leading axis (one row per input)."
        )
    leaves = []
    lengths = {}
    for path, leaf in with_paths:
        name = "inputs" + jax.tree_util.keystr(path)
        if not isinstance(leaf, np.ndarray | jax.Array):
            raise ValueError(
                f"`sweep`: {name} is a {type(leaf).__name__}, not an array. Every leaf "
                "of `inputs` must be an array (numpy or JAX) whose leading axis runs "
                "over the inputs; wrap lists with `np.asarray` and pass constants to "
                "`fn` by closure instead."
            )
        if isinstance(leaf, np.ndarray) and leaf.dtype.kind in "USO":
            held = "objects" if leaf.dtype.kind == "O" else "text"
            raise ValueError(
                f"`sweep`: {name} holds {held} (dtype {leaf.dtype}), which JAX "
                "cannot trace. Every leaf of `inputs` must be a numeric array; map "
                "labels to numbers (an index into a "
                "table `fn` closes over) or loop over them in Python."
            )
        if jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.extended):
            raise ValueError(
                f"`sweep`: {name} has the extended dtype {leaf.dtype} (typed PRNG "
                "keys?); pass `jax.random.key_data(keys)` and rebuild them in `fn` "
                "with `jax.random.wrap_key_data`."
            )
        if leaf.ndim == 0:
            raise ValueError(
                f"`sweep`: {name} is a scalar; every leaf of `inputs` needs a leading "
                "axis running over the inputs (shape `(N, ...)`)."
            )
        lengths[name] = leaf.shape[0]
        leaves.append(leaf if isinstance(leaf, np.ndarray) else np.asarray(leaf))
    if len(set(lengths.values())) > 1:
        listed = ", ".join(f"{k}: {v}" for k, v in lengths.items())
        raise ValueError(
            "`sweep`: the leaves of `inputs` must share their leading axis (one row "
            f"per input), got lengths {listed}."
        )
    n = next(iter(lengths.values()))
    if n == 0:
        raise ValueError(
            "`sweep` got no inputs: the leading axis has length 0 (there is nothing to "
            "evaluate, and no row to learn the outputs' shapes from: skip the call for "
            "an empty batch)."
        )
    return leaves, list(lengths), treedef, n


def _check_batch_size(batch_size) -> int:
    try:
        if isinstance(batch_size, bool):
            raise TypeError
        batch_size = operator.index(batch_size)
    except TypeError:
        raise ValueError(
            f"`batch_size` must be an integer >= 1, got {batch_size!r}."
        ) from None
    if batch_size < 1:
        raise ValueError(f"`batch_size` must be an integer >= 1, got {batch_size}.")
    return batch_size


def _check_devices(devices) -> list:
    if devices is None:
        return list(jax.local_devices())
    devices = list(devices)
    if not devices:
        raise ValueError("`devices` is empty: pass None (all local devices) or a list.")
    if not all(isinstance(d, jax.Device) for d in devices):
        raise ValueError("`devices` must be a list of `jax.Device`s (or None).")
    if len(set(devices)) != len(devices):
        raise ValueError(f"`devices` lists a device twice: {devices}.")
    if len({d.platform for d in devices}) > 1:
        raise ValueError(f"`devices` must share one platform, got {devices}.")
    me = jax.process_index()
    if any(d.process_index != me for d in devices):
        raise ValueError(
            "`sweep` runs on the devices of this process only (`jax.local_devices()`). "
            "Under `jax.distributed`, call it in every process with the same inputs "
            "and `checkpoint` folder: each process evaluates its share of the chunks "
            "on its own devices (see the docstring of `cjax.sweep`)."
        )
    return devices


# --------------------------------------------------------------------------------------
# Several processes (`jax.distributed`): the chunks of the others, through the folder.


class _PeerFailed(RuntimeError):
    pass


_SWEEPS = itertools.count()  # sweeps in this process: the same sequence in every one


class _Peers:
    """The other processes of a sweep under `jax.distributed`: `collect` waits for
    their chunk files in the shared folder; `report` tells them that this process
    failed, through the key-value store of JAX's coordination service, so that they
    raise instead of waiting for chunks that will not come."""

    _POLL = (0.02, 1.0)  # seconds between looks at the folder: first, at most

    def __init__(self):
        self.me = jax.process_index()
        self.key = f"constrained_jax.sweep/{next(_SWEEPS)}/failed/"
        # Private to JAX (`_compat`): without it a failure is seen by JAX's
        # heartbeat only.
        self.client = distributed_client()

    def report(self, error: BaseException) -> None:
        if self.client is None or isinstance(error, _PeerFailed):
            return
        text = f"{type(error).__name__}: {error}"
        try:
            self.client.key_value_set(self.key + str(self.me), text[:2000])
        except Exception:  # the service is gone too: nothing to tell
            pass

    def _check(self) -> None:
        if self.client is None:
            return
        try:
            failed = self.client.key_value_dir_get(self.key)
        except Exception:
            return
        if failed:
            name, text = failed[0]
            raise _PeerFailed(
                f"cjax.sweep: process {name.rsplit('/', 1)[-1]} failed, so its "
                f"chunks will not come; it raised {text}\nThe chunks finished by "
                "every process are in the checkpoint folder: run the sweep again "
                "with the same folder to compute only the others."
            )

    def collect(self, store, done, outputs, chunk, n, evaluate, bar) -> None:
        """Read the other processes' chunks as their files appear (a file there is
        whole: they are written atomically); a corrupted one is computed here."""
        pause = self._POLL[0]
        while not all(done):
            arrived = False
            there = {entry.name for entry in os.scandir(store.folder)}
            for index in [i for i, d in enumerate(done) if not d]:
                if store.path(index).name not in there:
                    continue
                start, stop = _bounds(index, chunk, n)
                loaded = store.load(index, start, stop, outputs)
                if loaded is None:
                    evaluate(index)
                    continue
                for out, part in zip(outputs, loaded, strict=True):
                    out[start:stop] = part
                done[index] = arrived = True
                bar.update(1)
            if not all(done):
                self._check()
                pause = self._POLL[0] if arrived else min(2 * pause, self._POLL[1])
                time.sleep(pause)


# --------------------------------------------------------------------------------------
# Fingerprints and checkpoint files.


def _strip_addresses(text: str) -> str:
    return _ADDRESS.sub("0x", text)


def _update_with_arrays(h, arrays) -> None:
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(memoryview(a.reshape(-1).view(np.uint8)))


def _inputs_fingerprint(leaves, paths, treedef) -> dict:
    def digest(leaf):
        h = hashlib.sha256()
        _update_with_arrays(h, [leaf])
        return h.hexdigest()

    return {
        "structure": _strip_addresses(str(treedef)),
        "leaves": paths,
        "shapes": [list(leaf.shape) for leaf in leaves],
        "dtypes": [leaf.dtype.str for leaf in leaves],
        "sha256": [digest(leaf) for leaf in leaves],
    }


def _devices_fingerprint(devices) -> str:
    d = devices[0]
    return f"{len(devices)} x {d.platform} ({d.device_kind})"


def _fn_fingerprint(closed_jaxpr) -> str:
    """SHA-256 of the jaxpr of `vmap(fn)` on one chunk: its text (deterministic
    across processes once memory addresses are removed) and its constants' values."""
    h = hashlib.sha256()
    h.update(_strip_addresses(str(closed_jaxpr.jaxpr)).encode())
    consts = []
    for c in closed_jaxpr.consts:
        if isinstance(c, jax.Array) and jax.dtypes.issubdtype(
            c.dtype, jax.dtypes.extended
        ):
            c = jax.random.key_data(c)
        consts.append(np.asarray(c))
    _update_with_arrays(h, consts)
    return h.hexdigest()


def _checksum(arrays) -> str:
    h = hashlib.sha256()
    _update_with_arrays(h, arrays)
    return h.hexdigest()


def _temporary_suffix(process: int) -> str:
    """The suffix of this process's temporary files (`.p<index>.tmp`): under
    `jax.distributed` a process cleans up only its own (a predecessor's, killed
    mid-write), never those another process is writing."""
    return f".p{process}.tmp"


def _write_atomically(
    path: pathlib.Path, write: Callable[[Any], None], *, exclusive: bool = False
) -> None:
    """`write(file)` into a temporary file next to `path`, `fsync`, then rename it
    over `path` (atomic on POSIX and Windows): readers see the old file or the whole
    new one, never a partial one. `exclusive=True`: link it to `path` instead, which
    raises `FileExistsError` if `path` exists (another process created it first)."""
    fd, tmp = tempfile.mkstemp(
        dir=path.parent,
        prefix=f".{path.name}.",
        suffix=_temporary_suffix(jax.process_index()),
    )
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        if not exclusive:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path)
            except FileExistsError:
                raise
            except OSError:  # no hard links on this file system: last one wins
                os.replace(tmp, path)
            else:
                os.remove(tmp)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    try:  # make the rename itself durable (POSIX); not possible everywhere
        dir_fd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dir_fd)
    except OSError:
        pass
    finally:
        os.close(dir_fd)


def _lock_path(folder: pathlib.Path) -> pathlib.Path:
    """The lock file of this process's sweep in `folder` (one per process index, so
    that the processes of one `jax.distributed` job share the folder)."""
    return folder / f"sweep.p{jax.process_index()}.lock"


def _lock_holder(path: pathlib.Path) -> dict | None:
    try:
        holder = json.loads(path.read_text())
        return holder if isinstance(holder, dict) else None
    except (OSError, ValueError):
        return None


def _holder_gone(path: pathlib.Path, holder: dict | None) -> bool:
    """Whether the sweep that wrote the lock `path` has certainly ended: its process
    (on this host) no longer exists. A lock of another host, or of a live process,
    is held; an unreadable one (its writer killed between creating and writing it)
    is stale after a minute."""
    if holder is None:
        try:
            return time.time() - path.stat().st_mtime > 60
        except OSError:
            return True  # gone meanwhile
    pid = holder.get("pid")
    if holder.get("host") != socket.gethostname() or not isinstance(pid, int):
        return False
    if os.name != "posix":
        return False  # no signal 0 to ask whether a process lives
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:  # it exists (another user's)
        return False
    return False


def _lock(folder: pathlib.Path) -> pathlib.Path:
    """Take the folder's lock (`O_CREAT | O_EXCL`: one of two sweeps gets it) with
    this process's id and host; a lock whose process has ended is taken over. A
    folder in use by another sweep is refused (`ValueError`), nothing written."""
    path = _lock_path(folder)
    record = json.dumps({"pid": os.getpid(), "host": socket.gethostname()})
    for _ in range(3):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            holder = _lock_holder(path)
            if _holder_gone(path, holder):
                path.unlink(missing_ok=True)  # stale: its sweep was killed
                continue
            who = (
                "an unknown process"
                if holder is None
                else f"process {holder.get('pid')} on {holder.get('host')!r}"
            )
            if holder is not None and holder.get("pid") == os.getpid():
                who = "another sweep of this process"
            raise ValueError(
                f"The checkpoint folder {str(folder)!r} is in use by {who} (its lock "
                f"file {path.name}): two sweeps writing one folder would destroy each "
                "other's files. Wait for that sweep to finish, or pass another folder "
                "as `checkpoint=`. If no sweep is running (a process killed on another "
                f"host), delete {str(path)!r}."
            ) from None
        with os.fdopen(fd, "w") as f:
            f.write(record)
        return path
    raise ValueError(
        f"Could not take the lock {str(path)!r} of the checkpoint folder: another "
        "sweep keeps taking it. Pass another folder as `checkpoint=`."
    )


def _chunk_fingerprint(path: pathlib.Path) -> str | None:
    """The sweep fingerprint a chunk file carries, or `None` if it is unreadable."""
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(data["meta"].tobytes())
    except Exception:
        return None
    return meta.get("fingerprint") if isinstance(meta, dict) else None


def _short(value) -> str:
    text = json.dumps(value) if not isinstance(value, str) else value
    return text if len(text) <= 80 else text[:77] + "..."


class _Checkpoint:
    """A checkpoint folder: `manifest.json` (the sweep's fingerprint `key`, and `info`
    not compared) and one `chunk_XXXXXX.npz` per finished chunk."""

    def __init__(self, folder: pathlib.Path, key: dict, info: dict):
        if folder.exists() and not folder.is_dir():
            raise ValueError(
                f"`checkpoint={str(folder)!r}` exists and is not a folder."
            )
        folder.mkdir(parents=True, exist_ok=True)
        self.folder = folder
        self.key = key
        self.digest = hashlib.sha256(
            json.dumps(key, sort_keys=True).encode()
        ).hexdigest()
        # One sweep per folder at a time: the lock before anything is read or
        # written, so that a refused sweep leaves the folder as it found it.
        self.lock = _lock(folder)
        try:
            self._open(info)
        except BaseException:
            self.close()
            raise

    def _open(self, info: dict) -> None:
        folder = self.folder
        manifest = folder / _MANIFEST
        if not manifest.exists():
            # A folder whose manifest was lost: its chunk files still name their
            # sweep. Refused, without writing a manifest, if they name another.
            for path in sorted(folder.glob("chunk_*.npz")):
                fingerprint = _chunk_fingerprint(path)
                if fingerprint is not None and fingerprint != self.digest:
                    self._refuse(
                        f"it has no {_MANIFEST}, and {path.name} carries the "
                        "fingerprint of another sweep"
                    )
            text = json.dumps({"key": self.key, "info": info}, indent=1, sort_keys=True)
            try:  # exclusive: of processes starting together, one writes it
                _write_atomically(
                    manifest, lambda f: f.write(text.encode()), exclusive=True
                )
            except FileExistsError:
                self._compare(manifest, info)
        else:
            self._compare(manifest, info)
        # Temporary files left by a process killed mid-write: all of them with one
        # process, only this process's own under `jax.distributed`. (No other sweep
        # is writing here: this one holds the folder's lock.)
        if jax.process_count() == 1:
            pattern = ".*.tmp"
        else:
            pattern = ".*" + _temporary_suffix(jax.process_index())
        for stale in folder.glob(pattern):
            stale.unlink(missing_ok=True)

    def close(self) -> None:
        """Release the folder's lock (at the end of the sweep, or on a refusal)."""
        if self.lock is not None:
            self.lock.unlink(missing_ok=True)
            self.lock = None

    def _refuse(self, why: str):
        raise ValueError(
            f"The checkpoint folder {str(self.folder)!r} was written for a different "
            f"sweep: {why}. Its results cannot be reused for this one. Pass a new "
            "folder as `checkpoint=`, or delete this one to start again."
        )

    def _compare(self, manifest: pathlib.Path, info: dict):
        try:
            old = json.loads(manifest.read_text())
            old_key, old_info = old["key"], old.get("info", {})
        except (OSError, ValueError, KeyError, TypeError) as e:
            self._refuse(f"its {_MANIFEST} is unreadable ({e})")
        if old_key == self.key:
            return
        differences = []
        names = {
            "format": "the checkpoint format",
            "length": "the number of inputs N",
            "devices": "the devices",
            "fn": "`fn` (the jaxpr of vmap(fn))",
        }
        for field in sorted(set(old_key) | set(self.key)):
            before, now = old_key.get(field), self.key.get(field)
            if before == now:
                continue
            if field == "inputs" and isinstance(before, dict):
                parts = [
                    f"{k} (checkpoint: {_short(before[k])}; now: {_short(now[k])})"
                    for k in ("structure", "shapes", "dtypes")
                    if before.get(k) != now.get(k)
                ]
                if not parts:
                    changed = [
                        path
                        for path, a, b in zip(
                            now["leaves"], before["sha256"], now["sha256"], strict=True
                        )
                        if a != b
                    ]
                    parts = ["the values of " + ", ".join(changed) + " differ"]
                differences.append("the inputs: " + "; ".join(parts))
            elif field == "chunking":
                differences.append(
                    f"the chunking (checkpoint: {_short(before)} with batch_size="
                    f"{old_info.get('batch_size')}; now: {_short(now)} with batch_size="
                    f"{info['batch_size']}): use the same batch_size and devices"
                )
            elif field == "fn":
                if any(old_key.get(f) != self.key.get(f) for f in _TRACED_WITH):
                    continue  # the jaxpr changes with those; fn may be the same
                note = ""
                if old_info.get("jax") != info["jax"]:
                    note = (
                        f"; the checkpoint was written with JAX {old_info.get('jax')},"
                        f" this is JAX {info['jax']}"
                    )
                differences.append(
                    "`fn` (the jaxpr of vmap(fn) on one chunk, or the values it "
                    f"closes over, changed{note})"
                )
            elif field == "outputs":
                if old_key.get("fn") == self.key.get("fn"):
                    differences.append(
                        f"the outputs ({_short(before)}; now {_short(now)})"
                    )
            else:
                differences.append(
                    f"{names.get(field, field)} (checkpoint: {_short(before)}; now: "
                    f"{_short(now)})"
                )
        self._refuse("; ".join(differences))

    def path(self, index: int) -> pathlib.Path:
        return self.folder / f"chunk_{index:06d}.npz"

    def save(self, index: int, start: int, stop: int, arrays) -> None:
        meta = {
            "fingerprint": self.digest,
            "index": index,
            "start": start,
            "stop": stop,
            "shapes": [list(a.shape) for a in arrays],
            "dtypes": [a.dtype.str for a in arrays],
            "sha256": _checksum(arrays),
        }
        named = {f"leaf_{i}": a for i, a in enumerate(arrays)}
        named["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
        _write_atomically(self.path(index), lambda f: np.savez(f, **named))

    def load(self, index: int, start: int, stop: int, outputs):
        """The chunk's output leaves, or `None` (with a warning if a file was there
        but unusable) if it must be computed."""
        path = self.path(index)
        if not path.exists():
            return None
        try:
            with np.load(path, allow_pickle=False) as data:
                meta = json.loads(data["meta"].tobytes())
                if not isinstance(meta, dict):
                    raise ValueError("its metadata is not a JSON object")
                arrays = [data[f"leaf_{i}"] for i in range(len(outputs))]
                extra = len(data.files) - len(outputs) - 1
        except Exception as e:  # truncated or garbled: zipfile, OSError, EOFError, ...
            return self._discard(path, f"unreadable: {type(e).__name__}: {e}")
        if meta.get("fingerprint") != self.digest:
            self._refuse(
                f"{path.name} carries the fingerprint of another sweep (chunk files "
                "from different folders mixed?)"
            )
        if extra:
            return self._discard(path, "it holds the wrong number of arrays")
        expected = [(stop - start,) + o.shape[1:] for o in outputs]
        fixed = []
        for a, o in zip(arrays, outputs, strict=True):
            if a.dtype != o.dtype and a.dtype.kind == "V" and a.itemsize == o.itemsize:
                a = a.view(o.dtype)  # dtypes numpy cannot name (bfloat16, ...)
            fixed.append(a)
        if (meta.get("index"), meta.get("start"), meta.get("stop")) != (
            index,
            start,
            stop,
        ):
            return self._discard(path, "its chunk bounds do not match its name")
        if [a.shape for a in fixed] != expected or [a.dtype for a in fixed] != [
            o.dtype for o in outputs
        ]:
            return self._discard(path, "its arrays have the wrong shapes or dtypes")
        if _checksum(fixed) != meta.get("sha256"):
            return self._discard(path, "its checksum does not match its contents")
        return fixed

    @staticmethod
    def _discard(path: pathlib.Path, why) -> None:
        warnings.warn(
            f"cjax.sweep: checkpoint file {str(path)!r} is corrupted or truncated "
            f"({why}); its chunk will be recomputed.",
            stacklevel=4,
        )
        return None
