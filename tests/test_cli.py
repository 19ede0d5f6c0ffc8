"""The command line: the tour checks every scene against its closed form and draws
its pictures; `scene NAME --param` runs one scene; failures give exit status 1.

The tour runs once per test module, as users run it: in a fresh process with no
`XLA_FLAGS` (so with the code generator and the diffrax patch the command line turns
on), followed in that process by the `scene` commands that the tests below check
(they reuse its compiled programs). The tests that patch the command line's
internals call `main` here, on the smallest scene."""

import contextlib
import importlib.metadata
import inspect
import io
import json
import math
import pathlib
import re
import subprocess
import sys
import time

import pytest

import constrained_jax.__main__ as cli
from constrained_jax import _code_generator, tour as tour_entries
from constrained_jax.__main__ import main

from .helpers import run_python


SCENES = [
    "cylinder_volume",
    "pendulum",
    "two_cylinders",
    "bouncing_ball",
    "friction",
    "rolling_disk",
    "rotating_hoop",
    "catenary",
    "dido",
    "sphere_geodesic",
]
PICTURES = [
    "cylinder_extremum.png",
    "two_cylinders_normal_force.png",
    "friction_two_cylinders.png",
    "catenary.png",
    "work_precision.png",
]


def _main(argv):
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(argv)
    return code, out.getvalue()


# The commands the fresh process runs after the tour, by name.
_SCENE_COMMANDS = {
    "cylinder_volume(b=2, l=3)": [
        "scene", "cylinder_volume", "--b", "2", "--l", "3", "--no-plots"
    ],
    "two_cylinders(theta0=0.3, alpha=1)": [
        "scene", "two_cylinders", "--theta0", "0.3", "--alpha", "1", "--out", "{out}"
    ],
    "pendulum(theta0=0.5, periods=2)": [
        "scene", "pendulum", "--theta0", "0.5", "--periods", "2", "--no-plots"
    ],
    "catenary(length=2, yr=0.5)": [
        "scene", "catenary", "--length", "2", "--yr", "0.5", "--no-plots"
    ],
    "sphere_geodesic(radius=2)": [
        "scene", "sphere_geodesic", "--radius", "2", "--no-plots"
    ],
}  # fmt: skip

_DRIVER = """
import contextlib, io, json, os
from constrained_jax.__main__ import main
results = {}
for name, argv in COMMANDS.items():
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(argv)
    results[name] = [code, out.getvalue()]
results["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "")
with open("results.json", "w") as f:
    json.dump(results, f)
"""


@pytest.fixture(scope="module")
def cli_runs(tmp_path_factory):
    """`(results, folder)`: the tour (`--out folder/tour`) and `_SCENE_COMMANDS`
    (`--out folder/NAME`) run by one fresh process in `folder`, each as `[exit status,
    output]` by name, and its final `XLA_FLAGS`."""
    folder = tmp_path_factory.mktemp("cli")
    commands = {"tour": ["tour", "--out", str(folder / "tour")]}
    for name, argv in _SCENE_COMMANDS.items():
        commands[name] = [a.replace("{out}", str(folder / name)) for a in argv]
    run = run_python(
        f"COMMANDS = {commands!r}\n{_DRIVER}", timeout=900, cwd=folder, XLA_FLAGS=None
    )
    assert run.returncode == 0, run.stdout + run.stderr
    return json.loads((folder / "results.json").read_text()), folder


@pytest.fixture(scope="module")
def tour(cli_runs):
    results, folder = cli_runs
    code, out = results["tour"]
    return code, out, folder / "tour"


@pytest.fixture(autouse=True)
def _restore_diffrax_patch(diffrax_patch):
    """`main` turns on the diffrax patch for the rest of its process: the tests that
    call it here leave the worker as they found it (`conftest.diffrax_patch`)."""


def _rows(out):
    """Table rows as {(scene, quantity): (computed, closed form, rel. error, tol)}:
    a row is indented under its scene's heading (`label` or `label: note`)."""
    rows = {}
    scene = None
    for line in out.splitlines():
        if line and not line.startswith(" "):
            scene = line.split(": ")[0]
        if not line.startswith("  ") or not line.endswith((" ok", " FAIL")):
            continue
        quantity, *numbers = re.split(r"\s{2,}", line.strip())
        computed, reference, rel, tol = (float(v) for v in numbers[:4])
        rows[(scene, quantity)] = (computed, reference, rel, tol)
    return rows


