"""Process-wide settings, opted into at the top of a script or notebook.

None of them changes a result beyond round-off, and importing `constrained_jax` turns
none of them on. Each is set only where it is known to work: on another jaxlib or
diffrax than the one it was written for, the call warns, returns `False` and leaves
the defaults.

- [`use_fast_compilation`][constrained_jax.settings.use_fast_compilation]:
    XLA:CPU's older code generator (faster compilation, slower programs).
- [`use_loop_kernels`][constrained_jax.settings.use_loop_kernels]: XLA:CPU compiles
    each small `while` loop (one trajectory) into one function (faster single
    trajectories).
- [`use_diffrax_patch`][constrained_jax.settings.use_diffrax_patch]: the library's
    diffrax solves traced with a smaller `t1` floor and, where the library has
    checked the save times, without diffrax's host callbacks (smaller programs that
    JAX's persistent compilation cache stores).

The two XLA settings must come before the first computation (XLA reads its flags
once, when JAX starts its backend); the diffrax patch before the first solve. The
command line `constrained-jax` turns on both XLA settings (`--xla-defaults` keeps
XLA's) and the diffrax patch (`--diffrax-defaults` keeps diffrax unchanged).

```python
import jax
import constrained_jax as cjax

cjax.settings.use_fast_compilation()
cjax.settings.use_loop_kernels()
cjax.enable_compilation_cache()
jax.config.update("jax_enable_x64", True)
```
"""

from ._code_generator import (
    LOOP_KERNEL_BYTES as LOOP_KERNEL_BYTES,
    use_fast_compilation as use_fast_compilation,
    use_loop_kernels as use_loop_kernels,
)
from ._diffrax_integrate import use_diffrax_patch as use_diffrax_patch
from ._misc import publish as _publish


_publish(globals(), __name__)


__all__ = [
    "LOOP_KERNEL_BYTES",
    "use_diffrax_patch",
    "use_fast_compilation",
    "use_loop_kernels",
]
