"""The tour: every built-in scene solved and checked against its closed form, with
its pictures (`python -m constrained_jax tour`).

One module per scene declares it once (`SCENE`: its parameters with their defaults,
its compiled programs, its checks and pictures); this registry lists them in the
order of the table. Adding a scene: write `tour/<name>.py` with its `SCENE` and add
it to `SCENES` below. The library never imports the tour.
"""

from dataclasses import replace

from . import (
    bouncing_ball,
    catenary,
    cylinder_volume,
    dido,
    friction,
    pendulum,
    rolling_disk,
    rotating_hoop,
    sphere_geodesic,
    two_cylinders,
)
from ._entry import (
    Check as Check,
    Job as Job,
    Param as Param,
    Program as Program,
    Row as Row,
    save as save,
    Scene as Scene,
    Table as Table,
    WIDTH as WIDTH,
)
from .work_precision import WorkPrecision as WorkPrecision


SCENES: dict[str, Scene] = {
    module.SCENE.name: module.SCENE
    for module in (
        cylinder_volume,
        pendulum,
        two_cylinders,
        bouncing_ball,
        friction,
        rolling_disk,
        rotating_hoop,
        catenary,
        dido,
        sphere_geodesic,
    )
}


BADLY_SCALED = (
    "badly scaled (a ~ 100 next to h ~ 0.4), to the same tolerance: Newton's "
    "step test does not depend on the scale of the unknowns"
)


def tour_jobs() -> list[Job]:
    """Every scene on its defaults, then the cylinder on a badly scaled budget
    (without its picture; its note says why it is there)."""
    jobs = [job for scene in SCENES.values() for job in scene.jobs()]
    badly_scaled = SCENES["cylinder_volume"].jobs(b=1e-3, l=1e3)
    return jobs + [replace(job, draw=False, note=BADLY_SCALED) for job in badly_scaled]
