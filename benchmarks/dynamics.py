"""Benchmark `constrained_jax` dynamics: accelerations and `simulate`, at matched error.

Two scenes:

- **Cartesian pendulum** (`constrained_jax.scenes.pendulum`): `q = (x, y)`, one
  holonomic constraint `r = l`, `m = 1`, `g = 9.81`, `l = 1`. Released from rest at
  `theta0 = 1.0` and integrated over 10 periods; the reference is the start state
  (after a whole number of periods, computed from the closed-form period, the pendulum
  is back where it started).
- **Two cylinders** (`constrained_jax.scenes.two_cylinders`): `q = (r, theta1,
  theta2)`, the lecture's two Pfaffian rows, `alpha = 0.5`, `a = 0.3`, `R = 1`. Released
  from rest at `theta0 = 0.3` and integrated for 0.8 s (`theta1` reaches 0.90, before
  detachment at 0.99). The reference is the closed form: the attached motion is an
  inverted pendulum, `theta1ddot = k sin(theta1)` with `k = g / ((1 + alpha)(R + a))`,
  so `theta1(t) = pi - 2 arcsin(s sn(K(s^2) - sqrt(k) t | s^2))`, `s = cos(theta0/2)`
  (Jacobi elliptic `sn`), and `theta1dot` follows from energy.

Three measurements:

1. **Accelerations** for a batch of 10,000 random states: the KKT solve that
   `LagrangianSystem` derives by autodiff (`solve_accelerations`, and the checked
   `accelerations`), against hand-written JAX with the KKT system solved by hand in
   closed form, both `jax.jit(jax.vmap(...))`. They are first checked to agree to
   1e-12.
2. **Trajectories**: one trajectory, and a batch of 1,000 (`jax.vmap` over the initial
   angle), with `cjax.simulate(..., solver=diffrax.Tsit5())`, against the same systems
   built with `sympy.physics.mechanics.LagrangesMethod` (constraints as `hol_coneqs` /
   `nonhol_coneqs`, i.e. the full constrained system with multipliers, not reduced
   coordinates), lambdified to NumPy and integrated by `scipy.integrate.solve_ivp`
   (DOP853). Tolerances of both are chosen so that the final-state error is about
   1e-8. SciPy's batch is a Python loop over a subset, extrapolated.
3. **Compile time** of the first `simulate` call (trace + lower, and compile).

Every JAX time is measured after compilation (ahead-of-time `lower().compile()`, one
warm-up call, then the median of several calls, each ended by `block_until_ready`);
compile times are reported separately. Run with `--quick` for a smoke test.

    python benchmarks/dynamics.py [--quick] [--out benchmarks/results]
"""

import argparse
import json
import os
import time

import jax


jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy  # noqa: E402
import scipy.integrate  # noqa: E402
import scipy.special  # noqa: E402
import sympy  # noqa: E402
from _common import (  # noqa: E402
    machine_info,
    time_jax,
    time_jax_interleaved,
    time_loop,
)
from sympy.physics.mechanics import dynamicsymbols, LagrangesMethod  # noqa: E402

import constrained_jax as cjax  # noqa: E402
from constrained_jax.scenes import pendulum as pend, two_cylinders as cyl  # noqa: E402


SEED = 0

PENDULUM_THETA0 = 1.0
PENDULUM_PERIODS = 10
# The batch: release angles uniform in this range, each run for 10 of its own periods.
PENDULUM_BATCH_THETA0 = (0.5, 1.5)
CYLINDERS_THETA0 = 0.3
CYLINDERS_T1 = 0.8
# The batch: release angles uniform in this range (all still attached at t = 0.8 s).
CYLINDERS_BATCH_THETA0 = (0.2, 0.3)

# Tolerances (rtol = atol) chosen by a scan so that the final-state error is ~1e-8.
# The Cartesian pendulum needs much tighter tolerances than its error suggests: 10
# periods of phase error accumulate.
JAX_TOLERANCES = {"pendulum": 1e-11, "cylinders": 1e-8}
SCIPY_TOLERANCES = {"pendulum": 5e-12, "cylinders": 5e-9}
SCIPY_METHOD = "DOP853"
REFERENCE_TOLERANCE = 1e-13


# ---------------------------------------------------------------------------------
# 1. Hand-written accelerations
# ---------------------------------------------------------------------------------