def test_tour_passes(tour):
    code, out, _ = tour
    assert code == 0, out
    assert "all checks passed" in out
    assert "FAIL" not in out
    rows = _rows(out)
    scenes = {scene for scene, _ in rows}
    assert set(SCENES) <= scenes
    assert "cylinder_volume(b=0.001, l=1000)" in scenes
    assert ("work-precision", "RATTLE order (slope)") in rows
    assert re.search(r"total \d+\.\d s", out)


def test_tour_reads_on_a_newcomer_screen(tour):
    """Every line fits 100 columns; before the first compile the tour says that the
    first run compiles and that later runs reuse the cache; each row that is not a
    scene on its defaults says why it is there."""
    _, out, _ = tour
    lines = out.splitlines()
    assert max(len(line) for line in lines) <= 100
    assert lines[0].startswith("The first run compiles 16 programs")
    start = " ".join(out[: out.index("quantity")].split())
    # The suite turns the compilation cache off (`conftest.py`); with it on:
    assert "The compilation cache is off: every run compiles them." in start
    on = " ".join(cli._first_run(12, pathlib.Path("/cache")).split())
    assert "Later runs read them from the compilation cache (/cache)" in on
    # Each scene's heading says in words what it is.
    for name in SCENES:
        (heading,) = [line for line in lines if line.startswith(f"{name}: ")]
        assert len(heading.split(": ", 1)[1]) > 10
    headings = [line for line in lines if line.startswith("cylinder_volume(b=0.001")]
    assert len(headings) == 2
    for heading in headings:
        assert heading.split(": ", 1)[1].startswith("badly scaled")
    assert any(
        line.startswith("work-precision: the variational integrator's order")
        for line in lines
    )


def test_rows_are_printed_as_each_scene_finishes(monkeypatch):
    """A job's rows are printed as soon as its program has compiled, before the
    next program's first call ends (one compilation at a time here)."""
    first_call = cli._first_call
    printed_first = []

    def slow_second(program, job):
        if program.name == "cylinder_volume_capped":
            deadline = time.monotonic() + 120
            while "radius a" not in sys.stdout.getvalue():
                if time.monotonic() > deadline:
                    break
                time.sleep(0.01)
            printed_first.append("radius a" in sys.stdout.getvalue())
        return first_call(program, job)

    monkeypatch.setattr(cli, "_first_call", slow_second)
    code, out = _main(["scene", "cylinder_volume", "--no-plots", "--jobs", "1"])
    assert code == 0, out
    assert printed_first == [True]


def test_tour_closed_forms_are_the_lectures(tour):
    """The closed-form column is the lecture's formula (recomputed here), and every
    relative error is within its stated tolerance."""
    _, out, _ = tour
    rows = _rows(out)
    for _, _, rel, tol in rows.values():
        assert rel <= tol
    # Cylinder: a = 2l/(5 pi), h = sqrt(bl/5).
    assert rows[("cylinder_volume", "radius a")][1] == pytest.approx(2 / (5 * math.pi))
    assert rows[("cylinder_volume", "height h")][1] == pytest.approx(math.sqrt(0.2))
    # Two cylinders (theta0 = 0.2, alpha = 0.5): theta* = arccos(2 cos theta0/3.5).
    theta_star = math.acos(2 * math.cos(0.2) / 3.5)
    assert rows[("two_cylinders", "detachment angle")][1] == pytest.approx(theta_star)
    # Pendulum (theta0 = 1): tension at the bottom m g (3 - 2 cos theta0).
    tension = 9.81 * (3 - 2 * math.cos(1.0))
    assert rows[("pendulum", "tension at T/4")][1] == pytest.approx(tension)
    # Dido (a = 1, C = 2.5): lambda = -R with sin(theta)/theta = 2a/C, R = a/sin.
    theta = _bisect(lambda t: math.sin(t) / t - 0.8, 1e-9, math.pi / 2)
    radius = 1 / math.sin(theta)
    assert rows[("dido", "multiplier (-R)")][1] == pytest.approx(-radius)


