"""fit(): an optax loop for inverse problems.

(Being written: see issue 6.)
"""


class FitResult:
    pass


def fit(loss, params0, *, optimizer=None, steps=1000, args=None, progress=True):
    raise NotImplementedError("cjax.fit is being written (issue 6)")