def pendulum_accelerations_by_hand(q, qd, args):
    """The Cartesian pendulum's KKT system solved by hand.

    `M = m 1`, `A = q^T / r` (the gradient of `G = r - l`), acceleration bias
    `Adot qd = (|qd|^2 - (q . qd)^2 / r^2) / r`, applied force `f = (0, -m g)`.
    From `m qdd - A^T lambda = f` and `A qdd = -bias`, with `A A^T = 1`:

        lambda = -m bias - A f = m (g y / r - bias),   qdd = (f + A^T lambda) / m.

    Valid for any state with `r > 0` (also off the constraint manifold).
    """
    m, g = args["m"], args["g"]
    x, y = q[0], q[1]
    r2 = x * x + y * y
    r = jnp.sqrt(r2)
    along = x * qd[0] + y * qd[1]
    bias = (qd[0] * qd[0] + qd[1] * qd[1] - along * along / r2) / r
    lam = m * (g * y / r - bias)
    qdd = jnp.stack([lam * x / (m * r), lam * y / (m * r) - g])
    return qdd, lam[None]


def cylinders_accelerations_by_hand(q, qd, args):
    """The two cylinders' KKT system solved by hand.

    `M = diag(M, M r^2, I)`, `Q - c = (M r theta1dot^2 - M g cos theta1,
    M g r sin theta1 - 2 M r rdot theta1dot, 0)`, constant rows `(1, 0, 0)` and
    `(0, R + a, -a)` (no bias). The first row gives `rddot = 0` and
    `lambda_1 = M g cos theta1 - M r theta1dot^2`; the second
    `theta2ddot = (1 + R/a) theta1ddot`; the third `lambda_2 = -I theta2ddot / a`, and
    then

        theta1ddot = (M g r sin theta1 - 2 M r rdot theta1dot)
                     / (M r^2 + I (R + a)^2 / a^2).

    In the attached phase (`r = R + a`, `rdot = 0`) these are the lecture's
    `theta1ddot = g sin theta1 / ((1 + alpha)(R + a))`,
    `lambda_1 = M g cos theta1 - M (R + a) theta1dot^2` (which energy turns into
    `M g ((3 + alpha) cos theta1 - 2 cos theta0) / (1 + alpha)`) and
    `lambda_2 = -(I / a^2)(R + a) theta1ddot`.
    """
    m, inertia, a, big_r, g = args["M"], args["I"], args["a"], args["R"], args["g"]
    r, theta1 = q[0], q[1]
    rd, theta1d = qd[0], qd[1]
    ratio = (big_r + a) / a
    sin, cos = jnp.sin(theta1), jnp.cos(theta1)
    theta1dd = (m * g * r * sin - 2 * m * r * rd * theta1d) / (
        m * r * r + inertia * ratio * ratio
    )
    theta2dd = ratio * theta1dd
    lam1 = m * (g * cos - r * theta1d * theta1d)
    lam2 = -inertia * theta2dd / a
    qdd = jnp.stack([jnp.zeros_like(theta1dd), theta1dd, theta2dd])
    return qdd, jnp.stack([lam1, lam2])


def random_states(scene: str, num: int):
    rng = np.random.default_rng(SEED)
    if scene == "pendulum":
        # Arbitrary states, on and off the circle: r in [0.5, 1.5], any direction.
        radius = rng.uniform(0.5, 1.5, num)
        phi = rng.uniform(-np.pi, np.pi, num)
        q = np.stack([radius * np.sin(phi), -radius * np.cos(phi)], axis=1)
        qd = rng.normal(0.0, 3.0, (num, 2))
        return jnp.asarray(q), jnp.asarray(qd)
    # Attached states (r = R + a, rdot = 0, rolling): where the dynamics lives.
    args = cyl.default_args()
    theta1 = jnp.asarray(rng.uniform(-1.0, 1.0, num))
    theta1d = jnp.asarray(rng.normal(0.0, 2.0, num))
    return jax.vmap(lambda th, thd: cyl.state(th, thd, args))(theta1, theta1d)


