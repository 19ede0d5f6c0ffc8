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
    inverse as inverse,
    pendulum as pendulum,
    rolling_disk as rolling_disk,
    rotating_hoop as rotating_hoop,
    sphere_geodesic as sphere_geodesic,
    two_cylinders as two_cylinders,
)
