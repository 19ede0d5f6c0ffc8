"""The contact of the friction scenes: a normal row `gap(q, t, args) = 0` held
while it pushes, and Coulomb friction on one tangential row with the coefficients
`args["mu_s"]`, `args["mu_k"]`."""

from .._constraints import Coulomb, Holonomic, Pfaffian, Unilateral


def mu_s(args):
    return args["mu_s"]


def mu_k(args):
    return args["mu_k"]


def rough_contact(gap, tangent_row) -> Unilateral:
    """`Unilateral(Holonomic(gap), gap=gap, restitution=0.0,
    friction=Coulomb(Pfaffian(tangent_row), mu_s, mu_k))`: contacts that close stay
    closed (inelastic)."""
    return Unilateral(
        Holonomic(gap),
        sign=1.0,
        gap=gap,
        restitution=0.0,
        friction=Coulomb(Pfaffian(tangent_row), mu_s=mu_s, mu_k=mu_k),
    )