def eom_variants(scene: str, t) -> dict:
    """The batched equations of motion of a scene at time `t`, each `(q, qd, args) ->
    (qdd, multipliers)` over a batch of states: autodiff `solve_accelerations`, the
    checked `accelerations`, and the hand-written closed form (also `gpu.py`'s)."""
    system = (pend if scene == "pendulum" else cyl).system()
    by_hand = (
        pendulum_accelerations_by_hand
        if scene == "pendulum"
        else cylinders_accelerations_by_hand
    )
    return {
        "autodiff solve_accelerations": lambda q, qd, args: jax.vmap(
            lambda q_, qd_: system.solve_accelerations(q_, qd_, t, args)[:2]
        )(q, qd),
        "autodiff accelerations (checked)": lambda q, qd, args: jax.vmap(
            lambda q_, qd_: system.accelerations(q_, qd_, t, args)
        )(q, qd),
        "hand-written": lambda q, qd, args: jax.vmap(
            lambda q_, qd_: by_hand(q_, qd_, args)
        )(q, qd),
    }


def accelerations_benchmark(
    scene: str, num: int, repeats: int, block: int = 10
) -> dict:
    """The batched equations of motion, every variant timed in `repeats` rounds of
    `block` calls in a row (`time_jax_interleaved`): each program in its own steady
    state, as a sweep calling it sees it. Called singly in turn, a program's time
    with XLA's threads depends on the program called before it."""
    module = pend if scene == "pendulum" else cyl
    system = module.system()
    system_lu = cjax.LagrangianSystem(
        system.lagrangian,
        system.constraints,
        system.forces,
        saddle_point_solver=cjax.FullKKTLU(),
    )
    args = module.default_args()
    q, qd = random_states(scene, num)
    t = jnp.asarray(0.0)

    variants = {
        **eom_variants(scene, t),
        # Ablation: a pivoted LU of the whole KKT matrix.
        "ablation: FullKKTLU (pivoted LU)": lambda q, qd, args: jax.vmap(
            lambda q_, qd_: system_lu.solve_accelerations(q_, qd_, t, args)[:2]
        )(q, qd),
        # Ablation: only the autodiff part (M, Q - c, A and the bias), no KKT solve.
        "ablation: autodiff M, Q-c, A, bias only": lambda q, qd, args: jax.vmap(
            lambda q_, qd_: system.saddle_point_system(q_, qd_, t, args)
        )(q, qd),
    }
    outputs, rows = time_jax_interleaved(
        variants, q, qd, args, repeats=repeats, block=block
    )
    for row in rows.values():
        row["num_states"] = num
    qdd_ref, lam_ref = outputs["hand-written"]
    agreement = {}
    for name in [*list(variants)[:2], "ablation: FullKKTLU (pivoted LU)"]:
        qdd, lam = outputs[name]
        agreement[name] = {
            "qdd_max_abs_diff": float(jnp.max(jnp.abs(qdd - qdd_ref))),
            "multipliers_max_abs_diff": float(jnp.max(jnp.abs(lam - lam_ref))),
            "qdd_max_rel_diff": float(
                jnp.max(jnp.abs(qdd - qdd_ref) / (1 + jnp.abs(qdd_ref)))
            ),
            "multipliers_max_rel_diff": float(
                jnp.max(jnp.abs(lam - lam_ref) / (1 + jnp.abs(lam_ref)))
            ),
        }
        worst = max(
            agreement[name]["qdd_max_rel_diff"],
            agreement[name]["multipliers_max_rel_diff"],
        )
        if worst > 1e-12:
            raise AssertionError(
                f"{scene}: {name} disagrees with the hand-written accelerations "
                f"({worst:.2e} > 1e-12)"
            )
    if scene == "cylinders":
        # The hand-written formulas against the scene's closed forms (attached phase).
        theta1 = q[:, 1]
        agreement["hand-written vs scene closed forms"] = {
            "theta1ddot_max_abs_diff": float(
                jnp.max(jnp.abs(qdd_ref[:, 1] - cyl.angular_acceleration(theta1, args)))
            ),
            "lambda2_max_abs_diff": float(
                jnp.max(jnp.abs(lam_ref[:, 1] - cyl.no_slip_multiplier(theta1, args)))
            ),
        }
    else:
        # On the circle, the multiplier is minus the tension.
        theta = jnp.linspace(-2.0, 2.0, 101)
        thetadot = jnp.linspace(-3.0, 3.0, 101)
        qc, qdc = jax.vmap(lambda th, thd: pend.state(th, thd, args))(theta, thetadot)
        _, lam_c = jax.vmap(lambda a, b: pendulum_accelerations_by_hand(a, b, args))(
            qc, qdc
        )
        agreement["hand-written vs -tension (on the circle)"] = {
            "multiplier_max_abs_diff": float(
                jnp.max(jnp.abs(lam_c[:, 0] + pend.tension(theta, thetadot, args)))
            )
        }
    hand = rows["hand-written"]["median_s"]
    for row in rows.values():
        row["ratio_to_hand_written"] = row["median_s"] / hand
    return {"num_states": num, "methods": rows, "agreement": agreement}