def _bisect(fn, lo, hi):
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if (fn(mid) > 0) == (fn(lo) > 0):
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def test_tour_writes_its_pictures(tour):
    code, out, out_dir = tour
    for name in PICTURES:
        path = out_dir / name
        assert path.is_file(), out
        data = path.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n"
        # Width and height from the IHDR chunk: the figure's 8 x 5.5 in at 100 dpi.
        width = int.from_bytes(data[16:20], "big")
        height = int.from_bytes(data[20:24], "big")
        assert (width, height) == (800, 550)
        assert len(data) > 20_000  # drawn, not blank
        assert f"picture: {path}" in out
    assert sorted(p.name for p in out_dir.iterdir()) == sorted(PICTURES)


def test_one_scene_with_parameters(cli_runs):
    results, folder = cli_runs
    label = "cylinder_volume(b=2, l=3)"
    code, out = results[label]
    assert code == 0, out
    rows = _rows(out)
    # a = 2l/(5 pi) with l = 3.
    assert rows[(label, "radius a")][1] == pytest.approx(6 / (5 * math.pi))
    # `--no-plots`: not even the default folder for pictures.
    assert not (folder / cli._DEFAULT_OUT).exists()

    label = "two_cylinders(theta0=0.3, alpha=1)"
    code, out = results[label]
    assert code == 0, out
    rows = _rows(out)
    theta_star = math.acos(2 * math.cos(0.3) / 4)
    assert rows[(label, "detachment angle")][1] == pytest.approx(theta_star)
    assert (folder / label / "two_cylinders_normal_force.png").stat().st_size > 20_000


@pytest.mark.parametrize(
    "label",
    [
        "pendulum(theta0=0.5, periods=2)",
        "catenary(length=2, yr=0.5)",
        "sphere_geodesic(radius=2)",
    ],
)
def test_more_scenes_with_parameters(cli_runs, label):
    code, out = cli_runs[0][label]
    assert code == 0, out
    assert {scene for scene, _ in _rows(out)} == {label}


