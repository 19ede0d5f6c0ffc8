"""Plot helpers (matplotlib, imported lazily: `pip install constrained_jax[plot]`).

(Being written: see issue 6.)
"""