# ---------------------------------------------------------------------------------
# 2. Trajectories: references
# ---------------------------------------------------------------------------------


def cylinders_theta1(theta0, t, args):
    """`(theta1, theta1dot)` of the attached motion released from rest, closed form."""
    theta0 = np.asarray(theta0, float)
    k = float(cyl.angular_acceleration(jnp.pi / 2, args))  # g / ((1 + alpha)(R + a))
    m = np.cos(theta0 / 2) ** 2
    sn, _, _, _ = scipy.special.ellipj(scipy.special.ellipk(m) - np.sqrt(k) * t, m)
    theta1 = np.pi - 2 * np.arcsin(np.sqrt(m) * sn)
    theta1d = np.sqrt(np.asarray(cyl.angular_velocity_squared(theta1, theta0, args)))
    return theta1, theta1d


def cylinders_reference(theta0, t, args):
    theta1, theta1d = cylinders_theta1(theta0, t, args)
    q, qd = jax.vmap(lambda a, b: cyl.state(a, b, args))(
        jnp.atleast_1d(theta1), jnp.atleast_1d(theta1d)
    )
    return np.asarray(q), np.asarray(qd)


def cylinders_reference_check(theta0, t, args) -> float:
    """The closed form against a tight DOP853 run of `theta1ddot = k sin theta1`."""
    k = float(cyl.angular_acceleration(jnp.pi / 2, args))
    sol = scipy.integrate.solve_ivp(
        lambda _, s: np.array([s[1], k * np.sin(s[0])]),
        (0.0, t),
        np.array([theta0, 0.0]),
        method="DOP853",
        rtol=REFERENCE_TOLERANCE,
        atol=REFERENCE_TOLERANCE,
    )
    theta1, theta1d = cylinders_theta1(theta0, t, args)
    return float(max(abs(sol.y[0, -1] - theta1), abs(sol.y[1, -1] - theta1d)))


def state_error(q, qd, q_ref, qd_ref) -> np.ndarray:
    """Max abs error over the final state `(q, qdot)`, per trajectory."""
    q, qd = np.atleast_2d(q), np.atleast_2d(qd)
    q_ref, qd_ref = np.atleast_2d(q_ref), np.atleast_2d(qd_ref)
    return np.maximum(
        np.max(np.abs(q - q_ref), axis=1), np.max(np.abs(qd - qd_ref), axis=1)
    )


# ---------------------------------------------------------------------------------
# 2. Trajectories: constrained_jax
# ---------------------------------------------------------------------------------


def _final_state(scene: str, tol: float):
    module = pend if scene == "pendulum" else cyl
    system = module.system()
    saveat = cjax.SaveAt(t1=True, multipliers=False, energy=False, violation=False)
    controller = diffrax.PIDController(rtol=tol, atol=tol)

    def final_state(theta0, args):
        q0, qd0 = module.state(theta0, jnp.zeros_like(theta0), args)
        if scene == "pendulum":
            t1 = PENDULUM_PERIODS * pend.period(theta0, args)
        else:
            t1 = CYLINDERS_T1
        traj = cjax.simulate(
            system,
            (0.0, t1),
            q0,
            qd0,
            args,
            solver=diffrax.Tsit5(),
            stepsize_controller=controller,
            saveat=saveat,
        )
        return traj.q[-1], traj.qd[-1], traj.stats["num_steps"]

    return final_state


