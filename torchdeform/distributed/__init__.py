"""Beyond one process: parameter sweeps over ranks (``torchdeform sweep``) on ``torch.distributed``.

Launched with ``torchrun`` (gloo on CPU); one process without it.
"""
