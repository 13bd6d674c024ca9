"""Beyond one process on ``torch.distributed``: sweeps, data-parallel learning.

Parameter sweeps over ranks (``torchdeform sweep``) and data-parallel learning
(:mod:`.data_parallel`: the windows of a loss shared out over ranks). Launched with ``torchrun``
(gloo on CPU); one process without it.
"""