def test_help_explains_each_command_and_scene(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--help"])
    assert info.value.code == 0
    text = capsys.readouterr().out
    for word in ("tour", "scene", "list", "tolerance"):
        assert word in text
    with pytest.raises(SystemExit) as info:
        main(["scene", "pendulum", "--help"])
    assert info.value.code == 0
    text = capsys.readouterr().out
    assert "--theta0" in text and "(default 1)" in text
    assert "--no-plots" in text and "--out" in text
    with pytest.raises(SystemExit):
        main(["tour", "--help"])
    # argparse may wrap the line at the hyphen.
    assert "work-precision" in re.sub(r"-\n\s*", "-", capsys.readouterr().out)


def test_list_names_every_scene():
    code, out = _main(["list"])
    assert code == 0
    for name in SCENES:
        assert re.search(rf"^{name}$", out, re.MULTILINE)


def test_unknown_scene_is_an_error():
    with pytest.raises(SystemExit) as info:
        main(["scene", "no_such_scene"])
    assert info.value.code != 0


def test_impossible_parameters_say_why():
    with pytest.raises(SystemExit) as info:
        main(["scene", "catenary", "--length", "0.5", "--no-plots"])
    assert "must exceed the chord" in str(info.value.code)
    with pytest.raises(SystemExit) as info:
        main(["scene", "rotating_hoop", "--omega", "1", "--no-plots"])
    assert "omega^2 > g/rho" in str(info.value.code)


def test_a_failing_check_gives_exit_status_1(monkeypatch):
    from constrained_jax.scenes import cylinder_volume

    closed_form = cylinder_volume.closed_form

    def wrong(b, l):
        ref = dict(closed_form(b, l))
        ref["a"] = ref["a"] * (1 + 1e-6)  # a relative error of 1e-6 > 1e-10
        return ref

    monkeypatch.setattr(cylinder_volume, "closed_form", wrong)
    code, out = _main(["scene", "cylinder_volume", "--no-plots"])
    assert code == 1
    assert "SOME CHECKS FAILED" in out
    (failed,) = [line for line in out.splitlines() if line.endswith("FAIL")]
    assert "radius a" in failed


def test_the_older_code_generator_by_default(tour, cli_runs):
    """A fresh `constrained-jax` process compiles with XLA:CPU's older code generator
    and small loops as one function each (`cjax.settings.use_fast_compilation`,
    `cjax.settings.use_loop_kernels`: the flags in its `XLA_FLAGS`), with the diffrax
    patch, and says so."""
    _, out, _ = tour
    text = " ".join(out.split())
    if importlib.metadata.version("jaxlib") in _code_generator._KNOWN_JAXLIB:
        assert (
            "compiled with XLA:CPU's older code generator and loops up to "
            "1048576 bytes as one function" in text
        )
        assert cli_runs[0]["XLA_FLAGS"] == (
            "--xla_cpu_use_fusion_emitters=false --xla_backend_extra_options"
            "=xla_cpu_small_while_loop_byte_threshold=1048576"
        )
    else:
        assert "compiled with XLA's defaults" in text
    assert "diffrax patched (--diffrax-defaults: unchanged)" in text


def test_xla_defaults_switch(monkeypatch):
    """`--xla-defaults` calls neither `use_fast_compilation` nor `use_loop_kernels`,
    and says what compiles: the user's own settings in `XLA_FLAGS`, if any."""
    from constrained_jax import _code_generator as module

    def fail():
        raise AssertionError("an XLA setting turned on despite --xla-defaults")

    monkeypatch.setattr(module, "use_fast_compilation", fail)
    monkeypatch.setattr(module, "use_loop_kernels", fail)
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=true")
    assert cli._code_generator(True) == "XLA's defaults"
    monkeypatch.setenv(
        "XLA_FLAGS",
        "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=4096",
    )
    assert cli._code_generator(True) == (
        "loops up to 4096 bytes as one function (--xla-defaults: XLA's defaults)"
    )
    assert cli._parser().parse_args(["tour", "--xla-defaults"]).xla_defaults
    assert not cli._parser().parse_args(["tour"]).xla_defaults


def test_nan_never_passes():
    row = tour_entries.Row("s", "q", float("nan"), 1.0, 1e-3)
    assert not row.passed
    row = tour_entries.Row("s", "q (/l)", 1e-9, 0.0, 1e-8, scale=1.0)
    assert row.passed and row.rel_error == pytest.approx(1e-9)


def test_each_scene_is_declared_once_in_its_tour_module():
    """The registry lists every scene in the table's order; a scene's builder takes
    exactly its declared parameters (their defaults are written only in `params`)."""
    assert list(tour_entries.SCENES) == SCENES
    for name, scene in tour_entries.SCENES.items():
        assert scene.name == name
        signature = inspect.signature(scene.build)
        assert list(signature.parameters) == ["label", *scene.params]
        assert all(
            p.default is inspect.Parameter.empty for p in signature.parameters.values()
        )
        assert scene.label({k: p.default for k, p in scene.params.items()}) == name


def test_the_library_does_not_import_the_tour():
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys, constrained_jax; "
            "assert 'constrained_jax.tour' not in sys.modules",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr


def test_without_matplotlib_the_checks_run_and_say_how_to_install(
    tmp_path, monkeypatch
):
    monkeypatch.setattr(cli, "_have_matplotlib", lambda: False)
    code, out = _main(["scene", "cylinder_volume", "--out", str(tmp_path)])
    assert code == 0
    assert "pip install 'constrained_jax[plot]'" in out
    assert "all checks passed" in out
    assert not any(tmp_path.iterdir())


def test_console_script_and_module_entry_point():
    (script,) = [
        ep
        for ep in importlib.metadata.entry_points(group="console_scripts")
        if ep.name == "constrained-jax"
    ]
    assert script.value == "constrained_jax.__main__:main"
    done = subprocess.run(
        [sys.executable, "-m", "constrained_jax", "list"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert "two_cylinders" in done.stdout
