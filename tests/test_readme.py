"""The README's example runs and says what the README says it says."""

import pathlib
import re

import numpy as np


def test_readme_example():
    readme = pathlib.Path(__file__).parents[1] / "README.md"
    blocks = re.findall(r"```python\n(.*?)```", readme.read_text(), flags=re.S)
    assert blocks, "README.md has no python example"
    namespace: dict = {}
    lines = blocks[0].strip().splitlines()
    exec("\n".join(lines[:-2]), namespace)  # noqa: S102
    sol = namespace["sol"]
    grad = eval(lines[-2].split("#")[0] + lines[-1].split("#")[0], namespace)  # noqa: S307
    a, h = 2 / (5 * np.pi), np.sqrt(1 / 5)
    np.testing.assert_allclose(sol.x, [a, h], rtol=1e-12)
    np.testing.assert_allclose(sol.multipliers, [-a * h], rtol=1e-12)
    np.testing.assert_allclose(grad, a * h, rtol=1e-10)