def _final_state_by_hand(scene: str, tol: float):
    """Ablation: `diffrax.diffeqsolve` on the hand-written accelerations, same solver,
    controller and time span as `_final_state` (no constraint checks, no
    `constrained_jax`)."""
    module = pend if scene == "pendulum" else cyl
    by_hand = (
        pendulum_accelerations_by_hand
        if scene == "pendulum"
        else cylinders_accelerations_by_hand
    )
    term = diffrax.ODETerm(lambda t, y, args: (y[1], by_hand(y[0], y[1], args)[0]))
    controller = diffrax.PIDController(rtol=tol, atol=tol)

    def final_state(theta0, args):
        q0, qd0 = module.state(theta0, jnp.zeros_like(theta0), args)
        if scene == "pendulum":
            t1 = PENDULUM_PERIODS * pend.period(theta0, args)
        else:
            t1 = jnp.asarray(CYLINDERS_T1, float)
        sol = diffrax.diffeqsolve(
            term,
            diffrax.Tsit5(),
            jnp.asarray(0.0, float),
            t1,
            None,
            (q0, qd0),
            args,
            saveat=diffrax.SaveAt(t1=True),
            stepsize_controller=controller,
            max_steps=16384,
        )
        return sol.ys[0][-1], sol.ys[1][-1], sol.stats["num_steps"]

    return final_state


def references(scene: str, theta0: np.ndarray):
    if scene == "pendulum":
        args = pend.default_args()
        q, qd = jax.vmap(lambda th: pend.state(th, jnp.zeros_like(th), args))(
            jnp.asarray(theta0)
        )
        return np.asarray(q), np.asarray(qd)
    return cylinders_reference(theta0, CYLINDERS_T1, cyl.default_args())


def jax_trajectories(scene: str, theta0, repeats: int, by_hand=False) -> dict:
    args = (pend if scene == "pendulum" else cyl).default_args()
    tol = JAX_TOLERANCES[scene]
    final_state = (_final_state_by_hand if by_hand else _final_state)(scene, tol)
    batched = np.ndim(theta0) > 0
    fn = jax.vmap(final_state, in_axes=(0, None)) if batched else final_state
    (q, qd, steps), info = time_jax(fn, jnp.asarray(theta0), args, repeats=repeats)
    q_ref, qd_ref = references(scene, np.atleast_1d(theta0))
    errors = state_error(q, qd, q_ref, qd_ref)
    steps = np.atleast_1d(np.asarray(steps))
    num = int(np.size(theta0))
    info.update(
        method=(
            f"ablation: diffrax Tsit5 on hand-written accelerations, rtol=atol={tol:g}"
            if by_hand
            else f"cjax simulate, Tsit5, rtol=atol={tol:g}"
        ),
        num_trajectories=num,
        num_timed=num,
        max_error=float(errors.max()),
        median_error=float(np.median(errors)),
        steps={"median": float(np.median(steps)), "max": int(steps.max())},
        per_trajectory_s=info["median_s"] / num,
    )
    return info


# ---------------------------------------------------------------------------------
# 2. Trajectories: SymPy + SciPy
# ---------------------------------------------------------------------------------


def sympy_pendulum():
    """`LagrangesMethod` with the holonomic constraint `sqrt(x^2 + y^2) - l = 0`."""
    x, y = dynamicsymbols("x y")
    xd, yd = dynamicsymbols("x y", 1)
    m, g, l = sympy.symbols("m g l")
    lagrangian = m * (xd**2 + yd**2) / 2 - m * g * y
    method = LagrangesMethod(
        lagrangian, [x, y], hol_coneqs=[sympy.sqrt(x**2 + y**2) - l]
    )
    method.form_lagranges_equations()
    return method, [x, y, xd, yd], [m, g, l]


def sympy_cylinders():
    """`LagrangesMethod` with the nonholonomic constraints `rdot = 0`,
    `(R + a) theta1dot - a theta2dot = 0` (the lecture's Pfaffian rows)."""
    r, th1, th2 = dynamicsymbols("r theta1 theta2")
    rd, th1d, th2d = dynamicsymbols("r theta1 theta2", 1)
    m, inertia, a, big_r, g = sympy.symbols("M I a R g")
    lagrangian = (
        m * (rd**2 + r**2 * th1d**2) / 2
        + inertia * th2d**2 / 2
        - m * g * r * sympy.cos(th1)
    )
    method = LagrangesMethod(
        lagrangian,
        [r, th1, th2],
        nonhol_coneqs=[rd, (big_r + a) * th1d - a * th2d],
    )
    method.form_lagranges_equations()
    return method, [r, th1, th2, rd, th1d, th2d], [m, inertia, a, big_r, g]


