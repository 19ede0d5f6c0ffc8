"""Where the test suite's time goes: per test, the seconds JAX spends tracing,
lowering and compiling (XLA), and how many programs it compiles.

A pytest plugin (JAX's monitoring events, recorded per test in each xdist worker)
and a summary by file:

    PYTHONPATH=benchmarks/dev SUITE_PROFILE_DIR=/tmp/profile \\
        python -m pytest -n 2 --dist worksteal -p suite_profile
    python benchmarks/dev/suite_profile.py /tmp/profile

Subprocesses (the notebooks' kernels, the float32 and multi-process fixtures) are
not seen. Each worker rewrites its JSON after every test, so a crashed run still
leaves what it measured.
"""

import collections
import json
import os
import sys
import time
from pathlib import Path


_current = {"test": None}
_records = collections.defaultdict(collections.Counter)


def _on_duration(event, duration, **kwargs):
    record = _records[_current["test"]]
    record[event.rsplit("/", 1)[-1]] += duration
    if event.endswith("backend_compile_duration"):
        record["compilations"] += 1
        record["compilations_over_1s"] += duration > 1.0


def _on_event(event, **kwargs):
    _records[_current["test"]]["event:" + event.rsplit("/", 1)[-1]] += 1


def pytest_configure(config):
    import jax

    jax.monitoring.register_event_duration_secs_listener(_on_duration)
    jax.monitoring.register_event_listener(_on_event)


def _dump():
    folder = Path(os.environ.get("SUITE_PROFILE_DIR", "suite_profile"))
    folder.mkdir(parents=True, exist_ok=True)
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    data = {str(k): dict(v) for k, v in _records.items() if k is not None}
    (folder / f"{worker}.json").write_text(json.dumps(data))


def pytest_runtest_logstart(nodeid, location):
    _current["test"] = nodeid
    _records[nodeid]["start"] = time.time()


def pytest_runtest_logfinish(nodeid, location):
    record = _records[nodeid]
    record["wall"] += time.time() - record.pop("start", time.time())
    _dump()


def summarize(folder: str) -> None:
    records = {}
    paths = sorted(Path(folder).glob("*.json"))
    if any(path.stem.startswith("gw") for path in paths):
        # Under xdist the controller sees the tests' walls but none of the workers'
        # JAX events: its file would overwrite theirs.
        paths = [path for path in paths if path.stem != "main"]
    for path in paths:
        records.update(json.loads(path.read_text()))
    by_file = collections.defaultdict(collections.Counter)
    total = collections.Counter()
    for test, record in records.items():
        by_file[test.split("::")[0]].update(record)
        total.update(record)
    keys = [
        ("wall", "wall s"),
        ("backend_compile_duration", "XLA s"),
        ("jaxpr_trace_duration", "trace s"),
        ("jaxpr_to_mlir_module_duration", "lower s"),
        ("compilations", "programs"),
        ("compilations_over_1s", "> 1 s"),
    ]
    print("| file | " + " | ".join(name for _, name in keys) + " |")
    print("|---|" + "---:|" * len(keys))
    for name, record in sorted(by_file.items(), key=lambda kv: -kv[1]["wall"]):
        print(f"| {name} | " + " | ".join(f"{record[k]:.0f}" for k, _ in keys) + " |")
    print("| total | " + " | ".join(f"{total[k]:.0f}" for k, _ in keys) + " |")


if __name__ == "__main__":
    summarize(sys.argv[1] if len(sys.argv) > 1 else "suite_profile")
