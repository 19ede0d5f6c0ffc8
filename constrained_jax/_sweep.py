"""sweep(): chunked jit(vmap(fn)), sharded over local devices, progress, resumable.

(Being written: see issue 6.)
"""


def sweep(fn, inputs, *, batch_size=1024, devices=None, checkpoint=None, progress=True):
    raise NotImplementedError("cjax.sweep is being written (issue 6)")