def scipy_rhs(scene: str):
    """The lambdified `mass_matrix_full \\ forcing_full` right-hand side.

    `mass_matrix_full` is the `(2n + k)`-square matrix of `qdot = u`, the Lagrange
    equations with multipliers, and the constraints at acceleration level; its solve
    gives `(qdot, qddot, lambda)`, of which the first `2n` are the ODE's right-hand
    side.
    """
    start = time.perf_counter()
    if scene == "pendulum":
        method, states, params = sympy_pendulum()
        args = pend.default_args()
        values = [float(args[k]) for k in ("m", "g", "l")]
    else:
        method, states, params = sympy_cylinders()
        args = cyl.default_args()
        values = [float(args[k]) for k in ("M", "I", "a", "R", "g")]
    mass = sympy.lambdify((states, params), method.mass_matrix_full, "numpy", cse=True)
    forcing = sympy.lambdify((states, params), method.forcing_full, "numpy", cse=True)
    build_s = time.perf_counter() - start
    n2 = len(states)

    def rhs(_, s):
        return np.linalg.solve(mass(s, values), forcing(s, values))[:n2, 0]

    return rhs, build_s, method.mass_matrix_full.shape[0]


def scipy_trajectory(rhs, scene: str, theta0: float, tol: float):
    if scene == "pendulum":
        args = pend.default_args()
        q0, qd0 = pend.state(theta0, 0.0, args)
        t1 = PENDULUM_PERIODS * float(pend.period(theta0, args))
    else:
        args = cyl.default_args()
        q0, qd0 = cyl.state(jnp.asarray(theta0), jnp.asarray(0.0), args)
        t1 = CYLINDERS_T1
    s0 = np.concatenate([np.asarray(q0), np.asarray(qd0)])
    sol = scipy.integrate.solve_ivp(
        rhs, (0.0, t1), s0, method=SCIPY_METHOD, rtol=tol, atol=tol
    )
    return sol.y[:, -1], sol.nfev, sol.success


def scipy_trajectories(scene: str, theta0, num_total: int, repeats: int) -> dict:
    rhs, build_s, kkt_size = scipy_rhs(scene)
    tol = SCIPY_TOLERANCES[scene]
    theta0 = np.atleast_1d(theta0)
    # Warm-up (the first call of the lambdified functions is slow).
    scipy_trajectory(rhs, scene, float(theta0[0]), tol)
    results, median, times = time_loop(
        lambda th: scipy_trajectory(rhs, scene, float(th), tol), theta0, repeats
    )
    final = np.stack([r[0] for r in results])
    n = final.shape[1] // 2
    q_ref, qd_ref = references(scene, theta0)
    errors = state_error(final[:, :n], final[:, n:], q_ref, qd_ref)
    nfev = np.array([r[1] for r in results])
    per = median / len(theta0)
    return {
        "method": f"sympy LagrangesMethod + scipy {SCIPY_METHOD}, rtol=atol={tol:g}",
        "num_trajectories": num_total,
        "num_timed": len(theta0),
        "median_s": per * num_total,
        "measured_s": median,
        "times_s": times,
        "extrapolated": len(theta0) != num_total,
        "per_trajectory_s": per,
        "max_error": float(errors.max()),
        "median_error": float(np.median(errors)),
        "nfev": {"median": float(np.median(nfev)), "max": int(nfev.max())},
        "all_successful": bool(all(r[2] for r in results)),
        "sympy_build_and_lambdify_s": build_s,
        "kkt_matrix_size": kkt_size,
    }


def batch_theta0(scene: str, num: int) -> np.ndarray:
    rng = np.random.default_rng(SEED)
    low, high = PENDULUM_BATCH_THETA0 if scene == "pendulum" else CYLINDERS_BATCH_THETA0
    return rng.uniform(low, high, num)


