"""Built-in scenes: each module holds one problem from the lecture, as the lecture
writes it (the function or Lagrangian, the constraints, the closed-form answer), and a
`solve(...)` that runs it with the library.
"""

from . import (
    bouncing_ball as bouncing_ball,
    catenary as catenary,
    chain as chain,
    cylinder_volume as cylinder_volume,
    dido as dido,
    incline_block as incline_block,
    inverse as inverse,
    painleve_rod as painleve_rod,
    pendulum as pendulum,
    rolling_disk as rolling_disk,
    rotating_hoop as rotating_hoop,
    sliding_disk as sliding_disk,
    sphere_geodesic as sphere_geodesic,
    two_cylinders as two_cylinders,
    two_cylinders_friction as two_cylinders_friction,
)