def trajectory_benchmark(scene: str, sizes: dict) -> dict:
    theta0 = PENDULUM_THETA0 if scene == "pendulum" else CYLINDERS_THETA0
    print(f"\n== {scene}: one trajectory ==")
    one = {
        "cjax": jax_trajectories(scene, np.float64(theta0), sizes["repeats_one"]),
        "scipy": scipy_trajectories(scene, theta0, 1, sizes["scipy_repeats_one"]),
    }
    one["hand-written diffrax"] = jax_trajectories(
        scene, np.float64(theta0), sizes["repeats_one"], by_hand=True
    )
    one["speedup"] = one["scipy"]["median_s"] / one["cjax"]["median_s"]
    thetas = batch_theta0(scene, sizes["batch"])
    print(f"== {scene}: batch of {sizes['batch']} ==")
    batch = {
        "cjax": jax_trajectories(scene, thetas, sizes["repeats_batch"]),
        "scipy": scipy_trajectories(
            scene, thetas[: sizes["scipy_batch"]], sizes["batch"], 1
        ),
        "hand-written diffrax": jax_trajectories(
            scene, thetas, sizes["repeats_batch"], by_hand=True
        ),
    }
    batch["speedup"] = batch["scipy"]["median_s"] / batch["cjax"]["median_s"]
    for label, block in (("one", one), (f"batch {sizes['batch']}", batch)):
        for name in ("cjax", "scipy", "hand-written diffrax"):
            row = block[name]
            print(
                f"{scene:9s} {label:10s} {row['method']:72s} {row['median_s']:9.4g} s"
                f"  max err {row['max_error']:.2e}"
            )
        print(f"{'':20s} speed-up of cjax: {block['speedup']:.3g}x")
    c = one["cjax"]
    print(
        f"first simulate call: trace+lower {c['trace_lower_s']:.2f} s, compile "
        f"{c['compile_s']:.2f} s, first call {c['first_call_s']:.2f} s"
    )
    return {"theta0": theta0, "one": one, "batch": batch}


# ---------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------


def plot(results: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(18, 6))
    scenes = ("pendulum", "cylinders")

    # Accelerations.
    ax = axes[0]
    names = list(results["accelerations"]["pendulum"]["methods"])
    width = 0.8 / len(names)
    short = {
        "autodiff solve_accelerations": "autodiff solve_accelerations",
        "autodiff accelerations (checked)": "autodiff accelerations (checked)",
        "hand-written": "hand-written",
        "ablation: FullKKTLU (pivoted LU)": "FullKKTLU\n(pivoted LU)",
        "ablation: autodiff M, Q-c, A, bias only": "autodiff assembly\n(no solve)",
    }
    for i, name in enumerate(names):
        values = [
            results["accelerations"][s]["methods"][name]["median_s"] * 1e3
            for s in scenes
        ]
        bars = ax.bar(
            np.arange(2) + (i - (len(names) - 1) / 2) * width,
            values,
            width,
            label=short[name],
        )
        for bar, s in zip(bars, scenes, strict=True):
            ratio = results["accelerations"][s]["methods"][name][
                "ratio_to_hand_written"
            ]
            ax.annotate(
                f"{bar.get_height():.2g} ms\n{ratio:.2g}x",
                (bar.get_x() + bar.get_width() / 2, bar.get_height()),
                ha="center",
                va="bottom",
                fontsize=7,
            )
    ax.set_xticks(
        range(2), ["Cartesian pendulum\n(3x3 KKT)", "two cylinders\n(5x5 KKT)"]
    )
    ax.set_ylabel("ms per batch (after compilation)")
    num = results["accelerations"]["pendulum"]["num_states"]
    ax.set_title(f"Accelerations, jit(vmap) over {num:,} states")
    ax.legend(fontsize=7)
    ax.set_ylim(top=ax.get_ylim()[1] * 1.25)

    # Trajectories.
    for ax, which in zip(axes[1:], ("one", "batch"), strict=True):
        labels, values, colors, notes = [], [], [], []
        for s in scenes:
            block = results["trajectories"][s][which]
            for name, label, color in (
                ("cjax", "cjax\nsimulate", "C0"),
                ("hand-written diffrax", "diffrax,\nby hand", "C2"),
                ("scipy", "sympy +\nDOP853", "C3"),
            ):
                row = block[name]
                labels.append(f"{s}\n{label}")
                values.append(row["median_s"])
                colors.append(color)
                extra = " (extrap.)" if row.get("extrapolated") else ""
                notes.append(
                    f"{row['median_s']:.3g} s{extra}\nerr {row['max_error']:.1e}"
                )
        bars = ax.bar(range(len(values)), values, color=colors)
        ax.set_yscale("log")
        ax.set_xticks(range(len(values)), labels, fontsize=7)
        for bar, note in zip(bars, notes, strict=True):
            ax.annotate(
                note,
                (bar.get_x() + bar.get_width() / 2, bar.get_height()),
                ha="center",
                va="bottom",
                fontsize=7,
            )
        ax.set_ylim(top=max(values) * 20)
        ax.set_ylabel("seconds (after compilation)")
        if which == "one":
            ax.set_title("One trajectory (pendulum 10 periods; cylinders 0.8 s)")
        else:
            n = results["trajectories"]["pendulum"]["batch"]["cjax"]["num_trajectories"]
            ax.set_title(f"Batch of {n:,} trajectories (cjax: vmap)")

    fig.suptitle(
        f"constrained_jax dynamics, jax {results['machine']['versions']['jax']}, "
        f"{results['machine']['cpu_count']}-core CPU; err = max abs final-state error "
        "against the closed form",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--quick", action="store_true", help="smaller sizes (smoke test)"
    )
    parser.add_argument("--out", default=os.path.join("benchmarks", "results"))
    opts = parser.parse_args()

    if opts.quick:
        num_states, acc_repeats = 1_000, 3
        sizes = {
            "batch": 100,
            "scipy_batch": 5,
            "repeats_one": 3,
            "scipy_repeats_one": 1,
            "repeats_batch": 1,
        }
    else:
        num_states, acc_repeats = 10_000, 11
        sizes = {
            "batch": 1_000,
            "scipy_batch": 20,
            "repeats_one": 7,
            "scipy_repeats_one": 3,
            "repeats_batch": 3,
        }
    os.makedirs(opts.out, exist_ok=True)
    results = {
        "machine": machine_info(
            diffrax=diffrax.__version__,
            scipy=scipy.__version__,
            sympy=sympy.__version__,
        ),
        "quick": opts.quick,
        "settings": {
            "pendulum": {
                "args": {k: float(v) for k, v in pend.default_args().items()},
                "theta0": PENDULUM_THETA0,
                "periods": PENDULUM_PERIODS,
                "batch_theta0_uniform": PENDULUM_BATCH_THETA0,
                "reference": "start state after 10 closed-form periods",
            },
            "cylinders": {
                "args": {k: float(v) for k, v in cyl.default_args().items()},
                "theta0": CYLINDERS_THETA0,
                "t1": CYLINDERS_T1,
                "batch_theta0_uniform": CYLINDERS_BATCH_THETA0,
                "reference": "closed form (Jacobi sn) for theta1, energy for theta1dot",
            },
            "jax_tolerances": JAX_TOLERANCES,
            "scipy_tolerances": SCIPY_TOLERANCES,
            "scipy_method": SCIPY_METHOD,
            "seed": SEED,
        },
    }
    print(json.dumps(results["machine"], indent=1))

    # 1. Accelerations.
    results["accelerations"] = {}
    for scene in ("pendulum", "cylinders"):
        block = accelerations_benchmark(scene, num_states, acc_repeats)
        results["accelerations"][scene] = block
        print(f"\n== {scene}: accelerations, {num_states} states ==")
        for name, row in block["methods"].items():
            print(
                f"{name:35s} {row['median_s'] * 1e3:8.3f} ms  "
                f"{row['ratio_to_hand_written']:.3g}x hand-written  "
                f"(compile {row['compile_s']:.2f} s)"
            )
        print("agreement:", json.dumps(block["agreement"]))

    # The closed form for the cylinders, checked against a tight integration.
    cyl_args = cyl.default_args()
    results["settings"]["cylinders"]["closed_form_vs_tight_dop853"] = max(
        cylinders_reference_check(th, CYLINDERS_T1, cyl_args)
        for th in (CYLINDERS_BATCH_THETA0[0], CYLINDERS_THETA0)
    )
    theta_end, _ = cylinders_theta1(CYLINDERS_BATCH_THETA0[1], CYLINDERS_T1, cyl_args)
    results["settings"]["cylinders"]["theta1_at_t1_max"] = float(theta_end)
    results["settings"]["cylinders"]["detachment_angle_min"] = float(
        cyl.detachment_angle(CYLINDERS_BATCH_THETA0[1], cyl_args)
    )

    # 2-3. Trajectories and compile time.
    results["trajectories"] = {
        scene: trajectory_benchmark(scene, sizes) for scene in ("pendulum", "cylinders")
    }

    json_path = os.path.join(opts.out, "dynamics.json")
    with open(json_path, "w") as f:
        json.dump(results, f, indent=1)
    png_path = os.path.join(opts.out, "dynamics.png")
    plot(results, png_path)
    print(f"\nwrote {json_path} and {png_path}")


if __name__ == "__main__":
    main()
